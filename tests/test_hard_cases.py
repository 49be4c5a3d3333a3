"""Hard cases for the whole renderer: sums at enormous sample counts, derivatives at zero
parameters, max_depth 0, Russian roulette at high albedo, scenes far from the origin, tiny
and huge shapes, grazing light, extreme dielectrics and roughness, non-finite values,
degenerate meshes, float32 against float64. Each case has an analytic answer or an exact
invariant (linearity, translation, precision), so a regression shows as a failure."""
import math
import warnings

import pytest
import torch

import torch_rbpt as tr
from conftest import furnace_scene, torch_threads

T = tr.Transform


def _sensor(res, origin=(0, 0, 5), target=(0, 0, 0), up=(0, 1, 0), fov=30, h=None):
    return {"type": "perspective", "fov": fov, "to_world": T.look_at(list(origin), list(target), list(up)),
            "film": {"type": "hdrfilm", "width": res, "height": h or res, "rfilter": {"type": "box"}}}


def _sky(radiance, res=4):
    return tr.load_dict({"type": "scene", "integrator": {"type": "path"}, "sensor": _sensor(res),
                         "sky": {"type": "constant", "radiance": {"type": "rgb", "value": radiance}}})


def _closed_sphere(albedo, radiance, integrator=None, res=4):
    return tr.load_dict({
        "type": "scene", "integrator": integrator or {"type": "path"},
        "sensor": {"type": "perspective", "fov": 40,
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "shell": {"type": "sphere", "radius": 3.0, "flip_normals": True,
                  "bsdf": {"type": "diffuse", "reflectance": albedo},
                  "emitter": {"type": "area", "radiance": radiance}},
    })


def _lit_plane(reflectance=0.5, light=None, max_depth=-1, res=8, offset=(0, 0, 0)):
    """A diffuse square (side 4, z = 0) seen from above, lit by `light` (default: an area
    light of radiance 1 facing down at z = 2); everything translated by `offset`."""
    o = list(offset)
    light = light or {"type": "rectangle", "to_world": T.translate([o[0], o[1], o[2] + 2]) @ T.rotate([1, 0, 0], 180),
                      "emitter": {"type": "area", "radiance": 1.0}}
    return tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": max_depth},
        "sensor": _sensor(res, origin=[o[0], o[1] - 1, o[2] + 6], target=o, fov=35),
        "plane": {"type": "rectangle", "to_world": T.translate(o) @ T.scale([2, 2, 1]),
                  "bsdf": {"type": "diffuse", "reflectance": reflectance}},
        "light": light,
    })


def _grad(scene, key, spp, seed=1, seed_grad=None):
    p = scene.params[key]
    p.requires_grad_(True)
    try:
        image = tr.render(scene, spp=spp, seed=seed, seed_grad=seed if seed_grad is None else seed_grad)
        (g,) = torch.autograd.grad(image.sum(), p)
    finally:
        p.requires_grad_(False)
    return g


# ---- Sums at enormous sample counts ------------------------------------------------------

def test01_pixel_sums_exact_at_two_million_spp():
    # 2^21 samples of (1, 0.1, 0.7): a float32 running sum drifts by ~1% here.
    scene = _sky([1.0, 0.1, 0.7], res=2)
    image = tr.render(scene, spp=2 ** 21, seed=0)
    assert torch.allclose(image, torch.tensor([1.0, 0.1, 0.7]).expand(2, 2, 3), rtol=1e-6, atol=0)


def test02_gradient_sums_exact_at_two_million_spp():
    # d(sum of a 4x4 image)/d(sky radiance) = 16 per channel. On one thread, a float32 gradient
    # buffer stalls at 8 once it holds 2^24 increments of 2^-21.
    scene = _sky([1.0, 0.1, 0.7], res=4)
    with torch_threads(1):
        g = _grad(scene, "sky.radiance.value", spp=2 ** 21)
    assert torch.allclose(g, torch.full((3,), 16.0), rtol=1e-6, atol=0)


# ---- Derivatives at zero parameters --------------------------------------------------------

@pytest.mark.parametrize("light", ["area", "point"])
def test03_emitter_derivative_does_not_vanish_at_zero(light):
    # The image is linear in the emitted radiance: its derivative is the same at 0 and at 1,
    # path for path (same seeds, replayed).
    point = {"type": "point", "position": [0.5, 0.3, 2.0], "intensity": 1.0}
    scene = _lit_plane(light=point if light == "point" else None)
    key = "light.intensity.value" if light == "point" else "light.emitter.radiance.value"
    g1 = _grad(scene, key, spp=16)
    with torch.no_grad():
        scene.params[key].zero_()
    g0 = _grad(scene, key, spp=16)
    assert float(g1.sum()) > 1.0
    assert torch.allclose(g0, g1, rtol=1e-5)


