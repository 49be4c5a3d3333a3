"""The gradient benchmarks (benchmarks/bench_grad_error.py, benchmarks/bench_tutorial.py,
benchmarks/bench_gradients.py) run in small --no-mitsuba settings and write CSV rows with
finite values."""
import csv
import math
from pathlib import Path

from conftest import load_benchmark


def read_csv(path: Path) -> list:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test01_grad_error_quick(tmp_path, shared):
    bench = load_benchmark("bench_grad_error")
    bench.main(["--quick", "--no-mitsuba", "--out", str(tmp_path / "results"),
                "--cache", str(tmp_path / "cache")])
    rows = read_csv(tmp_path / "results" / "grad_error.csv")
    kinds = {r["kind"] for r in rows}
    assert kinds == {"reflectance", "texture", "roughness", "beckmann", "roughplastic"}
    assert len(rows) == 5 * 2  # two spp per kind, ours only
    for r in rows:
        assert r["renderer"] == "torch_rbpt" and r["reference"] == "torch_rbpt"
        for col in ("time_s", "err", "err_corr", "fom", "err2_rse"):
            assert math.isfinite(float(r[col])) and float(r[col]) >= 0, (r["kind"], col, r[col])
        assert float(r["time_s"]) > 0
    for name in ("grad_error.png", "grad_error_reflectance.png", "grad_error_texture.png"):
        assert (tmp_path / "results" / name).exists()
    # The second run reads the cached references.
    assert list((tmp_path / "cache").glob("gradref_*.npz"))


def test02_tutorial_quick(tmp_path, shared):
    bench = load_benchmark("bench_tutorial")
    bench.main(["--quick", "--no-mitsuba", "--out", str(tmp_path)])
    rows = read_csv(tmp_path / "tutorial.csv")
    assert [r["renderer"] for r in rows] == ["torch_rbpt"]
    r = rows[0]
    for col in ("cold_s", "cold_no_ref_s", "warm_ms", "error", "final_loss"):
        assert math.isfinite(float(r[col])) and float(r[col]) >= 0, (col, r[col])
    assert float(r["cold_no_ref_s"]) <= float(r["cold_s"])
    # 12 iterations from (0.01, 0.2, 0.9), 0.55 RMS away from the truth: it must move towards it.
    assert float(r["error"]) < 0.55


def test03_gradients_small(tmp_path, shared):
    bench = load_benchmark("bench_gradients")
    bench.main(["--res", "16", "--spp", "1", "--repeats", "1", "--no-mitsuba", "--out", str(tmp_path)])
    rows = read_csv(tmp_path / "gradients.csv")
    assert [r["differentiated"] for r in rows][0] == "red.reflectance.value" and len(rows) == 2
    for r in rows:
        assert float(r["forward_s"]) > 0 and float(r["backward_s"]) > 0
    rough = read_csv(tmp_path / "roughplastic_alpha.csv")
    assert {(r["distribution"], r["step"], r["renderer"]) for r in rough} == {
        (d, s, "torch_rbpt") for d in ("beckmann", "ggx") for s in ("render", "render + backward")}
    for r in rough:
        assert float(r["same_alpha_ms"]) > 0 and float(r["new_alpha_ms"]) > 0, r
