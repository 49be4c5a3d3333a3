"""Smoke tests of benchmarks/bench_rays.py: the C++ ray benchmark on a 12-triangle cube (ours
alone, and against Embree 3 when its headers are installed) and the threads/memory parts at
tiny sizes. The numbers are not checked, only that each part runs and agrees with itself."""
import shutil

import pytest

from conftest import load_benchmark

bench_rays = load_benchmark("bench_rays")

needs_gxx = pytest.mark.skipif(shutil.which("g++") is None, reason="g++ not found")


@needs_gxx
def test01_rays_ours_only(capsys):
    out = bench_rays.run_rays(quick=True, use_embree=False, mesh="cube", threads="1", repeats=1)
    assert not out["embree"]
    assert out["triangles"] == 12
    assert {(r["rays"], r["query"]) for r in out["rows"]} == {
        (k, q) for k in ("incoherent", "coherent") for q in ("closest", "any")}
    assert all(r["ours_mrays"] > 0 for r in out["rows"])
    # Any-hit queries agree with closest-hit ones on which rays hit.
    for (name, query, ref), c in out["checks"].items():
        assert ref == "ours_closest" and int(c["mismatches"]) == 0, (name, query)
    assert all(0 < r["hit_fraction"] < 1 for r in out["rows"])
    # A smoke run's ray sets are too small to time: its report judges no target.
    capsys.readouterr()
    bench_rays.report_rays(out, "test machine")
    printed = capsys.readouterr().out
    assert "targets not judged" in printed and "target " not in printed


@needs_gxx
def test02_rays_against_embree():
    if bench_rays.embree_include() is None:
        pytest.skip("Embree 3 headers not found (apt-get install libembree-dev)")
    out = bench_rays.run_rays(quick=True, use_embree=True, mesh="cube", threads="1,2", repeats=1)
    assert out["embree"]
    rows = bench_rays.report_rays(out, "test machine")
    assert all(r["embree1_mrays"] > 0 and r["embree8_mrays"] == r["embree8_mrays"]
               for r in rows if r["query"] == "closest")
    # Same hits as Embree, up to a few rays grazing the cube's edges.
    for r in rows:
        assert r["mismatch_rate"] < 1e-3, r


def test03_threads_and_memory(tmp_path, shared):
    rows = bench_rays.run_threads(quick=True, mach="test machine")
    assert [r["threads"] for r in rows] == [1, 2] and all(r["seconds"] > 0 for r in rows)
    mem = bench_rays.run_memory(quick=True, mach="test machine", res=32, spps=(1, 2), depths=(2,))
    assert len(mem) == 2
    assert all(r["peak_rss_mb"] >= r["baseline_rss_mb"] > 0 and r["grad_finite"] for r in mem)
    bench_rays.write_csv(tmp_path / "threads_memory.csv", rows + mem)
    assert (tmp_path / "threads_memory.csv").read_text().count("\n") == 5
