"""The wavefront (csrc/wavefront.h): float renders of the path integrator whose vertices are
shaded in SIMD lanes give the scalar integrator's images bit for bit, and scenes outside its
subset are left to the scalar integrator."""
import math
import shutil

import numpy as np
import pytest
import torch

import torch_rbpt as tr
from torch_rbpt import _C
from conftest import SHARED, assert_marked_loops_vectorise, torch_threads

pytestmark = pytest.mark.skipif(_C.build_isa not in ("avx2", "avx512"),
                                reason="the wavefront needs an AVX2 build (PORTABLE=1 builds run path_li)")

# A quad light with vertex normals (2 triangles) and a strip light of 6 triangles.
QUAD_OBJ = """v -0.3 1.5 -0.3
v 0.3 1.5 -0.3
v 0.3 1.5 0.3
v -0.3 1.5 0.3
vn 0 -1 0
vn 0.1 -1 0
vn 0 -1 0.1
vn 0 -1 0
f 1//1 2//2 3//3
f 1//1 3//3 4//4
"""
STRIP_OBJ = "".join(f"v {x} 0.2 {z}\n" for x in (-1.0, -0.5, 0.0, 0.5) for z in (0.9, 1.0)) + \
    "".join(f"f {2 * i + 1} {2 * i + 3} {2 * i + 4}\nf {2 * i + 1} {2 * i + 4} {2 * i + 2}\n" for i in range(3))


def uses_wavefront(scene, sensor=0):
    return _C.uses_wavefront(scene._native, scene.sensors[sensor].native(), scene.integrator.native(),
                             scene.param_list())


def room_dict(tmp_path, integrator=None, **extra):
    """Diffuse walls (one-sided and twosided), a quad light with vertex normals, a strip light
    of 6 triangles seen from its back (flip_normals), and a rectangle light."""
    (tmp_path / "quad.obj").write_text(QUAD_OBJ)
    (tmp_path / "strip.obj").write_text(STRIP_OBJ)
    d = {
        "type": "scene",
        "integrator": {"type": "path", **(integrator or {})},
        "sensor": {"type": "perspective", "fov": 50,
                   "to_world": tr.Transform.look_at([0, 0.6, 3.2], [0, 0.5, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 21, "height": 13, "rfilter": {"type": "tent"}}},
        "floor": {"type": "rectangle", "to_world": tr.Transform.rotate([1, 0, 0], -90).scale(2),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.7, 0.5]}}},
        "back": {"type": "rectangle", "to_world": tr.Transform.translate([0, 1, -1]).scale(2),
                 "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": 0.6}}},
        "side": {"type": "rectangle", "to_world": tr.Transform.translate([-1.2, 1, 0]).rotate([0, 1, 0], 90).scale(2),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.2, 0.7, 0.3]}}},
        "quad": {"type": "obj", "filename": str(tmp_path / "quad.obj"), "bsdf": {"type": "diffuse"},
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [6.0, 5.0, 4.0]}}},
        "strip": {"type": "obj", "filename": str(tmp_path / "strip.obj"), "flip_normals": True,
                  "emitter": {"type": "area", "radiance": 2.0}},
        "panel": {"type": "rectangle", "to_world": tr.Transform.translate([1.1, 0.8, 0]).rotate([0, 1, 0], -90).scale(0.3),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 3.0, 6.0]}}},
    }
    d.update(extra)
    return d


def room(tmp_path, integrator=None, **extra):
    return tr.load_dict(room_dict(tmp_path, integrator, **extra))


def render_both(scene, monkeypatch, **kw):
    """The image with the wavefront, and with the scalar integrator."""
    assert uses_wavefront(scene)
    wavefront = tr.render(scene, **kw)
    with monkeypatch.context() as m:
        m.setenv("TORCH_RBPT_WAVEFRONT", "0")
        assert not uses_wavefront(scene)
        scalar = tr.render(scene, **kw)
    return wavefront, scalar


@pytest.mark.parametrize("integrator", [
    {}, {"max_depth": 1}, {"max_depth": 2}, {"max_depth": 4, "rr_depth": 1}, {"rr_depth": 2},
    {"hide_emitters": True}])
def test01_wavefront_image_is_the_scalar_image_bitwise(tmp_path, monkeypatch, integrator):
    scene = room(tmp_path, integrator)
    # (A tile's 16 x 13 x 7 samples: batches of 256 split pixels, and lanes freed by ended
    # paths take new samples, so paths of several depths share a batch.)
    wavefront, scalar = render_both(scene, monkeypatch, spp=7, seed=5)
    assert float(scalar.mean()) > 0.01  # lit by the lights, also with the emitters hidden
    assert torch.equal(wavefront, scalar)


def test02_wavefront_is_deterministic_across_threads(tmp_path):
    scene = room(tmp_path)
    with torch_threads(1):
        one = tr.render(scene, spp=32, seed=2)
    with torch_threads(2):
        two = tr.render(scene, spp=32, seed=2)
    assert torch.equal(one, two)


def backward(scene, keys, spp=8, seed=4):
    """The gradients of an L2 loss at `keys` (render_bwd with `seed`), and the numbers of
    paths the backward pass traced in lanes and with the tape."""
    image = tr.render(scene, spp=spp, seed=1).detach()
    needs = [k in keys for k in scene._keys]
    grads, lanes, taped = _C.render_bwd_paths(scene._native, scene.sensor.native(), scene.integrator.native(),
                                              scene.param_list(), needs, 2 * (image - 0.3), spp, seed)
    return {k: g for k, g in zip(scene._keys, grads) if g is not None}, lanes, taped


def assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=8, some_taped=False):
    """Every path of the backward pass traced in lanes (with `some_taped`: some of them, the
    others with the tape), and the gradients at `keys` (each nonzero) those of the tape on
    the same paths, to float rounding."""
    assert all(k in scene._keys for k in keys), scene._keys
    grads, lanes, taped = backward(scene, keys, spp=spp)
    if some_taped:
        assert lanes > 0 and taped > 0 and lanes + taped == 21 * 13 * spp
    else:
        assert lanes == 21 * 13 * spp and taped == 0
    with monkeypatch.context() as m:
        m.setenv("TORCH_RBPT_WAVEFRONT", "0")
        tape_grads, _, _ = backward(scene, keys, spp=spp)
    for k in keys:
        scale = float(tape_grads[k].abs().max())
        assert scale > 0, k
        torch.testing.assert_close(grads[k], tape_grads[k], rtol=1e-4, atol=1e-5 * scale, msg=k)


def test03_gradients_with_the_wavefront_forward_pass(tmp_path, monkeypatch):
    # The forward pass of a differentiable render takes the wavefront, or the scalar
    # integrator: the gradient does not depend on which forward ran (the backward pass traces
    # its own paths; with TORCH_RBPT_WAVEFRONT=0 it takes the tape, else lanes).
    grads = []
    for mode in ("1", "0"):
        monkeypatch.setenv("TORCH_RBPT_WAVEFRONT", mode)
        scene = room(tmp_path)
        key = "floor.bsdf.reflectance.value"
        scene.params[key].requires_grad_(True)
        image = tr.render(scene, spp=8, seed=1)
        (image ** 2).mean().backward()
        grads.append(scene.params[key].grad.clone())
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=0)
    assert float(grads[0].abs().sum()) > 0


DIFFUSE_KEYS = ["floor.bsdf.reflectance.data", "back.bsdf.brdf_0.reflectance.data", "side.bsdf.reflectance.value",
                "quad.bsdf.reflectance.value", "checks.bsdf.brdf_0.reflectance.color0.value",
                "checks.bsdf.brdf_0.reflectance.color1.value", "ball.bsdf.reflectance.color0.value",
                "ball.bsdf.reflectance.color1.value", "colors.vertex_color", "quad.emitter.radiance.value",
                "strip.emitter.radiance.value"]


def test09_backward_in_lanes_gives_the_tapes_gradients(tmp_path, monkeypatch):
    # Diffuse reflectances (RGB and scalar constants, bitmaps bilinear and nearest,
    # checkerboards, a mesh attribute) and emitter radiances (RGB and scalar) differentiated
    # in lanes, each vertex depositing dL . (L - L_before) / rho and each emission dL . C / Le:
    # the tape's gradients on the same paths, to float rounding.
    scene = textured_room(tmp_path)
    lanes_grads, lanes, taped = backward(scene, DIFFUSE_KEYS)
    assert lanes == 21 * 13 * 8 and taped == 0
    again, _, _ = backward(scene, DIFFUSE_KEYS)
    assert all(torch.equal(lanes_grads[k], again[k]) for k in DIFFUSE_KEYS)
    monkeypatch.setenv("TORCH_RBPT_WAVEFRONT", "0")
    tape_grads, lanes0, taped0 = backward(scene, DIFFUSE_KEYS)
    assert lanes0 == 0 and taped0 == lanes
    for k in DIFFUSE_KEYS:
        scale = float(tape_grads[k].abs().max())
        assert scale > 0, k
        torch.testing.assert_close(lanes_grads[k], tape_grads[k], rtol=1e-4, atol=1e-5 * scale, msg=k)
    # A reflectance with a zero channel (a fit's clamp): the quotient would be 0 / 0; the
    # lanes take that channel as 1 in the throughput (test27), and still give the tape's
    # gradients, that channel's derivative included. (A radiance with a zero channel takes
    # the tape: see test10.)
    monkeypatch.setenv("TORCH_RBPT_WAVEFRONT", "1")
    with torch.no_grad():
        scene.params["side.bsdf.reflectance.value"].copy_(torch.tensor([0.2, 0.0, 0.3]))
    assert_lanes_give_the_tapes_gradients(scene, DIFFUSE_KEYS, monkeypatch)
    grads, _, _ = backward(scene, DIFFUSE_KEYS)
    assert float(grads["side.bsdf.reflectance.value"][1].abs()) > 0


