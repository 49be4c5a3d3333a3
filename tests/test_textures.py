"""Bitmap textures (csrc/textures.h): uv to texel mapping, bilinear and nearest filtering,
wrap modes and sRGB decoding, against values read off Mitsuba 3.9.1
(tests/references/MITSUBA_FACTS.md, section k)."""
import math

import numpy as np
import pytest
import torch

import torch_rbpt as tr
from conftest import bsdf_scene, query_bsdf

# Mitsuba 3.9.1: R(u) at v = 0.25 for the 4x2 image with texel (x, y) = (x, y, 10y + x).
U = [-0.3, -0.05, 0.02, 0.98, 1.05, 1.3, 1.6]
MITSUBA_R = {
    ("repeat", "nearest"): [2, 3, 0, 3, 0, 1, 2],
    ("repeat", "bilinear"): [2.3, 2.1, 1.26, 1.74, 0.9, 0.7, 1.9],
    ("mirror", "nearest"): [1, 0, 0, 3, 3, 2, 1],
    ("mirror", "bilinear"): [0.7, 0, 0, 3, 3, 2.3, 1.1],
    ("clamp", "nearest"): [0, 0, 0, 3, 3, 3, 3],
    ("clamp", "bilinear"): [0, 0, 0, 3, 3, 3, 3],
}


@pytest.fixture
def ramp(tmp_path):
    data = np.zeros((2, 4, 3), dtype=np.float32)
    for y in range(2):
        for x in range(4):
            data[y, x] = (x, y, 10 * y + x)
    path = tmp_path / "ramp.exr"
    tr.write_image(path, torch.from_numpy(data))
    return path


def _lookup(path, uv, **props):
    scene = bsdf_scene({"type": "diffuse", "reflectance": {"type": "bitmap", "filename": str(path), **props}})
    n = len(uv)
    up = torch.tensor([[0.0, 0.0, 1.0]] * n)
    value, *_ = query_bsdf(scene, up, up, uv=uv)
    return value * math.pi  # eval = reflectance / pi * cos(wo), cos = 1


@pytest.mark.parametrize("wrap,filt", sorted(MITSUBA_R))
def test01_wrap_modes_and_filters_match_mitsuba(ramp, wrap, filt):
    value = _lookup(ramp, [[u, 0.25] for u in U], wrap_mode=wrap, filter_type=filt)
    torch.testing.assert_close(value[:, 0], torch.tensor(MITSUBA_R[(wrap, filt)], dtype=torch.float32), rtol=1e-5, atol=2e-5)


def test02_row_zero_is_v_zero(ramp):
    value = _lookup(ramp, [[0.125, 0.25], [0.125, 0.75]], filter_type="nearest")
    assert value[0, 1] == 0 and value[1, 1] == 1  # G holds the row index


def test03_srgb_png_is_decoded_unless_raw(tmp_path):
    path = tmp_path / "c.png"
    texel = np.array([[[130, 20, 128]]], dtype=np.uint8)
    import OpenImageIO as oiio
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(1, 1, 3, "uint8"))
    out.write_image(texel)
    out.close()
    # Mitsuba 3.9.1: (0.2232, 0.0070, 0.2159) decoded, c / 255 with raw=true.
    torch.testing.assert_close(_lookup(path, [[0.5, 0.5]])[0], torch.tensor([0.2232, 0.0070, 0.2159]), atol=2e-4, rtol=0)
    torch.testing.assert_close(_lookup(path, [[0.5, 0.5]], raw=True)[0], torch.tensor([0.5098, 0.0784, 0.5020]), atol=2e-4, rtol=0)


def test04_texels_are_a_live_parameter(ramp):
    scene = bsdf_scene({"type": "diffuse", "reflectance": {"type": "bitmap", "filename": str(ramp)}})
    data = scene.params["mat.reflectance.data"]
    assert data.shape == (2, 4, 3)
    data.mul_(0.5)
    up = torch.tensor([[0.0, 0.0, 1.0]])
    value, *_ = query_bsdf(scene, up, up, uv=[[0.375, 0.25]])
    torch.testing.assert_close(value[0] * math.pi, torch.tensor([0.5, 0.0, 0.5]))


def test05_bad_bitmaps_name_the_file(tmp_path):
    with pytest.raises(tr.SceneError, match="bitmap: file 'nope.png' not found"):
        bsdf_scene({"type": "diffuse", "reflectance": {"type": "bitmap", "filename": "nope.png"}})
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png")
    with pytest.raises(tr.SceneError, match="bitmap: .*broken.png"):
        bsdf_scene({"type": "diffuse", "reflectance": {"type": "bitmap", "filename": str(broken)}})