def test04_reflectance_derivative_does_not_vanish_at_zero():
    # One flat diffuse plane under an area light, direct illumination only (max_depth 2): the
    # image is affine in the reflectance and the derivative is the same at 0 and at 0.5. At 0
    # every path has zero throughput after its first bounce; the light it then reaches by
    # BSDF sampling must still count (Mitsuba drops it).
    scene = _lit_plane(reflectance=0.5, max_depth=2)
    key = "plane.bsdf.reflectance.value"
    g_half = _grad(scene, key, spp=32)
    tangent = {key: torch.ones(1)}
    d_half = tr.render_forward(scene, tangent, spp=32, seed=1)
    with torch.no_grad():
        scene.params[key].zero_()
    g_zero = _grad(scene, key, spp=32)
    d_zero = tr.render_forward(scene, tangent, spp=32, seed=1)
    assert float(g_half) > 1.0
    assert float(g_zero) == pytest.approx(float(g_half), rel=1e-5)
    assert torch.allclose(d_zero, d_half, rtol=1e-5, atol=1e-7)
    assert float(d_zero.sum()) == pytest.approx(float(g_half), rel=1e-4)


def test04b_zero_reflectance_derivative_through_many_bounces():
    # With every bounce (light and plane reflect each other) and no roulette, the image is a
    # polynomial in the reflectance on fixed paths: its derivative at 0, by reverse and by
    # forward mode, is the slope of a tiny finite difference (float64, same samples).
    key = "plane.bsdf.reflectance.value"
    scene = _lit_plane(reflectance=0.0, max_depth=8).to(torch.float64)
    scene.integrator.rr_depth = 100
    g = _grad(scene, key, spp=16)
    d = tr.render_forward(scene, {key: torch.ones(1, dtype=torch.float64)}, spp=16, seed=1)
    i0 = tr.render(scene, spp=16, seed=1)
    with torch.no_grad():
        scene.params[key].fill_(1e-6)
    i1 = tr.render(scene, spp=16, seed=1)
    slope = float((i1 - i0).sum()) / 1e-6
    assert slope > 1.0
    assert float(g) == pytest.approx(slope, rel=1e-4)
    assert float(d.sum()) == pytest.approx(slope, rel=1e-4)


# ---- Path length ---------------------------------------------------------------------------

@pytest.mark.parametrize("max_depth", [0, 1, 2, 3, 6])
def test05_every_max_depth_truncates_the_series(max_depth):
    # Inside a closed sphere emitting 1 with albedo 0.5: sum_{k < max_depth} 0.5^k.
    # max_depth 0 is black, as in Mitsuba (no vertex at all, not even emitters seen).
    scene = _closed_sphere(0.5, 1.0, {"type": "path", "max_depth": max_depth})
    image = tr.render(scene, spp=2048, seed=2).double()
    expected = sum(0.5 ** k for k in range(max_depth))
    if max_depth <= 1:
        assert torch.equal(image, torch.full_like(image, expected))
    else:
        assert float(image.mean()) == pytest.approx(expected, rel=5e-3)


def test06_russian_roulette_converges_at_high_albedo():
    # Albedo 0.999 and Le = 0.001: L = 1, reached only through ~1000 bounces. A survival
    # probability capped at 0.95 lets weights grow 5% a bounce (unbounded variance; the
    # mean came out at 0.22); roulette on the throughput itself keeps weights bounded.
    scene = _closed_sphere(0.999, 0.001, res=4)
    image = tr.render(scene, spp=1024, seed=3).double()   # 16k paths
    stderr = float(image.std()) / math.sqrt(image.numel())
    assert stderr < 0.03
    assert abs(float(image.mean()) - 1.0) < 4 * stderr + 5e-3


def test07_without_russian_roulette_the_series_is_exact():
    scene = _closed_sphere(0.9, 1.0, {"type": "path", "max_depth": 12, "rr_depth": 100})
    image = tr.render(scene, spp=512, seed=4).double()
    expected = sum(0.9 ** k for k in range(12))
    assert float(image.mean()) == pytest.approx(expected, rel=5e-3)


# ---- Geometry far from the origin, tiny and huge shapes -----------------------------------

