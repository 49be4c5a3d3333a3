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
# One stamp per build mode; building one mode removes the other's stamp, so switching rebuilds.
STAMP = .installed-$(MODE)

.PHONY: install demo test test-slow bench soak clean

# Install torch (local CPU wheel, pinned so pip never resolves a CUDA build), the other
# dependencies, and build the extension in place. Re-runs when a C++ source changes.
$(STAMP): requirements.txt $(SOURCES)
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

bench: $(STAMP)
	$(PYTHON) benchmarks/bench_render.py
	$(PYTHON) benchmarks/bench_gradients.py

# 1000 iterations of the fit_material loop, resident memory sampled: does it stay flat?
soak: $(STAMP)
	$(PYTHON) benchmarks/bench_soak.py

clean:
	rm -rf build *.egg-info torch_rbpt/*.so .installed .installed-* out