@pytest.mark.parametrize("key", ["beckmann.bsdf.specular_reflectance.value", "shiny.bsdf.specular_reflectance.value"])
def test10_backward_takes_the_tape_for_other_parameters(tmp_path, monkeypatch, key):
    # The inputs that the lanes do not differentiate (those other than the diffuse,
    # mirrors' and conductors' reflectances, and roughplastic's diffuse reflectance and
    # roughness, test35), such as roughplastic's specular reflectance (Beckmann's or GGX's):
    # the whole backward pass takes the tape, whatever else is differentiated.
    scene = room(tmp_path, {"max_depth": 5},
                 mirror={"type": "sphere", "radius": 0.25, "to_world": tr.Transform.translate([0.3, 0.25, 0.2]),
                         "bsdf": {"type": "conductor", "specular_reflectance": {"type": "rgb", "value": [0.9, 0.8, 0.7]}}},
                 metal={"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.4, 0.2, -0.2]),
                        "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}},
                 beckmann={"type": "sphere", "radius": 0.15, "to_world": tr.Transform.translate([0.0, 0.15, 0.5]),
                           "bsdf": {"type": "roughplastic", "alpha": 0.2}},
                 shiny={"type": "rectangle", "to_world": tr.Transform.translate([0.5, 0.02, 0.5]).rotate([1, 0, 0], -90).scale(0.3),
                        "bsdf": {"type": "roughplastic", "distribution": "ggx",
                                 "diffuse_reflectance": {"type": "rgb", "value": [0.7, 0.6, 0.5]}}})
    keys = ["floor.bsdf.reflectance.value", key]
    assert all(k in scene._keys for k in keys), scene._keys
    grads, lanes, taped = backward(scene, keys)
    assert lanes == 0 and taped == 21 * 13 * 8
    monkeypatch.setenv("TORCH_RBPT_WAVEFRONT", "0")
    tape_grads, _, _ = backward(scene, keys)
    assert all(torch.equal(grads[k], tape_grads[k]) and float(grads[k].abs().sum()) > 0 for k in keys)


@pytest.mark.skipif(not (SHARED / "cornell-box" / "scene_v3.xml").exists(), reason="shared scenes not present")
def test04_cornell_box_takes_the_wavefront(monkeypatch):
    scene = tr.load_file(SHARED / "cornell-box" / "scene_v3.xml")
    scene.sensor.film.width = scene.sensor.film.height = 24
    wavefront, scalar = render_both(scene, monkeypatch, spp=16, seed=9)
    assert torch.equal(wavefront, scalar)


@pytest.mark.parametrize("extra", [
    {"ball": {"type": "sphere", "radius": 0.25, "to_world": tr.Transform.translate([0.3, 0.25, 0.2]),
              "bsdf": {"type": "conductor"}}},
    {"glass": {"type": "sphere", "radius": 0.25, "to_world": tr.Transform.translate([-0.3, 0.25, 0.3]),
               "bsdf": {"type": "dielectric"}},
     "matte": {"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([0.4, 0.2, -0.3]),
               "bsdf": {"type": "diffuse", "reflectance": 0.9}},
     "inside_out": {"type": "sphere", "radius": 0.15, "flip_normals": True, "to_world": tr.Transform.translate([-0.5, 0.6, 0]),
                    "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": 0.5}}}},
    {"pane": {"type": "cube", "to_world": tr.Transform.translate([0.1, 0.3, 0.4]).scale([0.4, 0.3, 0.05]),
              "bsdf": {"type": "dielectric", "int_ior": 1.33, "ext_ior": 1.33}},
     "mirror": {"type": "rectangle", "to_world": tr.Transform.translate([0.6, 0.5, -0.5]).rotate([0, 1, 0], -40).scale(0.4),
                "bsdf": {"type": "twosided", "bsdf": {"type": "conductor",
                                                      "specular_reflectance": {"type": "checkerboard"}}}},
     "tinted": {"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.5, 0.2, -0.2]),
                "bsdf": {"type": "dielectric", "int_ior": 1.7,
                         "specular_reflectance": {"type": "rgb", "value": [0.9, 0.8, 0.7]},
                         "specular_transmittance": {"type": "checkerboard", "to_uv": tr.Transform.scale([6, 3, 1])}}}},
    {"gold": {"type": "sphere", "radius": 0.25, "to_world": tr.Transform.translate([0.3, 0.25, 0.2]),
              "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.2,
                       "specular_reflectance": {"type": "rgb", "value": [1.0, 0.8, 0.4]}}},
     "tilted": {"type": "rectangle", "to_world": tr.Transform.translate([0.6, 0.5, -0.5]).rotate([0, 1, 0], -40).scale(0.4),
                "bsdf": {"type": "twosided", "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.05,
                                                      "specular_reflectance": {"type": "checkerboard"}}}},
     "floor": {"type": "rectangle", "to_world": tr.Transform.rotate([1, 0, 0], -90).scale(2),
               "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3, "int_ior": 1.6,
                        "diffuse_reflectance": {"type": "checkerboard", "to_uv": tr.Transform.scale([4, 4, 1])}}},
     "shiny": {"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.5, 0.2, -0.1]),
               "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.08, "nonlinear": True,
                        "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.5, 0.8]},
                        "specular_reflectance": 0.7}}},
    {"rough": {"type": "cube", "to_world": tr.Transform.translate([0.2, 0.2, 0]).scale(0.2),
               "bsdf": {"type": "roughconductor", "alpha": 0.3}},
     "plastic": {"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.4, 0.2, 0]),
                 "bsdf": {"type": "roughplastic", "alpha": 0.2}}},
    {"rough": {"type": "cube", "to_world": tr.Transform.translate([0.2, 0.2, 0]).scale(0.2),
               "bsdf": {"type": "roughconductor", "alpha": 0.3}},
     "plastic": {"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.4, 0.2, 0]),
                 "bsdf": {"type": "roughplastic", "alpha": 0.2}},
     "glass": {"type": "sphere", "radius": 0.15, "to_world": tr.Transform.translate([0.4, 0.15, 0.4]),
               "bsdf": {"type": "dielectric"}},
     "satin": {"type": "sphere", "radius": 0.15, "to_world": tr.Transform.translate([-0.2, 0.15, 0.5]),
               "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.4}}},
    {"rough": {"type": "rectangle", "to_world": tr.Transform.translate([0.6, 0.5, -0.5]).rotate([0, 1, 0], -40).scale(0.4),
               "bsdf": {"type": "twosided", "bsdf": {"type": "roughconductor", "alpha": 0.05}}},
     "plastic": {"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.4, 0.2, 0]),
                 "bsdf": {"type": "roughplastic", "alpha": 0.01, "nonlinear": True,
                          "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.5, 0.8]}}},
     "glass": {"type": "sphere", "radius": 0.15, "to_world": tr.Transform.translate([0.4, 0.15, 0.4]),
               "bsdf": {"type": "dielectric"}},
     "bulb": {"type": "sphere", "radius": 0.05, "to_world": tr.Transform.translate([0.0, 0.8, 0.3]),
              "emitter": {"type": "area", "radiance": 20.0}}},
], ids=["mirror", "glass", "textured delta", "ggx", "beckmann", "all kinds", "all kinds, two lights"])
def test05_every_bsdf_gives_path_li_image(tmp_path, monkeypatch, extra):
    # Mirrors, dielectrics (index-matched too, textured, twosided) and rough BSDFs (GGX's
    # and Beckmann's, whose visible normals are sampled in lanes first) are shaded in lanes
    # with the diffuse vertices, the rough ones in stages over their lists of lanes, also
    # where the scene has several lights, one of them a sphere, and delta BSDFs ("all kinds,
    # two lights"). The image is path_li's.
    scene = room(tmp_path, {"max_depth": 6}, **extra)
    wavefront, scalar = render_both(scene, monkeypatch, spp=9, seed=4)
    assert torch.equal(wavefront, scalar)


COLOR_PLY = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
property float r
property float g
property float b
element face 2
property list uchar int vertex_indices
end_header
-0.4 0.6 -0.5 0.9 0.1 0.2
0.4 0.6 -0.5 0.1 0.8 0.3
0.4 1.2 -0.6 0.2 0.3 0.9
-0.4 1.2 -0.6 0.7 0.7 0.1
3 0 1 2
3 0 2 3
"""


def textured_room(tmp_path, integrator=None):
    """The room with diffuse reflectances that are bitmaps (bilinear and nearest, wrapped,
    with to_uv), checkerboards and a mesh attribute."""
    texels = torch.from_numpy(np.random.default_rng(3).uniform(0.05, 0.95, (5, 7, 3)).astype(np.float32))
    tr.write_image(tmp_path / "t.exr", texels)
    (tmp_path / "c.ply").write_text(COLOR_PLY)
    diffuse = lambda texture: {"type": "diffuse", "reflectance": texture}  # noqa: E731
    return room(
        tmp_path, integrator or {"max_depth": 6},
        floor={"type": "rectangle", "to_world": tr.Transform.rotate([1, 0, 0], -90).scale(2),
               "bsdf": diffuse({"type": "bitmap", "filename": str(tmp_path / "t.exr"),
                                "to_uv": tr.Transform.scale([3, 2, 1])})},
        back={"type": "rectangle", "to_world": tr.Transform.translate([0, 1, -1]).scale(2),
              "bsdf": {"type": "twosided", "bsdf": diffuse({"type": "bitmap", "filename": str(tmp_path / "t.exr"),
                                                            "filter_type": "nearest", "wrap_mode": "mirror",
                                                            "to_uv": tr.Transform.scale([2.5, 1.5, 1])})}},
        checks={"type": "rectangle", "to_world": tr.Transform.translate([0.4, 0.01, 0.3]).rotate([1, 0, 0], -90).scale(0.4),
                "bsdf": {"type": "twosided", "bsdf": diffuse({"type": "checkerboard"})}},
        ball={"type": "sphere", "radius": 0.25,
              "to_world": tr.Transform.translate([-0.4, 0.25, 0.2]).rotate([0.3, 1, 0.5], 40),
              "bsdf": diffuse({"type": "checkerboard", "to_uv": tr.Transform.scale([4, 4, 1])})},
        colors={"type": "ply", "filename": str(tmp_path / "c.ply"),
                "bsdf": {"type": "twosided", "bsdf": diffuse({"type": "mesh_attribute", "name": "vertex_color"})}})


def test07_textured_diffuse_reflectances_take_the_lanes_bitwise(tmp_path, monkeypatch):
    # A diffuse reflectance that is a bitmap, a checkerboard or a mesh attribute is looked up
    # in the trace stage and shaded in lanes; the checkered ball's uv (in its rotated frame)
    # is the interaction stage's.
    scene = textured_room(tmp_path)
    wavefront, scalar = render_both(scene, monkeypatch, spp=9, seed=6)
    assert float(scalar.mean()) > 0.01
    assert torch.equal(wavefront, scalar)


@pytest.mark.parametrize("change", ["direct", "float64"])
def test06_scenes_outside_the_subset_take_the_scalar_integrator(tmp_path, change):
    d = room_dict(tmp_path)
    if change == "direct":  # (one sample of each, or of one alone, is path tracing's first vertex: lanes)
        d["integrator"] = {"type": "direct", "emitter_samples": 2}
    scene = tr.load_dict(d, dtype=torch.float64 if change == "float64" else torch.float32)
    assert not uses_wavefront(scene)
    assert uses_wavefront(room(tmp_path))


@pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")
@pytest.mark.parametrize("march", ["x86-64-v3", "native"])
def test08_vector_stages_vectorise(tmp_path, march):
    # Every loop marked `#pragma GCC ivdep` in wavefront.cpp vectorises, in each of its
    # template instances, for AVX2 and for this machine. An edit that stops GCC (a helper it
    # no longer inlines, a load under a condition) keeps the images bitwise equal and only
    # makes them slower, which no other test sees. So do the film's batched filter weights
    # (camera.cpp: the tent's and the gaussian's), and the stratified samplers' draws in
    # lanes (sampler.cpp).
    assert assert_marked_loops_vectorise("wavefront.cpp", "#pragma GCC ivdep", march, tmp_path) >= 3
    assert assert_marked_loops_vectorise("camera.cpp", "#pragma GCC ivdep", march, tmp_path) == 2
    assert assert_marked_loops_vectorise("sampler.cpp", "#pragma GCC ivdep", march, tmp_path) == 20


def test11_backward_in_lanes_for_specular_inputs(tmp_path, monkeypatch):
    # A mirror's and a GGX and a Beckmann conductor's specular reflectance (RGB, and a
    # checkerboard on a twosided mirror), and a dielectric's specular reflectance and transmittance on the
    # branch its vertex sampled, are one factor of everything the path gathers after the
    # vertex, as a diffuse reflectance is: lanes, with the tape's gradients.
    scene = room(tmp_path, {"max_depth": 6},
                 mirror={"type": "sphere", "radius": 0.25, "to_world": tr.Transform.translate([0.3, 0.25, 0.2]),
                         "bsdf": {"type": "conductor", "specular_reflectance": {"type": "rgb", "value": [0.9, 0.8, 0.7]}}},
                 panel_mirror={"type": "rectangle",
                               "to_world": tr.Transform.translate([0.6, 0.5, -0.5]).rotate([0, 1, 0], -40).scale(0.4),
                               "bsdf": {"type": "twosided", "bsdf": {"type": "conductor",
                                                                     "specular_reflectance": {"type": "checkerboard"}}}},
                 metal={"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.4, 0.2, -0.2]),
                        "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3,
                                 "specular_reflectance": {"type": "rgb", "value": [0.95, 0.6, 0.3]}}},
                 beckmann={"type": "sphere", "radius": 0.15, "to_world": tr.Transform.translate([0.0, 0.15, 0.5]),
                           "bsdf": {"type": "roughconductor", "alpha": 0.2,
                                    "specular_reflectance": {"type": "rgb", "value": [0.8, 0.9, 0.6]}}},
                 glass={"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.1, 0.45, 0.6]),
                        "bsdf": {"type": "dielectric", "int_ior": 1.5,
                                 "specular_reflectance": {"type": "rgb", "value": [0.9, 0.95, 0.8]},
                                 "specular_transmittance": {"type": "checkerboard", "to_uv": tr.Transform.scale([4, 4, 1])}}})
    keys = ["glass.bsdf.specular_reflectance.value", "glass.bsdf.specular_transmittance.color0.value",
            "glass.bsdf.specular_transmittance.color1.value",
            "floor.bsdf.reflectance.value", "mirror.bsdf.specular_reflectance.value",
            "panel_mirror.bsdf.brdf_0.specular_reflectance.color0.value",
            "panel_mirror.bsdf.brdf_0.specular_reflectance.color1.value", "metal.bsdf.specular_reflectance.value",
            "beckmann.bsdf.specular_reflectance.value"]
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch)


@pytest.mark.parametrize("integrator", [{}, {"hide_emitters": True}, {"max_depth": 2}, {"rr_depth": 1}])
@pytest.mark.parametrize("lights", ["area lights", "environment only", "environment and a sphere"])
def test12_constant_environment_in_lanes(tmp_path, monkeypatch, integrator, lights):
    # The `constant` environment: its emitter samples (a uniform direction, a shadow ray to
    # infinity) in the vector stage, the emission of rays that escape in the shade stage, the
    # image bitwise path_li's; its radiance differentiated in lanes, with a reflectance, the
    # tape's gradients.
    d = room_dict(tmp_path, integrator)
    d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.4, 0.6]}}
    if lights != "area lights":
        for key in ("quad", "strip", "panel"):
            del d[key]
    if lights == "environment and a sphere":
        d["bulb"] = {"type": "sphere", "radius": 0.15, "center": [0.4, 1.2, 0.3], "emitter": {"type": "area", "radiance": 5.0}}
    scene = tr.load_dict(d)
    wavefront, scalar = render_both(scene, monkeypatch, spp=7, seed=5)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05
    assert_lanes_give_the_tapes_gradients(scene, ["sky.radiance.value", "floor.bsdf.reflectance.value"], monkeypatch)


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
@pytest.mark.parametrize("lights", ["area lights", "environment only"])
def test13_backward_in_lanes_for_conductor_roughness(tmp_path, monkeypatch, lights, distribution):
    # A rough conductor's roughness (GGX's, or Beckmann's, Mitsuba's default, whose visible
    # normals are sampled one path at a time) enters its vertex's emitter sample and BSDF
    # sample weight as one factor common to the channels, f(wo) (the pdf detached): each
    # vertex deposits C_e dlog f(wo_e) + (L - L_before - C_e) dlog f(wo_s). Lanes, with the
    # tape's gradients: a sphere, a twosided panel seen from both sides, a very smooth one;
    # with their specular reflectances, a diffuse reflectance and the lights' radiance.
    extra = dict(
        metal={"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.4, 0.2, -0.2]),
               "bsdf": {"type": "roughconductor", "distribution": distribution, "alpha": 0.3,
                        "specular_reflectance": {"type": "rgb", "value": [0.95, 0.6, 0.3]}}},
        panel_metal={"type": "rectangle", "to_world": tr.Transform.translate([0.5, 0.5, -0.3]).rotate([0, 1, 0], -60).scale(0.35),
                     "bsdf": {"type": "twosided", "bsdf": {"type": "roughconductor", "distribution": distribution, "alpha": 0.12}}},
        smooth={"type": "sphere", "radius": 0.15, "to_world": tr.Transform.translate([0.1, 0.15, 0.5]),
                "bsdf": {"type": "roughconductor", "distribution": distribution, "alpha": 0.02}})
    d = room_dict(tmp_path, {"max_depth": 6}, **extra)
    radiance = "quad.emitter.radiance.value"
    if lights == "environment only":
        for key in ("quad", "strip", "panel"):
            del d[key]
        d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 0.6, 0.8]}}
        radiance = "sky.radiance.value"
    scene = tr.load_dict(d)
    keys = ["metal.bsdf.alpha.value", "panel_metal.bsdf.brdf_0.alpha.value", "smooth.bsdf.alpha.value",
            "metal.bsdf.specular_reflectance.value", "floor.bsdf.reflectance.value", radiance]
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=16)


def sphere_lights(d, lights):
    """The room `d` lit by a small sphere (its cone sampled from outside) and a tiny one (the
    cone's Taylor expansion), beside its mesh lights, or by one of those, or by a sphere
    around the room with its normals flipped inwards (a uniform point, seen from inside)."""
    bulb = {"type": "sphere", "radius": 0.15, "center": [0.4, 1.2, 0.3],
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [8.0, 6.0, 3.0]}}}
    # sin^2 of the cone (0.02 / distance)^2 is below the expansion's 0.00068523 beyond 0.77
    star = {"type": "sphere", "radius": 0.02, "center": [-0.5, 1.4, 1.0], "emitter": {"type": "area", "radiance": 400.0}}
    dome = {"type": "sphere", "radius": 6.0, "flip_normals": True, "emitter": {"type": "area", "radiance": 0.5}}
    if lights != "spheres and meshes":
        for key in ("quad", "strip", "panel"):
            del d[key]
    if lights == "one sphere":
        d["bulb"] = bulb
    elif lights == "enclosing sphere":
        d["dome"] = dome
    else:
        d["bulb"], d["star"] = bulb, star
    return d


@pytest.mark.parametrize("lights", ["spheres and meshes", "one sphere", "enclosing sphere", "two spheres"])
def test14_sphere_lights_in_lanes(tmp_path, monkeypatch, lights):
    # Area lights on spheres: emitter samples in the vector stage (Geometry::sample_direction's
    # cone from outside, its small-cone expansion, a uniform point from inside; with no mesh
    # light, its instance that gathers no triangle), the image bitwise path_li's; their
    # radiance differentiated in lanes, with a reflectance.
    scene = tr.load_dict(sphere_lights(room_dict(tmp_path), lights))
    wavefront, scalar = render_both(scene, monkeypatch, spp=7, seed=5)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05
    radiance = {"one sphere": "bulb", "enclosing sphere": "dome"}.get(lights, "star") + ".emitter.radiance.value"
    assert_lanes_give_the_tapes_gradients(scene, [radiance, "floor.bsdf.reflectance.value"], monkeypatch)


@pytest.mark.parametrize("integrator", [{}, {"hide_emitters": True}, {"emitter_samples": 1, "bsdf_samples": 0},
                                        {"emitter_samples": 0, "bsdf_samples": 1}])
def test15_direct_integrator_is_the_first_vertex_of_path_tracing(tmp_path, monkeypatch, integrator, shared):
    # `direct` with one emitter sample and one BSDF sample computes path_li's first vertex
    # (path_settings()): it takes the lanes, and its image is direct_li's bit for bit, with
    # diffuse, mirror, glass and rough (GGX and Beckmann) vertices under mesh lights, spheres
    # and the sky; and so
    # on the shared veach-mis (roughplastic plates, Beckmann's, spheres down to the cone's
    # expansion). So also with one emitter sample alone (the path ends after it) or one BSDF
    # sample alone (no emitter sample drawn), neither MIS-weighted: veach-mis's other two
    # integrators.
    d = sphere_lights(room_dict(tmp_path), "spheres and meshes")
    d["integrator"] = {"type": "direct", **integrator}
    d["sky"] = {"type": "constant", "radiance": 0.2}
    d["mirror"] = {"type": "sphere", "radius": 0.2, "center": [0.3, 0.25, 0.2], "bsdf": {"type": "conductor"}}
    d["glass"] = {"type": "sphere", "radius": 0.2, "center": [-0.1, 0.45, 0.6], "bsdf": {"type": "dielectric"}}
    d["metal"] = {"type": "sphere", "radius": 0.2, "center": [-0.4, 0.2, -0.2],
                  "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}}
    d["brushed"] = {"type": "sphere", "radius": 0.15, "center": [0.7, 0.15, 0.4],
                    "bsdf": {"type": "roughconductor", "alpha": 0.15}}
    scene = tr.load_dict(d)
    wavefront, scalar = render_both(scene, monkeypatch, spp=7, seed=5)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05
    # The backward pass in lanes, against the tape's (direct_li's) gradients.
    keys = ["floor.bsdf.reflectance.value", "bulb.emitter.radiance.value", "metal.bsdf.alpha.value",
            "brushed.bsdf.alpha.value"]
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch)
    veach_file = {(1, 0): "lum", (0, 1): "bsdf"}.get((integrator.get("emitter_samples", 1), integrator.get("bsdf_samples", 1)), "both")
    veach = tr.load_file(SHARED / f"veach-mis/integrator_direct_{veach_file}.xml")
    assert uses_wavefront(veach)
    veach.sensor.film.width, veach.sensor.film.height = 48, 32
    wavefront, scalar = render_both(veach, monkeypatch, spp=4, seed=3)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05


@pytest.mark.parametrize("rfilter", [
    {"type": "box"}, {"type": "tent", "radius": 1.7}, {"type": "gaussian"}, {"type": "gaussian", "stddev": 0.75},
    {"type": "gaussian", "stddev": 1.2}, {"type": "mitchell"}, {"type": "lanczos", "lobes": 2}])
def test16_filter_weights_of_a_batch_are_the_scalar_splats(tmp_path, monkeypatch, rfilter):
    # The wavefront computes its batch's filter weights at once (Filter::eval_rows, the tent's
    # and the gaussian's in SIMD lanes) and splats a pixel's samples by runs over windows of
    # 5 x 5 and 7 x 7 (the gaussian's stddev 0.5 and 0.75); the pixels must be those the
    # scalar integrator splats sample by sample, with every filter, also where a crop window
    # cuts the splats.
    d = room_dict(tmp_path)
    d["sensor"]["film"]["rfilter"] = rfilter
    scene = tr.load_dict(d)
    wavefront, scalar = render_both(scene, monkeypatch, spp=5, seed=2)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.01
    d["sensor"]["film"].update(crop_offset_x=3, crop_offset_y=2, crop_width=11, crop_height=7)
    wavefront, scalar = render_both(tr.load_dict(d), monkeypatch, spp=5, seed=2)
    assert wavefront.shape[:2] == (7, 11) and torch.equal(wavefront, scalar)


@pytest.mark.parametrize("rfilter", [
    {"type": "gaussian"}, {"type": "mitchell"}, {"type": "lanczos", "lobes": 2}, {"type": "gaussian", "stddev": 4.0}])
def test17_backward_in_lanes_with_batched_filter_weights(tmp_path, monkeypatch, rfilter):
    # The backward pass sums its samples' filter weights and gathers their adjoints with
    # weights computed a batch at once (SplatWeights; a tile's pixels at a time, but for
    # filters wider than 8 pixels, whose tiles exceed a batch: the last case); its gradients
    # in lanes must be the tape's, which gathers sample by sample, also under a crop window.
    d = room_dict(tmp_path)
    d["sensor"]["film"]["rfilter"] = rfilter
    assert_lanes_give_the_tapes_gradients(tr.load_dict(d), ["floor.bsdf.reflectance.value"], monkeypatch)
    d["sensor"]["film"].update(crop_offset_x=3, crop_offset_y=2, crop_width=11, crop_height=7)
    scene = tr.load_dict(d)
    key = "floor.bsdf.reflectance.value"
    grads, lanes, taped = backward(scene, [key])
    assert lanes == 11 * 7 * 8 and taped == 0
    with monkeypatch.context() as m:
        m.setenv("TORCH_RBPT_WAVEFRONT", "0")
        tape_grads, _, _ = backward(scene, [key])
    scale = float(tape_grads[key].abs().max())
    assert scale > 0
    torch.testing.assert_close(grads[key], tape_grads[key], rtol=1e-4, atol=1e-5 * scale)


@pytest.mark.parametrize("bitmap", [
    {"wrap_mode": "clamp", "to_uv": tr.Transform.translate([-0.3, 0.2, 0]).scale([1.7, 2.2, 1])},
    {"wrap_mode": "repeat"}, {"wrap_mode": "mirror", "filter_type": "nearest"},
    {"gray": True, "wrap_mode": "mirror", "to_uv": tr.Transform.scale([-3.5, 2.5, 1])},
    {"to_uv": tr.Transform.scale([3e8, 3e8, 1])}])
def test18_bitmap_reflectances_in_the_wavefront(tmp_path, monkeypatch, bitmap):
    # Bitmap reflectances (every wrap mode, bilinear and nearest, to_uv, one or three
    # channels, texel coordinates beyond 2^20) under the wavefront: the image is the scalar
    # integrator's bit for bit, and the backward pass in lanes, which logs the texels each
    # vertex reads, gives the tape's gradients.
    bitmap = dict(bitmap)
    channels = 1 if bitmap.pop("gray", False) else 3
    texels = torch.from_numpy(np.random.default_rng(4).uniform(0.05, 0.95, (6, 5, channels)).astype(np.float32))
    tr.write_image(tmp_path / "t.exr", texels)
    d = room_dict(tmp_path, {"max_depth": 4})
    d["floor"]["bsdf"] = {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": str(tmp_path / "t.exr"), **bitmap}}
    d["back"]["bsdf"] = {"type": "twosided", "bsdf": d["floor"]["bsdf"]}
    scene = tr.load_dict(d)
    wavefront, scalar = render_both(scene, monkeypatch, spp=6, seed=7)
    assert float(scalar.mean()) > 0.01
    assert torch.equal(wavefront, scalar)
    keys = [k for k in scene._keys if k.endswith("reflectance.data")]
    assert keys
    assert_lanes_give_the_tapes_gradients(scene, keys[:1], monkeypatch, spp=4)


@pytest.mark.parametrize("light", ["quad", "strip", "panel"])
@pytest.mark.parametrize("extra", [{}, {"ball": {"type": "sphere", "radius": 0.25, "bsdf": {"type": "dielectric"},
                                             "to_world": tr.Transform.translate([0.3, 0.25, 0.2])}}],
                         ids=["diffuse", "delta"])
def test19_one_mesh_light_picked_in_lanes(tmp_path, monkeypatch, light, extra):
    # With one light its emitter samples' triangles and points are picked in lanes from all
    # of its triangles (light_point_stage: from 2 for the quad with vertex normals and the
    # rectangle, from 8 for the 6-triangle strip seen from its back): the image is the scalar
    # integrator's bit for bit.
    d = room_dict(tmp_path, {"max_depth": 5}, **extra)
    for other in {"quad", "strip", "panel"} - {light}:
        del d[other]
    scene = tr.load_dict(d)
    wavefront, scalar = render_both(scene, monkeypatch, spp=8, seed=11)
    assert float(scalar.mean()) > 0.005
    assert torch.equal(wavefront, scalar)


@pytest.mark.parametrize("sensor", [
    {"type": "orthographic"}, {"type": "thinlens", "fov": 50, "aperture_radius": 0.05, "focus_distance": 3.0}])
def test20_other_sensors_start_their_paths_alone(tmp_path, monkeypatch, sensor):
    # The perspective sensor's camera rays are made in lanes; the others' one sample at a
    # time, into the lanes each refill frees: the images must be the scalar integrator's.
    d = room_dict(tmp_path, {"max_depth": 6})
    d["sensor"] = {**sensor, "to_world": d["sensor"]["to_world"], "film": d["sensor"]["film"]}
    wavefront, scalar = render_both(tr.load_dict(d), monkeypatch, spp=9, seed=4)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05


LAMP = {"type": "point", "position": [0.3, 1.3, 0.5], "intensity": {"type": "rgb", "value": [3.0, 2.0, 1.0]}}


@pytest.mark.parametrize("integrator", ["path", "direct"])
@pytest.mark.parametrize("lights", ["point light and meshes", "point light alone", "cube light", "disk light",
                                    "point light, sky, delta and rough BSDFs", "point light and Beckmann"])
def test21_emitters_sampled_aside(tmp_path, monkeypatch, lights, integrator):
    # Emitters the vector stage does not sample itself (a point light, an area light on a
    # cube's 12 triangles or on a disk) take the wavefront: emitter_sample() samples them one
    # lane at a time (aside_emitter_stage), the vector stage evaluates the BSDF, the MIS weight
    # (none for a point light's delta sample) and the shadow ray; rough lanes redo it in
    # rough_emitter_stage. The image is path_li's bit for bit, with one light or several,
    # beside the sky, mirrors, GGX and Beckmann (in lanes); the lights' emission and a
    # reflectance are differentiated in lanes with the tape's gradients. `direct` (path
    # tracing's first vertex) likewise gives direct_li's image.
    d = room_dict(tmp_path, {"type": integrator} if integrator == "direct" else None)
    light = "lamp.intensity.value"
    if lights in ("point light alone", "point light and Beckmann"):
        for key in ("quad", "strip", "panel"):
            del d[key]
    if lights.startswith("point light"):
        d["lamp"] = LAMP
    if lights == "point light and Beckmann":
        d["plate"] = {"type": "rectangle", "to_world": tr.Transform.translate([0.5, 0.3, 0.4]).rotate([1, 0, 0], -60).scale(0.25),
                      "bsdf": {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.2}}
        d["coat"] = {"type": "sphere", "radius": 0.2, "center": [-0.4, 0.2, -0.2],
                     "bsdf": {"type": "roughplastic", "distribution": "beckmann", "alpha": 0.15}}
    elif lights == "cube light":
        d["box"] = {"type": "cube", "to_world": tr.Transform.translate([0.3, 1.3, 0.2]).scale(0.1),
                    "emitter": {"type": "area", "radiance": 3.0}}
        light = "box.emitter.radiance.value"
    else:
        d["disk"] = {"type": "disk", "to_world": tr.Transform.translate([0, 1.5, 0]).rotate([1, 0, 0], 90).scale(0.2),
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5.0, 4.0, 3.0]}}}
        light = "disk.emitter.radiance.value"
    if lights == "point light, sky, delta and rough BSDFs":
        d["sky"] = {"type": "constant", "radiance": 0.2}
        d["mirror"] = {"type": "sphere", "radius": 0.2, "center": [0.3, 0.25, 0.2], "bsdf": {"type": "conductor"}}
        d["metal"] = {"type": "sphere", "radius": 0.2, "center": [-0.4, 0.2, -0.2],
                      "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}}
        d["plate"] = {"type": "rectangle", "to_world": tr.Transform.translate([0.5, 0.3, 0.4]).rotate([1, 0, 0], -60).scale(0.25),
                      "bsdf": {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.2}}
    scene = tr.load_dict(d)
    wavefront, scalar = render_both(scene, monkeypatch, spp=7, seed=5)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05
    # Without the aside light the image is another: its samples reached the film.
    without = {k: v for k, v in d.items() if k not in ("lamp", "box", "disk")}
    if lights not in ("point light alone", "point light and Beckmann"):
        assert not torch.equal(tr.render(tr.load_dict(without), spp=7, seed=5), wavefront)
    if integrator == "path":
        assert_lanes_give_the_tapes_gradients(scene, [light, "floor.bsdf.reflectance.value"], monkeypatch)


@pytest.mark.parametrize("integrator", [{"max_depth": 1}, {"max_depth": 2}, {"hide_emitters": True},
                                        {"max_depth": 4, "rr_depth": 1}, {"rr_depth": 2}])
@pytest.mark.parametrize("light", ["point", "cube"])
def test22_emitters_sampled_aside_at_every_path_setting(tmp_path, monkeypatch, integrator, light):
    # test21's aside emitters with paths cut at their first or second vertex, with the
    # emitters hidden from the camera, and with roulette from the first vertices: the
    # wavefront's image is still path_li's bit for bit.
    d = room_dict(tmp_path, integrator)
    if light == "point":
        d["lamp"] = LAMP
    else:
        d["box"] = {"type": "cube", "to_world": tr.Transform.translate([0.3, 1.3, 0.2]).scale(0.1),
                    "emitter": {"type": "area", "radiance": 3.0}}
    wavefront, scalar = render_both(tr.load_dict(d), monkeypatch, spp=9, seed=3)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05


@pytest.mark.parametrize("sampler", [{"type": "stratified"}, {"type": "stratified", "jitter": False},
                                     {"type": "multijitter"}, {"type": "orthogonal"}, {"type": "ldsampler"}])
@pytest.mark.parametrize("scene", ["every kind in lanes", "Beckmann shaded aside", "point light, direct"])
def test23_other_samplers_draw_each_vertex_before_the_lanes(tmp_path, monkeypatch, sampler, scene):
    # With a sampler other than `independent` the wavefront draws each vertex's numbers
    # before its stages, one lane at a time by Sampler (draw_stage: the dimensions, the
    # permutations and the jitter path_li's vertex would take), and the stages read them
    # instead of their streams; the vertices shaded aside and emitters sampled aside continue
    # the same sampler. The image is the scalar integrator's bit for bit, with diffuse,
    # mirror, glass, GGX and Beckmann vertices, roulette from the second vertex on, sample
    # counts the sampler rounds up (5 to 9, or to 16 for ldsampler), and `direct`.
    if scene == "point light, direct":
        d = room_dict(tmp_path, {"type": "direct"})
        d["lamp"] = LAMP
        d["plate"] = {"type": "rectangle", "to_world": tr.Transform.translate([0.5, 0.3, 0.4]).rotate([1, 0, 0], -60).scale(0.25),
                      "bsdf": {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.2}}
    else:
        d = room_dict(tmp_path, {"max_depth": 6, "rr_depth": 2})
        d["rough"] = {"type": "cube", "to_world": tr.Transform.translate([0.2, 0.2, 0]).scale(0.2),
                      "bsdf": {"type": "roughconductor", "alpha": 0.3}}
        d["plastic"] = {"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.4, 0.2, 0]),
                        "bsdf": {"type": "roughplastic", "alpha": 0.2}}
        d["glass"] = {"type": "sphere", "radius": 0.15, "to_world": tr.Transform.translate([0.4, 0.15, 0.4]),
                      "bsdf": {"type": "dielectric"}}
        d["satin"] = {"type": "sphere", "radius": 0.15, "to_world": tr.Transform.translate([-0.2, 0.15, 0.5]),
                      "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.4}}
        if scene == "Beckmann shaded aside":  # (several lights, one a sphere, and delta BSDFs)
            d["bulb"] = {"type": "sphere", "radius": 0.05, "to_world": tr.Transform.translate([0.0, 0.8, 0.3]),
                         "emitter": {"type": "area", "radiance": 20.0}}
    independent = tr.render(tr.load_dict(d), spp=5, seed=4)
    d["sensor"]["sampler"] = dict(sampler)
    scene = tr.load_dict(d)
    wavefront, scalar = render_both(scene, monkeypatch, spp=5, seed=4)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05
    assert not torch.equal(scalar, independent)


@pytest.mark.parametrize("sampler", [{"type": "stratified"}, {"type": "multijitter"}, {"type": "orthogonal"},
                                     {"type": "ldsampler"}])
def test24_backward_in_lanes_with_other_samplers(tmp_path, monkeypatch, sampler):
    # The backward pass traces its paths in lanes with any sampler: the film positions of a
    # sample index are drawn by Sampler for the whole tile first (the independent sampler's
    # in SIMD lanes), the paths start from them, and the gradients are the tape's on the
    # same paths. (9 samples per pixel: a square, rows x columns and a prime squared; the
    # ldsampler rounds them to 16.)
    d = room_dict(tmp_path, {"max_depth": 4})
    d["sensor"]["sampler"] = dict(sampler)
    spp = 16 if sampler["type"] == "ldsampler" else 9
    assert_lanes_give_the_tapes_gradients(tr.load_dict(d), ["floor.bsdf.reflectance.value", "quad.emitter.radiance.value"],
                                          monkeypatch, spp=spp)


@pytest.mark.parametrize("integrator", [{"type": "direct"}, {"type": "path", "max_depth": 2},
                                        {"type": "path", "max_depth": 1}])
def test25_last_rays_traced_only_towards_emitters(tmp_path, monkeypatch, integrator):
    # Where every path of a batch is at its last vertex, only the rays that enter an emitting
    # shape's box are traced (WavefrontScene::emitter_boxes): the image stays path_li's bit for
    # bit, with mesh lights, spheres (one of them tiny), a disk and rough and mirror
    # vertices whose BSDF samples aim at them, and fewer rays are traced than path_li traces.
    # With the environment emitting, every ray is traced.
    from torch_rbpt.render import render_with_stats
    d = sphere_lights(room_dict(tmp_path), "spheres and meshes")
    d["integrator"] = integrator
    d["disk"] = {"type": "disk", "to_world": tr.Transform.translate([0.6, 1.4, -0.4]).rotate([1, 0, 0], 90).scale(0.2),
                 "emitter": {"type": "area", "radiance": 3.0}}
    d["mirror"] = {"type": "sphere", "radius": 0.2, "center": [0.3, 0.25, 0.2], "bsdf": {"type": "conductor"}}
    d["metal"] = {"type": "sphere", "radius": 0.2, "center": [-0.4, 0.2, -0.2],
                  "bsdf": {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.1}}
    for sky in (False, True):
        if sky:
            d["sky"] = {"type": "constant", "radiance": 0.2}
        scene = tr.load_dict(d)
        assert uses_wavefront(scene)
        wavefront, rays = render_with_stats(scene, spp=9, seed=4)
        with monkeypatch.context() as m:
            m.setenv("TORCH_RBPT_WAVEFRONT", "0")
            scalar, scalar_rays = render_with_stats(scene, spp=9, seed=4)
        assert torch.equal(wavefront, scalar)
        assert float(scalar.mean()) > 0.05
        # (path_li and direct_li count a few rays otherwise: 6655 against 6655 and 6771 with
        # the sky; without it 4580 against 6779 and 6895, 143 against 2457 at max_depth 1.)
        assert rays > 0.95 * scalar_rays if sky else rays < 0.9 * scalar_rays


@pytest.mark.parametrize("integrator", [{"type": "path"}, {"type": "path", "max_depth": 2}])
def test26_tiles_share_a_chunk_of_samples(tmp_path, monkeypatch, integrator):
    # At a few samples per pixel, consecutive tiles give their samples to one call of
    # trace_wavefront (up to WavefrontChunk), each sample splatted into its own tile's block:
    # 128 x 96 pixels are 8 x 6 tiles, which 1 thread takes in groups of 12, 9, 6, ... and 2
    # threads of 6, 5, 4, ... (a quarter of the tiles left per worker, down to single tiles),
    # with a gaussian's splats reaching neighbouring tiles. The image is path_li's bit for
    # bit, for both thread counts and for spp 1, 3 (groups) and 40 (one tile per call).
    d = room_dict(tmp_path, integrator)
    d["sensor"]["film"].update({"width": 128, "height": 96, "rfilter": {"type": "gaussian"}})
    scene = tr.load_dict(d)
    for spp in (1, 3, 40):
        with torch_threads(1):
            one = tr.render(scene, spp=spp, seed=6)
        with torch_threads(2):
            two = tr.render(scene, spp=spp, seed=6)
        with monkeypatch.context() as m:
            m.setenv("TORCH_RBPT_WAVEFRONT", "0")
            scalar = tr.render(scene, spp=spp, seed=6)
        assert float(scalar.mean()) > 0.01
        assert torch.equal(one, scalar) and torch.equal(two, scalar), spp


def test27_zero_channels_of_inputs_in_lanes(tmp_path, monkeypatch):
    # A reflectance clamped to 0 in a channel (a fit's clamp) would make the lanes' quotient
    # dL . (L - L_before) / rho 0 / 0: they take that channel of rho as 1 in the path's
    # throughput (not in its roulette throughput, so the paths are the tape's), which then
    # gathers dL/drho there up to the channel's next such vertex, and every other record's
    # terms end at the first. Diffuse reflectances (constants the paths meet again and again,
    # a bitmap), a mirror's and a GGX conductor's specular reflectance (its roughness
    # differentiated at the same vertices), radiances gathered after them: in lanes, with the
    # tape's gradients, zero channels included; a dielectric's zero channel takes the tape
    # for the paths that meet it.
    texels = np.random.default_rng(5).uniform(0.1, 0.9, (4, 6, 3)).astype(np.float32)
    texels[..., 1] = 0.0
    tr.write_image(tmp_path / "z.exr", torch.from_numpy(texels))
    d = room_dict(
        tmp_path, {"max_depth": 8},
        mat={"type": "rectangle", "to_world": tr.Transform.translate([0.2, 0.01, 0.4]).rotate([1, 0, 0], -90).scale(0.5),
             "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": str(tmp_path / "z.exr")}}},
        mirror={"type": "sphere", "radius": 0.25, "to_world": tr.Transform.translate([0.3, 0.25, -0.2]),
                "bsdf": {"type": "conductor", "specular_reflectance": {"type": "rgb", "value": [0.9, 0.0, 0.7]}}},
        metal={"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.4, 0.2, -0.2]),
               "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3,
                        "specular_reflectance": {"type": "rgb", "value": [0.0, 0.6, 0.3]}}})
    d["floor"]["bsdf"]["reflectance"]["value"] = [0.8, 0.0, 0.5]
    d["side"]["bsdf"]["reflectance"]["value"] = [0.0, 0.7, 0.3]
    scene = tr.load_dict(d)
    keys = ["floor.bsdf.reflectance.value", "side.bsdf.reflectance.value", "mat.bsdf.reflectance.data",
            "mirror.bsdf.specular_reflectance.value", "metal.bsdf.specular_reflectance.value",
            "metal.bsdf.alpha.value", "quad.emitter.radiance.value", "panel.emitter.radiance.value"]
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=16)
    grads, _, _ = backward(scene, keys, spp=16)
    for key, channel in [("floor.bsdf.reflectance.value", 1), ("side.bsdf.reflectance.value", 0),
                         ("mirror.bsdf.specular_reflectance.value", 1), ("metal.bsdf.specular_reflectance.value", 0)]:
        assert float(grads[key][channel].abs()) > 0, key
    assert float(grads["mat.bsdf.reflectance.data"][..., 1].abs().sum()) > 0

    # A diffuse reflectance zero in every channel: its weight (rho, taken as 1) is the factor
    # 1 that path_li's roulette sees there, so its paths stay in lanes; a mirror's takes the
    # tape (its roulette factor is not its weight).
    with torch.no_grad():
        scene.params["side.bsdf.reflectance.value"].zero_()
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=16)
    assert float(backward(scene, keys, spp=16)[0]["side.bsdf.reflectance.value"].abs().min()) > 0
    with torch.no_grad():
        scene.params["mirror.bsdf.specular_reflectance.value"].zero_()
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=16, some_taped=True)

    d["glass"] = {"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.1, 0.45, 0.6]),
                  "bsdf": {"type": "dielectric", "int_ior": 1.5,
                           "specular_reflectance": {"type": "rgb", "value": [0.9, 0.0, 0.8]}}}
    scene = tr.load_dict(d)
    keys = ["glass.bsdf.specular_reflectance.value", "floor.bsdf.reflectance.value"]
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=16, some_taped=True)


def test28_zero_channels_of_radiances_in_lanes(tmp_path, monkeypatch):
    # A differentiated radiance with zero channels (a light fitted towards a colour, clamped
    # at 0): the lanes read those channels as 1, so its emitter samples are taken (all three
    # zero, the wavefront would skip them) and each emission record carries dC/dLe there;
    # render_bwd takes those terms out of the path's radiance again before the other records'
    # quotients (a reflectance's, a GGX roughness's, whose emitter sample's C_e is the true
    # one). RGB radiances with one and with three zero channels, a scalar one at 0, beside a
    # reflectance with a zero channel of its own: in lanes, with the tape's gradients.
    extra = dict(metal={"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([-0.4, 0.2, -0.2]),
                        "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}})
    d = room_dict(tmp_path, {"max_depth": 6}, **extra)
    d["quad"]["emitter"]["radiance"]["value"] = [6.0, 0.0, 4.0]
    d["side"]["bsdf"]["reflectance"]["value"] = [0.5, 0.6, 0.0]
    keys = ["quad.emitter.radiance.value", "panel.emitter.radiance.value", "strip.emitter.radiance.value",
            "side.bsdf.reflectance.value", "floor.bsdf.reflectance.value", "metal.bsdf.alpha.value"]
    scene = tr.load_dict(d)
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=16)
    grads, _, _ = backward(scene, keys, spp=16)
    assert float(grads["quad.emitter.radiance.value"][1].abs()) > 0
    with torch.no_grad():
        scene.params["panel.emitter.radiance.value"].zero_()
        scene.params["strip.emitter.radiance.value"].zero_()
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=16)
    grads, _, _ = backward(scene, keys, spp=16)
    assert float(grads["panel.emitter.radiance.value"].abs().min()) > 0
    assert float(grads["strip.emitter.radiance.value"].abs().min()) > 0
    # A point light's intensity (sampled aside) and an environment's radiance.
    d = room_dict(tmp_path, {"max_depth": 5})
    d["lamp"] = {"type": "point", "position": [0.3, 1.2, 0.4], "intensity": {"type": "rgb", "value": [3.0, 0.0, 2.0]}}
    d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.0, 0.2, 0.3]}}
    scene = tr.load_dict(d)
    keys = ["lamp.intensity.value", "sky.radiance.value", "floor.bsdf.reflectance.value"]
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=16)
    grads, _, _ = backward(scene, keys, spp=16)
    assert float(grads["lamp.intensity.value"][1].abs()) > 0 and float(grads["sky.radiance.value"][0].abs()) > 0


@pytest.mark.parametrize("lights", ["environment and a sphere", "a sphere only"])
def test29_spheres_alone_take_the_lanes(tmp_path, monkeypatch, lights):
    # A scene without a triangle (spheres under the sky: a material on a ball) takes the
    # wavefront, whose interaction stage has no triangle to gather from: the image bitwise
    # path_li's, and the backward pass in lanes with the tape's gradients.
    d = room_dict(tmp_path, {"max_depth": 5})
    d = {k: v for k, v in d.items() if not isinstance(v, dict) or v.get("type") not in ("rectangle", "obj")}
    d["ground"] = {"type": "sphere", "radius": 50, "center": [0, -50, 0],
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.6, 0.5]}}}
    d["ball"] = {"type": "sphere", "radius": 0.35, "center": [-0.3, 0.35, 0.2],
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "checkerboard", "to_uv": tr.Transform.scale([4, 4, 1])}}}
    d["metal"] = {"type": "sphere", "radius": 0.25, "center": [0.5, 0.25, 0.3],
                  "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}}
    d["glass"] = {"type": "sphere", "radius": 0.2, "center": [0.1, 0.2, 0.8], "bsdf": {"type": "dielectric"}}
    d["inside_out"] = {"type": "sphere", "radius": 0.15, "center": [-0.6, 0.8, 0], "flip_normals": True,
                       "bsdf": {"type": "diffuse"}}
    d["bulb"] = {"type": "sphere", "radius": 0.15, "center": [0.4, 1.2, 0.6],
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [8.0, 7.0, 5.0]}}}
    if lights == "environment and a sphere":
        d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.4, 0.6]}}
    scene = tr.load_dict(d)
    shapes = [v for v in d.values() if isinstance(v, dict) and ("bsdf" in v or "emitter" in v)]
    assert len(shapes) == 6 and all(v["type"] == "sphere" for v in shapes)
    wavefront, scalar = render_both(scene, monkeypatch, spp=7, seed=5)
    assert float(scalar.mean()) > 0.02
    assert torch.equal(wavefront, scalar)
    keys = ["ground.bsdf.reflectance.value", "ball.bsdf.reflectance.color0.value", "bulb.emitter.radiance.value"]
    if lights == "environment and a sphere":
        keys.append("sky.radiance.value")
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch)


@pytest.mark.parametrize("integrator", [{"shading_samples": 3}, {"shading_samples": 4, "hide_emitters": True},
                                        {"emitter_samples": 2, "bsdf_samples": 0},
                                        {"emitter_samples": 0, "bsdf_samples": 3}])
@pytest.mark.parametrize("sampler", ["independent", "stratified"])
def test30_direct_with_several_samples_takes_the_lanes(tmp_path, monkeypatch, integrator, sampler):
    # `direct` with n emitter samples and n BSDF samples (Mitsuba's shading_samples), or n of
    # one kind alone, is n paths of two vertices from the camera ray's first vertex, each of
    # throughput 1/n (path_settings(): sub_paths): the wavefront traces them one after the
    # other from the camera ray, each sample's stream going on, and its image is direct_li's
    # bit for bit, with diffuse, mirror, glass, GGX and Beckmann vertices under mesh, sphere,
    # point and sky lights, the emitters hidden or not, with the independent sampler and a
    # stratified one (whose dimensions go on too).
    d = sphere_lights(room_dict(tmp_path, {"type": "direct", **integrator}), "spheres and meshes")
    d["sky"] = {"type": "constant", "radiance": 0.2}
    d["lamp"] = LAMP
    d["mirror"] = {"type": "sphere", "radius": 0.2, "center": [0.3, 0.25, 0.2], "bsdf": {"type": "conductor"}}
    d["glass"] = {"type": "sphere", "radius": 0.2, "center": [-0.1, 0.45, 0.6], "bsdf": {"type": "dielectric"}}
    d["metal"] = {"type": "sphere", "radius": 0.2, "center": [-0.4, 0.2, -0.2],
                  "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}}
    d["plate"] = {"type": "rectangle", "to_world": tr.Transform.translate([0.5, 0.3, 0.4]).rotate([1, 0, 0], -60).scale(0.25),
                  "bsdf": {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.2}}
    if sampler != "independent":
        d["sensor"]["sampler"] = {"type": sampler}
    scene = tr.load_dict(d)
    wavefront, scalar = render_both(scene, monkeypatch, spp=4, seed=5)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05
    # Its samples are not one sub-path's.
    one = dict(integrator, **{"emitter_samples": min(1, integrator.get("emitter_samples", 1)),
                              "bsdf_samples": min(1, integrator.get("bsdf_samples", 1))})
    one.pop("shading_samples", None)
    d["integrator"] = {"type": "direct", **one}
    assert not torch.equal(tr.render(tr.load_dict(d), spp=4, seed=5), scalar)
    # The backward pass in lanes, with the tape's (direct_li's) gradients: each sub-path's
    # records take the radiance where it ended (an End record) for the end of their terms.
    # A reflectance with a zero channel sends its samples to the tape (its `unit` records
    # bound each other's terms within one path).
    keys = ["floor.bsdf.reflectance.value", "side.bsdf.reflectance.value", "metal.bsdf.alpha.value",
            "plate.bsdf.alpha.value", "bulb.emitter.radiance.value", "quad.emitter.radiance.value"]
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=4)
    with torch.no_grad():
        scene.params["side.bsdf.reflectance.value"].copy_(torch.tensor([0.2, 0.0, 0.3]))
    assert_lanes_give_the_tapes_gradients(scene, keys, monkeypatch, spp=4, some_taped=True)


def test31_room_of_balls_is_a_flat_tree_of_several_nodes(tmp_path, monkeypatch):
    # Twenty balls on the room's floor (diffuse, glass and rough metal) make a tree of several
    # nodes whose primitives are few (BVH::flat beyond one node): its rays are tested in
    # lanes, and the image is path_li's bit for bit.
    d = room_dict(tmp_path, {"max_depth": 5})
    bsdfs = [{"type": "diffuse"}, {"type": "dielectric"}, {"type": "roughconductor", "alpha": 0.2}]
    for i in range(20):
        d[f"ball{i}"] = {"type": "sphere", "radius": 0.06, "center": [-0.8 + 0.4 * (i % 5), 0.06, -0.8 + 0.45 * (i // 5)],
                         "bsdf": bsdfs[i % 3]}
    scene = tr.load_dict(d)
    assert scene._native.bvh_flat and scene._native.bvh_node_count > 1
    wavefront, scalar = render_both(scene, monkeypatch, spp=7, seed=5)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05


@pytest.mark.parametrize("integrator", [{"type": "path", "max_depth": 4}, {"type": "path", "hide_emitters": True},
                                        {"type": "direct", "shading_samples": 3},
                                        {"type": "direct", "shading_samples": 3, "hide_emitters": True}])
def test32_rays_that_escape_end_in_lanes(tmp_path, monkeypatch, integrator):
    # Balls on a floor under the sky, seen against it: the rays that escape end in SIMD
    # lanes (sky_stage) with the sky's emission, MIS-weighted, for a camera ray with
    # throughput 1 (also for `direct`'s sub-paths, whose throughput is 1/n) and none where
    # hide_emitters hides it: the image is the scalar integrator's bit for bit.
    d = room_dict(tmp_path, integrator)
    d = {k: v for k, v in d.items() if not isinstance(v, dict) or v.get("type") not in ("rectangle", "obj")}
    d["floor"] = {"type": "rectangle", "to_world": tr.Transform.rotate([1, 0, 0], -90).scale(1.5), "bsdf": {"type": "diffuse"}}
    d["ball"] = {"type": "sphere", "radius": 0.3, "center": [-0.2, 0.3, 0.1], "bsdf": {"type": "diffuse"}}
    d["metal"] = {"type": "sphere", "radius": 0.2, "center": [0.4, 0.2, 0.3],
                  "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}}
    d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.4, 0.6]}}
    scene = tr.load_dict(d)
    wavefront, scalar = render_both(scene, monkeypatch, spp=6, seed=2)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05
    # The sky seen directly fills a part of the image, or is hidden there.
    seen = tr.render(tr.load_dict({**d, "integrator": {**integrator, "hide_emitters": not integrator.get("hide_emitters", False)}}),
                     spp=6, seed=2)
    assert not torch.equal(seen, scalar)
    background = (scalar if integrator.get("hide_emitters") else seen).sum(-1) == 0
    assert int(background.sum()) > 20


def dome_obj(rings: int, segments: int) -> str:
    """A half sphere of radius 0.25 around (0, 1.3, 0), open at the bottom, with vertex
    normals pointing out: 2 (rings - 1) segments + segments triangles of unequal areas."""
    lines, center = [], (0.0, 1.3, 0.0)
    for i in range(rings + 1):
        theta = 0.5 * math.pi * i / rings
        for j in range(segments):
            phi = 2 * math.pi * j / segments
            n = (math.sin(theta) * math.cos(phi), math.cos(theta), math.sin(theta) * math.sin(phi))
            lines.append("v %f %f %f" % tuple(c + 0.25 * a for c, a in zip(center, n)))
            lines.append("vn %f %f %f" % n)
    for i in range(rings):
        for j in range(segments):
            a, b = i * segments + j + 1, i * segments + (j + 1) % segments + 1
            c, d = a + segments, b + segments
            lines.append(f"f {a}//{a} {c}//{c} {d}//{d}")
            if i > 0:
                lines.append(f"f {a}//{a} {d}//{d} {b}//{b}")
    return "\n".join(lines) + "\n"


def lights_scene(tmp_path, lights):
    """The room with the lights that `lights` names (test33, test34), and the keys of their
    radiances and intensities."""
    (tmp_path / "dome.obj").write_text(dome_obj(4, 12))
    (tmp_path / "long.obj").write_text("".join(f"v {-1.0 + 0.1 * i} 0.25 {0.7 + 0.02 * (i % 3)}\nv {-1.0 + 0.1 * i} 0.25 0.9\n"
                                               for i in range(21)) +
                                       "".join(f"f {2 * i + 1} {2 * i + 3} {2 * i + 4}\nf {2 * i + 1} {2 * i + 4} {2 * i + 2}\n"
                                               for i in range(20)))
    d = room_dict(tmp_path, {"max_depth": 5, "rr_depth": 2})
    keys = []
    if "dome" in lights:
        d["dome"] = {"type": "obj", "filename": str(tmp_path / "dome.obj"),
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [12.0, 9.0, 6.0]}}}
        keys.append("dome.emitter.radiance.value")
    if "strip of 40" in lights:
        d["long"] = {"type": "obj", "filename": str(tmp_path / "long.obj"), "flip_normals": True,
                     "emitter": {"type": "area", "radiance": 3.0}}
        keys.append("long.emitter.radiance.value")
    if lights in ("dome alone", "a cylinder alone"):
        for key in ("quad", "strip", "panel"):
            del d[key]
    if "cylinder" in lights:
        d["tube"] = {"type": "cylinder", "p0": [-0.6, 0.9, -0.3], "p1": [0.4, 1.3, 0.2], "radius": 0.06,
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [9.0, 7.0, 5.0]}}}
        keys.append("tube.emitter.radiance.value")
    if "two cylinders" in lights:
        d["shade"] = {"type": "cylinder", "p0": [0.5, 1.0, 0.1], "p1": [0.5, 1.3, 0.1], "radius": 0.25, "flip_normals": True,
                      "emitter": {"type": "area", "radiance": 5.0}}
        d["disk"] = {"type": "disk", "to_world": tr.Transform.translate([-0.5, 1.4, 0.1]).rotate([1, 0, 0], 90).scale(0.15),
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5.0, 4.0, 3.0]}}}
        keys += ["shade.emitter.radiance.value", "disk.emitter.radiance.value"]
    if "disks" in lights:
        d["disk"] = {"type": "disk", "to_world": tr.Transform.translate([0.5, 1.4, 0.1]).rotate([1, 0, 0], 90).scale(0.15),
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5.0, 4.0, 3.0]}}}
        d["under"] = {"type": "disk", "flip_normals": True,
                      "to_world": tr.Transform.translate([-0.5, 1.2, 0.2]).rotate([1, 0, 0], -90).scale(0.2),
                      "emitter": {"type": "area", "radiance": 4.0}}
        keys += ["disk.emitter.radiance.value", "under.emitter.radiance.value"]
    if "point light" in lights:
        d["lamp"] = LAMP
        keys.append("lamp.intensity.value")
    if lights == "two point lights alone":
        for key in ("quad", "strip", "panel"):
            del d[key]
        d["lamp"] = LAMP
        d["bulb"] = {"type": "point", "position": [-0.4, 1.1, 0.6], "intensity": 2.0}
        keys += ["lamp.intensity.value", "bulb.intensity.value"]
    if "stratified" in lights:
        d["sensor"]["sampler"] = {"type": "stratified"}
    return tr.load_dict(d), keys


LIGHTS = ["dome alone", "dome, strip of 40 and a point light", "strip of 40, stratified",
          "two disks, one flipped, a dome and a point light", "two cylinders, one flipped, a disk and a dome",
          "a cylinder alone", "two point lights alone"]


@pytest.mark.parametrize("lights", LIGHTS)
def test33_lights_sampled_in_lanes(tmp_path, monkeypatch, lights):
    # Area lights on meshes of more than 8 triangles, on disks and on cylinders, and point
    # lights are sampled in SIMD lanes (lane_emitter_stage: each lane's triangle found by a
    # binary search of its light's CDF, its vertices gathered; a disk's or cylinder's point
    # placed by its frame in double) rather than by emitter_sample() one lane at a time: a
    # dome of 84 triangles of unequal areas with vertex normals, a strip of 40 seen from its
    # back (flip_normals), disks seen from their front and from their back (flip_normals), a
    # slanted cylinder and a flipped one lighting the floor through its open end, point
    # lights, beside small mesh lights (the vector stage's own), with the stratified sampler.
    # The image is path_li's bit for bit, and the lights' radiances are differentiated in
    # lanes with the tape's gradients.
    scene, keys = lights_scene(tmp_path, lights)
    wavefront, scalar = render_both(scene, monkeypatch, spp=9, seed=5)
    assert torch.equal(wavefront, scalar)
    assert float(scalar.mean()) > 0.05
    assert_lanes_give_the_tapes_gradients(scene, keys + ["floor.bsdf.reflectance.value"], monkeypatch, spp=9)


@pytest.mark.parametrize("lights", [LIGHTS[1], LIGHTS[3], LIGHTS[4]])
def test34_lights_sampled_aside_as_a_new_emitter_type(tmp_path, monkeypatch, lights):
    # A new emitter type runs in the wavefront with emitters.h's code alone: the lanes whose
    # light the vector stage does not sample get emitter_sample()'s sample one lane at a
    # time (aside_emitter_stage). Every light of test33 taken that way
    # (TORCH_RBPT_WAVEFRONT=aside) gives path_li's image bit for bit, and the tape's
    # gradients in lanes.
    monkeypatch.setenv("TORCH_RBPT_WAVEFRONT", "aside")
    scene, keys = lights_scene(tmp_path, lights)
    wavefront, scalar = render_both(scene, monkeypatch, spp=9, seed=5)
    assert torch.equal(wavefront, scalar)
    assert_lanes_give_the_tapes_gradients(scene, keys + ["floor.bsdf.reflectance.value"], monkeypatch, spp=9)


@pytest.mark.parametrize("plastic", ["ggx", "beckmann, nonlinear", "bitmap, twosided, sky"])
def test35_backward_in_lanes_for_roughplastic(tmp_path, monkeypatch, plastic):
    # A roughplastic's diffuse reflectance rho is a factor of one of its value's two terms,
    # f = ks spec + g(rho) base, g(rho) = rho / (1 - R_int) (rho / (1 - rho R_int) when
    # nonlinear): each of its vertices deposits, per channel, C_e dlog f(wo_e) +
    # (L - L_before - C_e) dlog f(wo_s) with dlog = d log f / d rho (a Term record); and so
    # does its roughness alpha, with dlog = d log f / d alpha (through D, the G1s and the
    # tables, whose derivatives the tape takes to first order). Lanes, with the tape's
    # gradients: a sphere and a panel of it (GGX's; Beckmann's, nonlinear; a bitmap on a
    # twosided panel seen from both sides, under the sky alone), each with both parameters,
    # beside a diffuse reflectance, a Beckmann conductor's roughness and a light's radiance;
    # then the roughness alone, and the reflectance alone. A zero channel of
    # a constant rho needs no `unit` (f keeps ks spec there), and its derivative is not zero;
    # but Beckmann's spec, far from its peak, is zero or tiny in float: where f_c is, it gives
    # no derivative, or a huge dlog_c (whose deposit would magnify the float sums' rounding),
    # and the sample takes the tape.
    texels = np.random.default_rng(7).uniform(0.1, 0.9, (4, 6, 3)).astype(np.float32)
    tr.write_image(tmp_path / "p.exr", torch.from_numpy(texels))
    bitmap = plastic.startswith("bitmap")

    def bsdf():
        rho = ({"type": "bitmap", "filename": str(tmp_path / "p.exr")} if bitmap
               else {"type": "rgb", "value": [0.7, 0.0, 0.3]})
        return {"type": "roughplastic", "distribution": "beckmann" if plastic.startswith("beckmann") else "ggx",
                "alpha": 0.2, "diffuse_reflectance": rho, "nonlinear": "nonlinear" in plastic}
    twosided = "twosided" in plastic
    d = room_dict(
        tmp_path, {"max_depth": 6},
        shiny={"type": "sphere", "radius": 0.25, "to_world": tr.Transform.translate([-0.3, 0.25, 0.1]), "bsdf": bsdf()},
        board={"type": "rectangle", "to_world": tr.Transform.translate([0.5, 0.5, -0.3]).rotate([0, 1, 0], -60).scale(0.35),
               "bsdf": {"type": "twosided", "bsdf": bsdf()} if twosided else bsdf()},
        metal={"type": "sphere", "radius": 0.2, "to_world": tr.Transform.translate([0.3, 0.2, 0.5]),
               "bsdf": {"type": "roughconductor", "alpha": 0.3}})
    radiance = "quad.emitter.radiance.value"
    if "sky" in plastic:
        for key in ("quad", "strip", "panel"):
            del d[key]
        d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 0.6, 0.8]}}
        radiance = "sky.radiance.value"
    scene = tr.load_dict(d)
    field = "data" if bitmap else "value"
    board = f"board.bsdf.{'brdf_0.' if twosided else ''}"
    rho_keys = [f"shiny.bsdf.diffuse_reflectance.{field}", f"{board}diffuse_reflectance.{field}"]
    alpha_keys = ["shiny.bsdf.alpha", f"{board}alpha"]
    others = ["floor.bsdf.reflectance.value", "metal.bsdf.alpha.value", radiance]
    beckmann = plastic.startswith("beckmann")
    assert_lanes_give_the_tapes_gradients(scene, rho_keys + alpha_keys + others, monkeypatch, spp=16, some_taped=beckmann)
    assert_lanes_give_the_tapes_gradients(scene, alpha_keys + others[:1], monkeypatch, spp=16)
    assert_lanes_give_the_tapes_gradients(scene, rho_keys[:1], monkeypatch, spp=16, some_taped=beckmann)
    if not bitmap:
        grads, _, _ = backward(scene, rho_keys, spp=16)
        assert all(float(grads[k][1].abs()) > 0 for k in rho_keys)
