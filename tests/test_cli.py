"""The command line (torch_rbpt/__main__.py)."""
import subprocess
import sys

import torch

import torch_rbpt as tr
from conftest import ROOT


def _run(*args):
    return subprocess.run([sys.executable, "-m", "torch_rbpt", *args], capture_output=True,
                          text=True, cwd=ROOT)


def test01_render_writes_exr_and_png_matching_the_api(tmp_path):
    out = tmp_path / "box.exr"
    r = _run("render", "torch_rbpt/scenes/cornell_box.xml", "-o", str(out), "--spp", "4",
             "-D", "res=16", "--seed", "3")
    assert r.returncode == 0, r.stderr
    assert out.exists() and out.with_suffix(".png").exists()
    image = tr.read_image(out)
    expected = tr.render(tr.load_file(ROOT / "torch_rbpt/scenes/cornell_box.xml", res=16), spp=4, seed=3)
    assert torch.equal(image, expected)  # bands of rows are bitwise identical to one render


def test02_errors_are_reported_without_a_traceback(tmp_path):
    r = _run("render", "no/such/scene.xml", "-o", str(tmp_path / "x.exr"))
    assert r.returncode == 1
    assert "error:" in r.stderr and "no/such/scene.xml" in r.stderr and "Traceback" not in r.stderr
    r = _run("render", "torch_rbpt/scenes/cornell_box.xml", "-o", str(tmp_path / "x.exr"), "-D", "resolution")
    assert r.returncode == 2 and "NAME=VALUE" in r.stderr


def test03_reports_the_sample_count_the_sampler_takes(tmp_path):
    # A stratified sampler rounds 10 spp up to 16 (a square), as Mitsuba's; the CLI says so.
    xml = (ROOT / "torch_rbpt/scenes/cornell_box.xml").read_text()
    scene_file = tmp_path / "stratified.xml"
    scene_file.write_text(xml.replace('<sampler type="independent">', '<sampler type="stratified">'))
    r = _run("render", str(scene_file), "-o", str(tmp_path / "s.exr"), "--spp", "10", "-D", "res=8")
    assert r.returncode == 0, r.stderr
    assert "16 spp (stratified sampler: 10 rounded to 16)" in r.stdout
    r = _run("render", "torch_rbpt/scenes/cornell_box.xml", "-o", str(tmp_path / "i.exr"), "--spp", "10",
             "-D", "res=8")
    assert r.returncode == 0, r.stderr
    assert "10 spp," in r.stdout and "rounded" not in r.stdout
