"""Textures (csrc/textures.h): bitmaps (uv to texel mapping, bilinear and nearest filtering,
wrap modes and sRGB decoding), checkerboards and `to_uv`, against values read off Mitsuba
3.9.1 (tests/references/MITSUBA_FACTS.md, section k, and texture_values.json); checkerboard
colours' gradients."""
import json
import math

import numpy as np
import pytest
import torch

import torch_rbpt as tr
from conftest import REFERENCES, bsdf_scene, directional_derivatives, query_bsdf

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


# -- checkerboard and to_uv (against texture.eval of Mitsuba 3.9.1, texture_values.json) ------

MITSUBA_TEXTURES = json.loads((REFERENCES / "texture_values.json").read_text())


def _xml_texture_scene(tmp_path, texture_xml, dtype=torch.float32):
    """A scene with one diffuse BSDF (native index 0) whose reflectance is `texture_xml`."""
    xml = texture_xml.replace("<texture ", '<texture name="reflectance" ', 1)
    path = tmp_path / "tex.xml"
    path.write_text(f'<scene version="3.0.0"><path value="{REFERENCES}"/>'
                    f'<bsdf type="diffuse" id="m">{xml}</bsdf></scene>')
    return tr.load_file(path, dtype=dtype)


@pytest.mark.parametrize("name", sorted(MITSUBA_TEXTURES["textures"]))
def test06_checkerboard_and_to_uv_match_mitsuba(tmp_path, name):
    # to_uv maps (u, v, 1) by the 2D affine part of the 4x4 transform; the checkerboard is
    # color0 where frac(u) > 1/2 and frac(v) > 1/2 agree.
    entry = MITSUBA_TEXTURES["textures"][name]
    scene = _xml_texture_scene(tmp_path, entry["xml"])
    uv = MITSUBA_TEXTURES["uvs"]
    up = torch.tensor([[0.0, 0.0, 1.0]] * len(uv))
    value, *_ = query_bsdf(scene, up, up, uv=uv)
    torch.testing.assert_close(value * math.pi, torch.tensor(entry["eval"]), rtol=1e-5, atol=1e-5)
    for key, v in entry["params"].items():  # Mitsuba's keys and values (1 or 3 entries)
        torch.testing.assert_close(scene.params[f"m.reflectance.{key}"], torch.tensor(v), rtol=2e-5, atol=2e-6)


def test07_checkerboard_keys_defaults_and_fixed_to_uv(tmp_path):
    scene = _xml_texture_scene(tmp_path, '<texture type="checkerboard"><transform name="to_uv">'
                                         '<scale x="2" y="3"/><translate x="0.5"/></transform></texture>')
    assert scene.params["m.reflectance.color0.value"].tolist() == pytest.approx([0.4])  # Mitsuba's defaults
    assert scene.params["m.reflectance.color1.value"].tolist() == pytest.approx([0.2])
    to_uv = scene.params["m.reflectance.to_uv"]  # 3x3, as Mitsuba's traverse shows it
    assert to_uv.tolist() == [[2, 0, 0.5], [0, 3, 0], [0, 0, 1]]
    with pytest.raises(ValueError, match="to_uv"):
        scene.params["m.reflectance.to_uv"] = to_uv * 2
    with pytest.raises(tr.SceneError, match="color0 and color1 must be constants"):
        _xml_texture_scene(tmp_path, '<texture type="checkerboard"><texture type="checkerboard" name="color0"/></texture>')


def _checker_box(res, plastic=False, dtype=torch.float64):
    """A checkerboard floor (in a roughplastic with `plastic`, whose sampling weights follow
    the texture's mean) and a checkered ball under a sky."""
    T = tr.Transform
    floor_type = {"type": "roughplastic", "alpha": 0.3} if plastic else {"type": "diffuse"}
    floor_input = "diffuse_reflectance" if plastic else "reflectance"
    return tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 60, "to_world": T.look_at([0, 1.2, 2], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": T.rotate([1, 0, 0], -90) @ T.scale(2),
                  "bsdf": {**floor_type, floor_input: {
                      "type": "checkerboard", "color0": {"type": "rgb", "value": [0.7, 0.2, 0.1]},
                      "color1": {"type": "spectrum", "value": 0.4},
                      "to_uv": T.scale([3, 3, 1])}}},
        "ball": {"type": "sphere", "center": [0, 0.4, 0], "radius": 0.4,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "checkerboard", "to_uv": T.scale([6, 4, 1])}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.8, 0.9, 1.0]}},
    }, dtype=dtype)


@pytest.mark.parametrize("key", ["floor.bsdf.reflectance.color0.value",
                                 "floor.bsdf.reflectance.color1.value",
                                 "ball.bsdf.reflectance.color1.value"])
def test08_checkerboard_colours_gradcheck_replay(key):
    scene = _checker_box(3)
    x0 = scene.params[key].detach().clone()

    def f(x):
        scene.params[key] = x
        return tr.render(scene, spp=2, seed=5, seed_grad=5)

    assert torch.autograd.gradcheck(f, (x0.clone().requires_grad_(),), eps=1e-6, atol=1e-5, rtol=1e-3)


def test09_checkerboard_gradient_is_unbiased_with_independent_seeds():
    """The mean over seeds of the backward gradient of a linear loss (its own seeds) agrees
    with central finite differences (common random numbers) within 4 standard errors."""
    res, spp, n = 4, 4, 64
    scene = _checker_box(res, plastic=True)
    key = "floor.bsdf.diffuse_reflectance.color0.value"
    w = torch.rand(res, res, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    direction = torch.tensor([1.0, 0.5, 0.8], dtype=torch.float64)
    h = 1e-2
    d = directional_derivatives(scene, key, w, direction, spp, n, h=h)
    rev, fd = d["backward"], d["fd"]
    se = math.sqrt(rev.var() / n + fd.var() / n)
    assert abs(rev.mean() - fd.mean()) < 4 * se
    assert abs(float(rev.mean())) > 4 * float(rev.std()) / math.sqrt(n)  # resolved, not ~0


@pytest.mark.parametrize("shape", [
    {"type": "sphere", "radius": 0.8},
    {"type": "disk", "to_world": tr.Transform.rotate([1, 0, 0], 30)},
    {"type": "cylinder", "p0": [0, -0.8, 0], "p1": [0, 0.8, 0], "radius": 0.6},
    {"type": "rectangle"},
])
def test10_a_textured_shape_of_each_kind_shows_its_texture(shape):
    """Surface interactions compute uv only for shapes whose BSDF has a texture: a
    checkerboard on each kind of shape shows both of its colours (a uv left at zero would
    show color0 alone). Emitter and untextured shapes in the same scene need no uv."""
    T = tr.Transform
    checker = {"type": "checkerboard", "color0": {"type": "rgb", "value": [0.9, 0.05, 0.05]},
               "color1": {"type": "rgb", "value": [0.05, 0.05, 0.9]}, "to_uv": T.scale([4, 4, 1])}
    scene = tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 50, "to_world": T.look_at([0, 0, 3.5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}}},
        "textured": dict(shape, bsdf={"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": checker}}),
        "plain": {"type": "sphere", "center": [5, 0, 0], "radius": 0.5},
        "sky": {"type": "constant", "radiance": 1.0},
    })
    image = tr.render(scene, spp=4, seed=0)
    r, b = image[..., 0], image[..., 2]
    assert (r > 3 * b).sum() >= 20 and (b > 3 * r).sum() >= 20