def _ball_on_floor(offset, res=32):
    o = list(offset)
    return tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "sensor": _sensor(res, origin=[o[0], o[1] + 3, o[2] + 6], target=[o[0], o[1] + 0.5, o[2]], fov=40),
        "floor": {"type": "rectangle",
                  "to_world": T.translate(o) @ T.rotate([1, 0, 0], -90) @ T.scale([4, 4, 1]),
                  "bsdf": {"type": "diffuse", "reflectance": 0.8}},
        "ball": {"type": "sphere", "center": [o[0], o[1] + 1, o[2]], "radius": 1.0,
                 "bsdf": {"type": "diffuse", "reflectance": 0.5}},
        "light": {"type": "rectangle",
                  "to_world": T.translate([o[0], o[1] + 4, o[2]]) @ T.rotate([1, 0, 0], 90),
                  "emitter": {"type": "area", "radiance": 4.0}},
    })


def test08_scene_far_from_the_origin_keeps_its_contact_shadows():
    # The same scene translated by 1e5: offsets scaled by the distance to the origin
    # (8.9 units there) skipped the ball, and the blocks around it came out 32-35% too bright.
    near = tr.render(_ball_on_floor([0, 0, 0]), spp=64, seed=5)
    far = tr.render(_ball_on_floor([1e5, 0, 1e5]), spp=64, seed=6)
    blocks = lambda img: img.mean(-1).reshape(4, 8, 4, 8).mean((1, 3))
    b_near, b_far = blocks(near), blocks(far)
    lit = b_near > 0.01
    assert int(lit.sum()) >= 12
    assert float(((b_far - b_near) / b_near)[lit].abs().max()) < 0.08
    assert float(far.mean()) == pytest.approx(float(near.mean()), rel=0.02)


@pytest.mark.parametrize("radius", [1e-4, 1.0, 1e4])
def test09_tiny_and_huge_spheres_in_a_furnace(radius):
    # A diffuse sphere of albedo 0.5 under a unit sky reflects 0.5 at any scale.
    scene = tr.load_dict({
        "type": "scene", "integrator": {"type": "path"},
        "sensor": {**_sensor(8, origin=[0, 0, 5 * radius], fov=30),
                   "near_clip": radius, "far_clip": 100 * radius},
        "ball": {"type": "sphere", "radius": radius, "bsdf": {"type": "diffuse", "reflectance": 0.5}},
        "sky": {"type": "constant", "radiance": 1.0},
    })
    image = tr.render(scene, spp=1024, seed=7)
    center = image[3:5, 3:5].double()
    assert float(center.mean()) == pytest.approx(0.5, abs=0.01)


def test10_huge_sphere_near_its_horizon():
    # A sphere of radius 1e5 seen from 10 units above it, looking at its horizon: every pixel
    # below the horizon is the furnace's 0.5 (a hit point rebuilt in float read 0.23-0.42).
    R = 1e5
    scene = tr.load_dict({
        "type": "scene", "integrator": {"type": "path"},
        "sensor": _sensor(32, origin=[0, 10, 0], target=[0, 10, -100], fov=30),
        "ball": {"type": "sphere", "center": [0, -R, 0], "radius": R,
                 "bsdf": {"type": "diffuse", "reflectance": 0.5}},
        "sky": {"type": "constant", "radiance": 1.0},
    })
    image = tr.render(scene, spp=256, seed=8).mean(-1)
    ground = image[18:]          # rows below the horizon (which lies in row 16)
    assert float(ground.mean()) == pytest.approx(0.5, abs=0.01)
    assert float(ground.mean(1).min()) > 0.47
    assert torch.equal(image[:14], torch.ones_like(image[:14]))


# ---- Emitters: grazing, tiny and bright ----------------------------------------------------

def _point_lit_pixel(position, intensity, res=9):
    scene = _lit_plane(reflectance=0.5, light={"type": "point", "position": position, "intensity": intensity},
                       max_depth=2, res=res)
    return scene


@pytest.mark.parametrize("elevation", [60.0, 5.0, 0.5])
def test11_grazing_point_light_follows_the_cosine_law(elevation):
    # L = rho / pi * I cos(theta) / d^2 at the point of the plane under the centre pixel.
    d = 3.0
    theta = math.radians(90.0 - elevation)
    pos = [d * math.sin(theta), 0.0, d * math.cos(theta)]
    scene = tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 2},
        "sensor": _sensor(9, origin=[0, 0, 4], target=[0, 0, 0], fov=1.0),
        "plane": {"type": "rectangle", "to_world": T.scale([4, 4, 1]),
                  "bsdf": {"type": "diffuse", "reflectance": 0.5}},
        "light": {"type": "point", "position": pos, "intensity": 10.0},
    })
    image = tr.render(scene, spp=16, seed=9)
    expected = 0.5 / math.pi * 10.0 * math.cos(theta) / d ** 2
    assert float(image[4, 4].mean()) == pytest.approx(expected, rel=0.02)


