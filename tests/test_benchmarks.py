"""The benchmarks run in their smoke settings (ours only, no Mitsuba needed; test08 checks
mitsuba_ref where Mitsuba is installed)."""
import csv
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, SHARED, load_benchmark, uninstrumented_env


@pytest.mark.skipif(not (SHARED / "cbox" / "cbox.xml").exists(), reason="shared scenes not present")
def test01_error_time_quick(tmp_path):
    bench = load_benchmark("bench_error_time")
    results = bench.main(["--quick", "--scenes", "cbox", "--no-mitsuba",
                          "--out", str(tmp_path / "results"), "--cache", str(tmp_path / "cache")])
    assert [sc["name"] for sc in results] == ["cbox"]
    with open(tmp_path / "results" / "error_time.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["scene"], r["renderer"], int(r["spp"])) for r in rows] == [
        ("cbox", "torch_rbpt", 4), ("cbox", "torch_rbpt", 16)]
    for r in rows:
        assert (int(r["width"]), int(r["height"])) == (64, 64)
        for key in ("seconds", "rmse", "rel_error", "mrays_per_s"):
            v = float(r[key])
            assert math.isfinite(v) and v > 0, (key, r[key])
        assert r["cpu"] and int(r["cores"]) >= 1 and r["date"]
        assert r["reference"] == "cbox_64x64_256spp_ours_sums.exr"
    # 4x the samples: the error drops (by about 2x)
    assert float(rows[1]["rmse"]) < 0.8 * float(rows[0]["rmse"])
    assert (tmp_path / "cache" / "cbox_64x64_256spp_ours_sums.exr").exists()
    assert (tmp_path / "results" / "error_time_cbox.png").exists()
    assert (tmp_path / "results" / "error_time.png").exists()


def test02_time_at_error():
    bench = load_benchmark("bench_error_time")
    curve = [(1.0, 0.4), (4.0, 0.2), (16.0, 0.1)]
    t, ext = bench.time_at_error(curve, 0.2)
    assert t == pytest.approx(4.0) and not ext
    t, ext = bench.time_at_error(curve, 0.4 / math.sqrt(2))  # halfway in log-log
    assert t == pytest.approx(2.0) and not ext
    t, ext = bench.time_at_error(curve, 0.05)  # beyond: error ~ time^-1/2
    assert t == pytest.approx(64.0) and ext
    t, ext = bench.time_at_error(curve, 0.8)
    assert t == pytest.approx(0.25) and ext


@pytest.mark.skipif(not (SHARED / "cbox" / "cbox.xml").exists(), reason="shared scenes not present")
def test03_variance_split_by_path_length(tmp_path):
    bench = load_benchmark("bench_variance")
    (r,) = bench.main(["--scenes", "cbox", "--res", "32", "--spp", "16", "--out", str(tmp_path)])
    assert r["variance"] > 0 and (r["width"], r["height"]) == (32, 32)
    assert r["emitters_seen"] + r["direct"] + r["longer"] == pytest.approx(1.0)
    # The cbox's mirror and glass spheres and diffuse walls: every length matters (a render
    # that ignored max_depth would put everything in the first share).
    assert 0.1 < r["emitters_seen"] < 0.8 and r["longer"] > 0.15
    assert (tmp_path / "variance.csv").exists()


def test04_simd_stages_vectorise_bitwise(tmp_path):
    # The shading stages run as one path at a time and as a loop GCC vectorises give the same
    # bits with setup.py's flags (the premise of running paths in SIMD lanes without changing
    # images), at every vector width this CPU runs.
    bench = load_benchmark("bench_simd")
    rows = bench.main(["--quick", "--out", str(tmp_path)])
    builds = sorted({r["isa"] for r in rows})
    assert "native" in builds and "portable" in builds
    assert [r["stage"] for r in rows] == ["camera", "interaction", "vertex"] * len(builds)
    for r in rows:
        assert r["bitwise_equal"] == 1, r
        assert math.isfinite(r["speedup"]) and r["scalar_ns"] > 0 and r["simd_ns"] > 0
    with open(tmp_path / "simd_stages.csv") as f:
        assert len(list(csv.DictReader(f))) == len(rows)


