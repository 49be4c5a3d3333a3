# torch_rbpt: `make demo` and `make test` set everything up on a fresh machine first.
PYTHON ?= python3
PIP = $(PYTHON) -m pip
SOURCES = $(wildcard csrc/*.h csrc/*.cpp) setup.py

# SANITIZE=1 builds the extension (and tests/cpp) with AddressSanitizer and
# UndefinedBehaviorSanitizer and runs the tests with their runtime preloaded into Python.
SANITIZE ?= 0
export SANITIZE
ifeq ($(SANITIZE),1)
MODE = sanitize
# Python is not instrumented: the ASan runtime must be the first library loaded. No leak
# detection in Python processes: CPython, torch and pybind11's function records are never freed
# by design, and LeakSanitizer's exit scan costs over a minute per Python process here; the
# standalone tests/cpp program runs with it on (tests/test_autodiff.py).
SANITIZER_ENV = LD_PRELOAD="$(shell $(CXX) -print-file-name=libasan.so) $(shell $(CXX) -print-file-name=libubsan.so)" \
	ASAN_OPTIONS=detect_leaks=0:halt_on_error=1:detect_odr_violation=0:log_path=$(CURDIR)/out/sanitizer/asan \
	UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
else
MODE = release
SANITIZER_ENV =
endif
# MARCH=<cpu> builds the extension for another CPU than this one (setup.py), e.g. x86-64-v3
# for any AVX2 machine; `make bench-avx2` uses it. MTUNE=<cpu> forces the tuning, which
# setup.py otherwise picks for this machine (torch_rbpt/build_flags.py).
MARCH ?=
export MARCH
MTUNE ?=
export MTUNE
# One stamp per build mode; building one mode removes the other's stamp, so switching rebuilds.
STAMP = .installed-$(MODE)$(if $(MARCH),-$(MARCH))$(if $(MTUNE),-tune-$(MTUNE))

.PHONY: install demo test test-slow bench bench-avx2 soak fuzz clean

# Install torch (local CPU wheel, pinned so pip never resolves a CUDA build), the other
# dependencies, and build the extension in place. Re-runs when a C++ source changes.
$(STAMP): requirements.txt $(SOURCES) torch_rbpt/build_flags.py
	@rm -f .installed .installed-*
	$(PIP) install --quiet torch==2.13.0
	$(PIP) install --quiet -r requirements.txt
	$(PIP) install --quiet --no-build-isolation -e .
	@touch $@

install: $(STAMP)

# The main job: recover the red wall's reflectance of the bundled Cornell box from an image.
demo: $(STAMP)
	$(PYTHON) examples/fit_material.py

# Under SANITIZE=1 a report ends the process that hit it. ASan writes its reports to
# out/sanitizer/ (child processes' too, whose stderr a test may swallow): any file there fails
# the run and is printed. UBSan ignores log_path beside a preloaded ASan and writes to stderr,
# so pytest captures only sys.stderr: its fd-level capture would lose a report with the process.
test: $(STAMP)
ifeq ($(SANITIZE),1)
	@rm -rf out/sanitizer && mkdir -p out/sanitizer
	$(SANITIZER_ENV) $(PYTHON) -m pytest -q --capture=sys -m "not slow" tests; status=$$?; \
	if ls out/sanitizer/* >/dev/null 2>&1; then cat out/sanitizer/*; echo "sanitizer reports in out/sanitizer/"; exit 1; fi; \
	exit $$status
else
	$(PYTHON) -m pytest -q -m "not slow" tests
endif

test-slow: $(STAMP)
	$(PYTHON) -m pytest -q -m slow tests

# Speed against Mitsuba 3 and Embree 3 (each compared in the same run when installed:
# `pip install mitsuba`, `apt-get install libllvm19 libembree-dev`); tables, CSV and plots go
# to benchmarks/results/. The first run renders and caches converged references.
bench: $(STAMP)
	$(PYTHON) benchmarks/bench_error_time.py
	$(PYTHON) benchmarks/bench_grad_error.py
	$(PYTHON) benchmarks/bench_tutorial.py
	$(PYTHON) benchmarks/bench_gradients.py
	$(PYTHON) benchmarks/bench_rays.py
	$(PYTHON) benchmarks/bench_profile.py
	$(PYTHON) benchmarks/bench_variance.py
	$(PYTHON) benchmarks/bench_simd.py
	$(PYTHON) benchmarks/bench_survey.py

# The comparison as on an AVX2-only machine: ours built for x86-64-v3, Mitsuba's kernels
# compiled for Haswell with 8 lanes and its Embree limited to AVX2 (the benchmarks re-run
# themselves with benchmarks/embree_max_isa.cpp preloaded, built with g++); results in
# benchmarks/results/avx2. A later plain `make` rebuilds for this machine.
bench-avx2:
	$(MAKE) MARCH=x86-64-v3 install
	$(PYTHON) benchmarks/bench_error_time.py --mitsuba-isa avx2 --out benchmarks/results/avx2
	$(PYTHON) benchmarks/bench_grad_error.py --mitsuba-isa avx2 --out benchmarks/results/avx2
	$(PYTHON) benchmarks/bench_tutorial.py --mitsuba-isa avx2 --out benchmarks/results/avx2

# Fuzz each loader (XML, dict, OBJ, PLY, images) for FUZZ_SECONDS seconds, one target at a
# time, starting from fuzz/seeds/<target>; not part of `make test`. New inputs that reach new
# code go to fuzz/corpus/<target>, findings to fuzz/findings/<target>-crash-* (see fuzz/README.md).
FUZZ_SECONDS ?= 60
FUZZ_TARGETS = xml dict obj ply image

fuzz: $(STAMP)
	$(PIP) install --quiet -r requirements-fuzz.txt
	@status=0; for t in $(FUZZ_TARGETS); do \
		mkdir -p fuzz/corpus/$$t fuzz/findings; \
		echo "== fuzz_$$t: $(FUZZ_SECONDS) s"; \
		$(PYTHON) fuzz/fuzz_$$t.py fuzz/corpus/$$t fuzz/seeds/$$t -max_total_time=$(FUZZ_SECONDS) \
			-timeout=30 -rss_limit_mb=4096 -artifact_prefix=fuzz/findings/$$t- || status=1; \
	done; exit $$status

# 1000 iterations of the fit_material loop, resident memory sampled: does it stay flat?
soak: $(STAMP)
	$(PYTHON) benchmarks/bench_soak.py

clean:
	rm -rf build *.egg-info torch_rbpt/*.so .installed .installed-* out fuzz/corpus
