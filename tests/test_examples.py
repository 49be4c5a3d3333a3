"""The examples (examples/*.py) run as-is in their smoke settings and leave their outputs."""
import importlib.util

import pytest

from conftest import ROOT


def _load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_fit_material_smoke(tmp_path):
    fit = _load("fit_material")
    rms = fit.main(["--smoke", "--out", str(tmp_path)])
    for name in ("reference", "initial", "final"):
        assert (tmp_path / f"{name}.exr").exists() and (tmp_path / f"{name}.png").exists()
    assert (tmp_path / "comparison.png").exists() and (tmp_path / "convergence.png").exists()
    # Start (0.01, 0.2, 0.9) is 0.55 RMS away from the truth: the fit must move towards it.
    assert rms < 0.3