def test05_csv_at_a_relative_path(tmp_path, monkeypatch, capsys):
    # `make bench-avx2` passes --out benchmarks/results/avx2, relative to the checkout
    machine = load_benchmark("machine")
    monkeypatch.chdir(tmp_path)
    relative = Path("results") / "avx2" / "x.csv"
    machine.write_csv(relative, [{"scene": "cbox", "seconds": 1.5}, {"scene": "glossy", "rmse": 0.25}])
    with open(tmp_path / relative) as f:
        rows = list(csv.DictReader(f))
    assert rows == [{"scene": "cbox", "seconds": "1.5", "rmse": ""},
                    {"scene": "glossy", "seconds": "", "rmse": "0.25"}]
    assert f"wrote {tmp_path / relative}" in capsys.readouterr().out  # outside the checkout
    assert machine.shown(relative, root=tmp_path) == relative  # inside it
    assert machine.shown(tmp_path / relative, root=tmp_path) == relative


def test06_sweep_turns(tmp_path):
    # Each renderer's turn is an untimed render and then the timed one: the time is the best of
    # the timed renders alone (a render right after the other renderer's is slowed by its
    # lingering threads and caches), the error the mean over both.
    import torch
    bench = load_benchmark("bench_error_time")
    ref = torch.zeros(2, 2, 3)
    log = []

    class Fake:
        def __init__(self, name, scale):
            self.name, self.scale = name, scale

        def warm(self, spp):
            log.append((self.name, "warm", spp))

        def timed(self, spp, seed):
            log.append((self.name, seed))
            # Untimed seeds (>= repeats) report a time no timed render reaches.
            dt = 0.001 if seed >= 2 else self.scale * spp * (1 + seed)
            return torch.full((2, 2, 3), float(seed + 1)), dt, 7

    rs = [Fake("ours", 1.0), Fake("Mitsuba", 2.0)]
    out = bench.sweep(rs, [4], 2, ref)
    assert log == [("ours", "warm", 4), ("Mitsuba", "warm", 4),
                   ("ours", 2), ("ours", 0), ("Mitsuba", 2), ("Mitsuba", 0),
                   ("ours", 3), ("ours", 1), ("Mitsuba", 3), ("Mitsuba", 1)]
    rows, mean = out["ours"]
    assert rows[0]["seconds"] == pytest.approx(4.0)          # the best timed render
    assert rows[0]["rmse"] == pytest.approx((3 + 1 + 4 + 2) / 4)  # images of seeds 2, 0, 3, 1
    assert out["Mitsuba"][0][0]["seconds"] == pytest.approx(8.0)
    assert torch.allclose(mean, torch.full((2, 2, 3), 2.5))


@pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")
def test07_embree_limit_appends_max_isa(tmp_path):
    # The AVX2 setting limits Mitsuba's Embree to AVX2 through a preloaded library
    # (benchmarks/embree_max_isa.cpp) that puts itself in front of mitsuba::rtcNewDevice and
    # passes Mitsuba's configuration on with max_isa appended. Here in front of a stand-in
    # for Mitsuba's Embree, called as libmitsuba.so calls it (an imported symbol): the stand-in
    # must receive the appended configuration, and the report must hold it.
    fake = tmp_path / "libfake_embree.so"
    (tmp_path / "fake.cpp").write_text(
        '#include <cstdio>\n'
        'namespace mitsuba { struct RTCDeviceTy; RTCDeviceTy *rtcNewDevice(const char *c) {'
        ' std::printf("device %s\\n", c); return nullptr; } }\n')
    (tmp_path / "main.cpp").write_text(
        '#include <cstdio>\n#include <cstdlib>\n'
        'namespace mitsuba { struct RTCDeviceTy; RTCDeviceTy *rtcNewDevice(const char *c); }\n'
        'int main() { mitsuba::rtcNewDevice("threads=2,user_threads=2");'
        ' std::printf("report %s\\n", std::getenv("RBPT_EMBREE_CONFIG")); }\n')
    shim = tmp_path / "shim.so"
    for cmd in (["g++", "-shared", "-fPIC", str(tmp_path / "fake.cpp"), "-o", str(fake)],
                ["g++", str(tmp_path / "main.cpp"), str(fake), f"-Wl,-rpath,{tmp_path}", "-o", str(tmp_path / "main")],
                ["g++", "-O2", "-shared", "-fPIC", str(ROOT / "benchmarks" / "embree_max_isa.cpp"), "-o", str(shim), "-ldl"]):
        build = subprocess.run(cmd, capture_output=True, text=True, env=uninstrumented_env())
        assert build.returncode == 0, build.stderr[-2000:]
    env = dict(uninstrumented_env(), LD_PRELOAD=str(shim), RBPT_EMBREE_LIB=str(fake), RBPT_EMBREE_MAX_ISA="avx2")
    run = subprocess.run([str(tmp_path / "main")], capture_output=True, text=True, env=env)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split("\n")[:2] == ["device threads=2,user_threads=2,max_isa=avx2",
                                          "report threads=2,user_threads=2,max_isa=avx2"]
    # Without the stand-in's path it stops with a message rather than running unlimited.
    run = subprocess.run([str(tmp_path / "main")], capture_output=True, text=True, env=dict(env, RBPT_EMBREE_LIB=""))
    assert run.returncode != 0 and "no mitsuba::rtcNewDevice" in run.stderr


