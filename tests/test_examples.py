"""The examples (examples/*.py) run as-is in their smoke settings and leave their outputs."""


from conftest import load_example




def test_fit_material_smoke(tmp_path):
    fit = load_example("fit_material")
    rms = fit.main(["--smoke", "--out", str(tmp_path)])
    for name in ("reference", "initial", "final"):
        assert (tmp_path / f"{name}.exr").exists() and (tmp_path / f"{name}.png").exists()
    assert (tmp_path / "comparison.png").exists() and (tmp_path / "convergence.png").exists()
    # Start (0.01, 0.2, 0.9) is 0.55 RMS away from the truth: the fit must move towards it.
    assert rms < 0.3