def test12_tiny_bright_sphere_light_acts_as_a_point_light():
    # A sphere of radius 1e-3 with radiance Le has intensity Le * pi r^2 towards any side.
    r, Le = 1e-3, 1e6
    scene = tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 2},
        "sensor": _sensor(9, origin=[0, 0, 4], target=[0, 0, 0], fov=1.0),
        "plane": {"type": "rectangle", "to_world": T.scale([4, 4, 1]),
                  "bsdf": {"type": "diffuse", "reflectance": 0.5}},
        "light": {"type": "sphere", "center": [1, 0, 2], "radius": r,
                  "emitter": {"type": "area", "radiance": Le}},
    })
    image = tr.render(scene, spp=64, seed=10)
    cos, d2 = 2 / math.sqrt(5), 5.0
    expected = 0.5 / math.pi * Le * math.pi * r * r * cos / d2
    assert float(image[4, 4].mean()) == pytest.approx(expected, rel=0.01)
    assert torch.isfinite(image).all()


def test13_lights_on_surfaces():
    # A point light lying on a plane lights it at grazing incidence only (cos = 0), and a
    # spherical light resting on the plane touches it in one point: both render finite,
    # with no dropped samples, and the sphere's light falls off from its contact point.
    point = _lit_plane(light={"type": "point", "position": [0.3, 0.2, 0.0], "intensity": 5.0}, max_depth=2)
    ball = _lit_plane(light={"type": "sphere", "center": [0, 0, 0.5], "radius": 0.5,
                             "emitter": {"type": "area", "radiance": 1.0}}, max_depth=2, res=16)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dark = tr.render(point, spp=16, seed=11)
        lit = tr.render(ball, spp=64, seed=11)
    assert float(dark.abs().max()) == 0.0
    assert torch.isfinite(lit).all()
    row = lit[8].mean(-1)
    assert float(row[0]) > 0 and float(row[2]) > float(row[0])


# ---- Materials at their extremes -----------------------------------------------------------

@pytest.mark.parametrize("alpha,lo", [(1e-4, 0.99), (0.05, 0.97), (1.0, 0.25)])
def test14_rough_conductor_furnace_from_tiny_to_huge_roughness(alpha, lo):
    # A white rough conductor under a unit sky: energy never exceeds 1; at small roughness
    # nearly all of it is reflected (single scattering loses energy only at large alpha).
    scene = tr.load_dict({
        "type": "scene", "integrator": {"type": "path"},
        "sensor": _sensor(8, fov=30),
        "ball": {"type": "sphere", "bsdf": {"type": "roughconductor", "alpha": alpha, "distribution": "ggx"}},
        "sky": {"type": "constant", "radiance": 1.0},
    })
    image = tr.render(scene, spp=512, seed=12)
    center = float(image[3:5, 3:5].mean())
    assert torch.isfinite(image).all()
    assert lo < center < 1.0 + 5e-3


@pytest.mark.parametrize("int_ior", [1.0, 1.5, 10.0])
def test15_dielectric_sphere_in_a_furnace_is_invisible(int_ior):
    # A lossless dielectric under a unit sky: every path ends in the sky, L = 1 exactly for an
    # index-matched sphere, and in expectation for any other index (including the strong
    # total internal reflection of eta = 10).
    scene = tr.load_dict({
        "type": "scene", "integrator": {"type": "path"},
        "sensor": _sensor(8, fov=30),
        "ball": {"type": "sphere", "bsdf": {"type": "dielectric", "int_ior": int_ior, "ext_ior": 1.0}},
        "sky": {"type": "constant", "radiance": 1.0},
    })
    image = tr.render(scene, spp=256, seed=13).double()
    if int_ior == 1.0:
        assert torch.allclose(image, torch.ones_like(image), atol=1e-6)
    else:
        assert float(image.mean()) == pytest.approx(1.0, abs=0.01)