@pytest.mark.skipif(not (SHARED / "cbox" / "cbox.xml").exists(), reason="shared scenes not present")
def test08_mitsuba_passes_make_one_film(monkeypatch):
    # A Mitsuba render split into passes adds up the passes' film sums (weights times values,
    # and weights) and divides once, as one film taking all the samples would; averaging the
    # passes' normalised images instead keeps each pass's ratio estimate.
    mitsuba_ref = load_benchmark("mitsuba_ref")
    if not mitsuba_ref.available():
        pytest.skip("Mitsuba 3 not installed")
    import mitsuba as mi
    scene = mitsuba_ref.load_scene(SHARED / "cbox" / "cbox.xml", width=24, height=16)
    monkeypatch.setattr(mitsuba_ref, "MAX_SAMPLES_PER_PASS", 24 * 16 * 4)
    img = mitsuba_ref.render(scene, 12, seed=3)  # three passes of 4 spp
    sensor = scene.sensors()[0]
    sums, averaged = 0.0, 0.0
    for i in range(3):
        seed = mitsuba_ref._pass_seed(3, i)
        scene.integrator().render(scene, sensor, seed=seed, spp=4, develop=False)
        sums = sums + np.array(sensor.film().bitmap(raw=True), dtype=np.float64)
        averaged = averaged + np.asarray(mi.render(scene, spp=4, seed=seed), dtype=np.float64)[..., :3] / 3
    assert img.shape == (16, 24, 3) and img.dtype == np.float32
    assert (sums[..., -1] > 0).all()
    # (Mitsuba's film adds its splats atomically, in an order that varies from render to
    # render: the same seed's images agree to a few units in the last place.)
    np.testing.assert_allclose(img, sums[..., :3] / sums[..., -1:], rtol=1e-5, atol=1e-6)
    # (The tent filter's weights differ from pass to pass: the two ways differ.)
    assert np.abs(img - averaged).max() > 1e-4
    # One pass is mi.render's own image.
    monkeypatch.setattr(mitsuba_ref, "MAX_SAMPLES_PER_PASS", 1 << 22)
    one = mitsuba_ref.render(scene, 4, seed=3)
    np.testing.assert_allclose(one, np.asarray(mi.render(scene, spp=4, seed=3))[..., :3], rtol=1e-5, atol=1e-6)


@pytest.mark.skipif(not (SHARED / "cbox" / "cbox.xml").exists(), reason="shared scenes not present")
def test09_survey_variants_load_and_differ(tmp_path):
    # bench_survey.py's variants are edits of the shared cbox's text: each must still apply
    # (an edit that no longer matches raises) and give a scene we load and render, and the
    # one whose light it changes must render differently from the cbox.
    import torch
    import torch_rbpt as tr
    bench = load_benchmark("bench_survey")
    images = {}
    for name in bench.VARIANTS:
        scene = tr.load_file(bench.scene_file(name, tmp_path), res=16)
        images[name] = tr.render(scene, spp=4, seed=1)
        assert bool(torch.isfinite(images[name]).all()) and float(images[name].mean()) > 0.01, name
    assert (tmp_path / "direct4.xml").read_text().count("shading_samples") == 1
    for name in ("point", "cube_light", "disk_light", "many_spheres"):
        assert not torch.equal(images[name], images["cbox"]), name
