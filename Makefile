# torch_rbpt: `make demo` and `make test` set everything up on a fresh machine first.
PYTHON ?= python3
PIP = $(PYTHON) -m pip
SOURCES = $(wildcard csrc/*.h csrc/*.cpp) setup.py

.PHONY: install demo test test-slow bench fuzz clean

# Install torch (local CPU wheel, pinned so pip never resolves a CUDA build), the other
# dependencies, and build the extension in place. Re-runs when a C++ source changes.
.installed: requirements.txt $(SOURCES)
	$(PIP) install --quiet torch==2.13.0
	$(PIP) install --quiet -r requirements.txt
	$(PIP) install --quiet --no-build-isolation -e .
	@touch .installed

install: .installed

# The main job: recover the red wall's reflectance of the bundled Cornell box from an image.
demo: .installed
	$(PYTHON) examples/fit_material.py

test: .installed
	$(PYTHON) -m pytest -q -m "not slow" tests

test-slow: .installed
	$(PYTHON) -m pytest -q -m slow tests

# Speed against Mitsuba 3 and Embree 3 (each compared in the same run when installed:
# `pip install mitsuba`, `apt-get install libllvm19 libembree-dev`); tables, CSV and plots go
# to benchmarks/results/. The first run renders and caches converged references.
bench: .installed
	$(PYTHON) benchmarks/bench_error_time.py
	$(PYTHON) benchmarks/bench_grad_error.py
	$(PYTHON) benchmarks/bench_tutorial.py
	$(PYTHON) benchmarks/bench_gradients.py
	$(PYTHON) benchmarks/bench_rays.py

# Fuzz each loader (XML, dict, OBJ, PLY, images) for FUZZ_SECONDS seconds, one target at a
# time, starting from fuzz/seeds/<target>; not part of `make test`. New inputs that reach new
# code go to fuzz/corpus/<target>, findings to fuzz/findings/<target>-crash-* (see fuzz/README.md).
FUZZ_SECONDS ?= 60
FUZZ_TARGETS = xml dict obj ply image

fuzz: .installed
	$(PIP) install --quiet -r requirements-fuzz.txt
	@status=0; for t in $(FUZZ_TARGETS); do \
		mkdir -p fuzz/corpus/$$t fuzz/findings; \
		echo "== fuzz_$$t: $(FUZZ_SECONDS) s"; \
		$(PYTHON) fuzz/fuzz_$$t.py fuzz/corpus/$$t fuzz/seeds/$$t -max_total_time=$(FUZZ_SECONDS) \
			-timeout=30 -rss_limit_mb=4096 -artifact_prefix=fuzz/findings/$$t- || status=1; \
	done; exit $$status

clean:
	rm -rf build *.egg-info torch_rbpt/*.so .installed out fuzz/corpus
