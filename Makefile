# torch_rbpt: `make demo` and `make test` set everything up on a fresh machine first.
PYTHON ?= python3
PIP = $(PYTHON) -m pip
SOURCES = $(wildcard csrc/*.h csrc/*.cpp) setup.py

.PHONY: install demo test test-slow bench clean

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

bench: .installed
	$(PYTHON) benchmarks/bench_render.py
	$(PYTHON) benchmarks/bench_gradients.py

clean:
	rm -rf build *.egg-info torch_rbpt/*.so .installed out