def test16_reflectance_above_one_scales_linearly():
    # Parameters beyond physical bounds are the user's choice: a one-bounce image is linear.
    scene = _lit_plane(reflectance=0.5, max_depth=2)
    a = tr.render(scene, spp=16, seed=14)
    with torch.no_grad():
        scene.params["plane.bsdf.reflectance.value"].fill_(1.5)
    b = tr.render(scene, spp=16, seed=14)
    lit = a.mean(-1) > 0
    assert lit.any()
    assert torch.allclose(b[lit], 3 * a[lit], rtol=1e-5)


# ---- Bad values ----------------------------------------------------------------------------

@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test17_non_finite_parameter_is_an_error_naming_it(value):
    scene = _lit_plane()
    with torch.no_grad():
        scene.params["light.emitter.radiance.value"].fill_(value)
    with pytest.raises(ValueError, match=r"light\.emitter\.radiance\.value.*non-finite"):
        tr.render(scene, spp=1)


def test18_non_finite_texel_is_an_error_naming_the_texture(tmp_path):
    texels = torch.full((4, 4, 3), 0.5)
    texels[1, 2, 0] = float("nan")
    tr.write_image(tmp_path / "t.exr", torch.zeros(4, 4, 3))
    scene = tr.load_dict({
        "type": "scene", "sensor": _sensor(4),
        "plane": {"type": "rectangle",
                  "bsdf": {"type": "diffuse", "id": "mat",
                           "reflectance": {"type": "bitmap", "filename": str(tmp_path / "t.exr")}}},
        "sky": {"type": "constant", "radiance": 1.0},
    })
    key = next(k for k in scene.params.keys() if k.endswith(".data"))
    with torch.no_grad():
        scene.params[key].copy_(texels.reshape(scene.params[key].shape))
    with pytest.raises(ValueError, match=key.replace(".", r"\.") + ".*non-finite"):
        tr.render(scene, spp=1)


def test18b_exr_with_a_non_finite_texel_is_refused_at_load(tmp_path):
    # Mitsuba reads it and renders a dark image; we name the file and the texel.
    texels = torch.full((4, 4, 3), 0.5)
    texels[2, 1, 1] = float("inf")
    tr.write_image(tmp_path / "bad.exr", texels)
    with pytest.raises(tr.SceneError, match=r"bad\.exr.*non-finite.*row 2, column 1, channel 1"):
        tr.load_dict({"type": "scene", "sensor": _sensor(4),
                      "plane": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {
                          "type": "bitmap", "filename": str(tmp_path / "bad.exr")}}}})


def test19_non_finite_samples_are_counted_and_reported():
    # Finite inputs whose product overflows: samples that become infinite inside the
    # integrator are dropped from the image and reported, never silently.
    scene = _lit_plane(reflectance=1e30)
    with torch.no_grad():
        scene.params["light.emitter.radiance.value"].fill_(1e30)
    with pytest.warns(RuntimeWarning, match=r"non-finite value"):
        image = tr.render(scene, spp=2)
    assert torch.isfinite(image).all()


def test20_degenerate_triangles_render_finite(tmp_path):
    # A mesh whose faces include zero-area ones (a repeated vertex, collinear vertices), used
    # as a surface and as an emitter (zero-area faces are never sampled).
    (tmp_path / "m.obj").write_text(
        "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nv 0 0 0\nv 2 2 0\n"
        "f 1 2 3\nf 1 3 4\nf 1 5 3\nf 2 2 2\nf 1 3 6\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for emitter in [False, True]:
            mesh = {"type": "obj", "filename": str(tmp_path / "m.obj"), "bsdf": {"type": "diffuse"}}
            if emitter:
                mesh["emitter"] = {"type": "area", "radiance": 1.0}
            scene = tr.load_dict({"type": "scene", "sensor": _sensor(8), "m": mesh,
                                  "sky": {"type": "constant", "radiance": 0.5}})
            image = tr.render(scene, spp=16, seed=15)
            assert torch.isfinite(image).all()
            assert float(image[4, 4].mean()) > (0.9 if emitter else 0.2)


# ---- Precision -----------------------------------------------------------------------------

def test21_float32_and_float64_renders_agree():
    # Geometry and sampling are float in both; only spectral arithmetic differs.
    s32 = furnace_scene(0.7, res=8)
    s64 = furnace_scene(0.7, res=8, dtype=torch.float64)
    a = tr.render(s32, spp=64, seed=16).double()
    b = tr.render(s64, spp=64, seed=16)
    assert b.dtype == torch.float64
    assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)
    g32 = _grad(s32, "ball.bsdf.reflectance.value", spp=16).double()
    g64 = _grad(s64, "ball.bsdf.reflectance.value", spp=16)
    assert torch.allclose(g32, g64, rtol=1e-4)
