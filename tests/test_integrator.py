"""Integrators and the render loop (csrc/integrator.h, render.cpp): analytic furnace scenes,
determinism across thread counts, bands of rows, seeds."""
import math

import pytest
import torch

import torch_rbpt as tr
from conftest import ROOT, furnace_scene, torch_threads


def _center(image, k=2):
    h, w = image.shape[:2]
    return image[h // 2 - k:h // 2 + k, w // 2 - k:w // 2 + k]


@pytest.mark.parametrize("albedo", [0.3, 0.8])
def test01_furnace_sphere_in_unit_environment(albedo):
    # A convex diffuse sphere under a uniform unit sky reflects exactly its albedo.
    scene = furnace_scene(albedo, res=8)
    image = tr.render(scene, spp=2048, seed=3)
    center = _center(image).double()
    stderr = center.std() / math.sqrt(center.numel()) + 1e-3
    assert abs(float(center.mean()) - albedo) < 4 * float(stderr) + 2e-3
    assert float(image[0, 0].mean()) == pytest.approx(1.0, abs=1e-6)  # the sky itself


def _closed_sphere(albedo, radiance, integrator=None):
    return tr.load_dict({
        "type": "scene",
        "integrator": integrator or {"type": "path"},
        "sensor": {"type": "perspective", "fov": 40,
                   "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}}},
        "shell": {"type": "sphere", "radius": 3.0, "flip_normals": True,
                  "bsdf": {"type": "diffuse", "reflectance": albedo},
                  "emitter": {"type": "area", "radiance": radiance}},
    })


@pytest.mark.parametrize("albedo", [0.5, 0.8])
def test02_closed_emitting_sphere_converges_to_geometric_series(albedo):
    # Inside a closed diffuse sphere that emits Le everywhere: L = Le / (1 - albedo),
    # which exercises every bounce, emitter sampling + MIS, and Russian roulette.
    scene = _closed_sphere(albedo, 1.0)
    image = tr.render(scene, spp=4096, seed=1).double()
    expected = 1.0 / (1.0 - albedo)
    stderr = image.std() / math.sqrt(image.numel())
    assert abs(float(image.mean()) - expected) < 4 * float(stderr) + 2e-3 * expected


def test03_max_depth_truncates_the_series():
    # max_depth = 3: emission seen directly plus two bounces.
    scene = _closed_sphere(0.5, 1.0, {"type": "path", "max_depth": 3})
    image = tr.render(scene, spp=4096, seed=2).double()
    assert float(image.mean()) == pytest.approx(1 + 0.5 + 0.25, rel=5e-3)
    direct_only = _closed_sphere(0.5, 1.0, {"type": "path", "max_depth": 1})
    assert torch.equal(tr.render(direct_only, spp=4), torch.ones(4, 4, 3))


def test04_direct_integrator_one_bounce():
    for es, bs in [(1, 1), (1, 0), (0, 1), (2, 3), (3, 3), (4, 0), (0, 2)]:
        scene = _closed_sphere(0.5, 1.0, {"type": "direct", "emitter_samples": es, "bsdf_samples": bs})
        image = tr.render(scene, spp=2048, seed=4).double()
        assert float(image.mean()) == pytest.approx(1.5, rel=5e-3), (es, bs)


def test04b_hide_emitters_drops_only_directly_seen_emission():
    scene = _closed_sphere(0.5, 1.0, {"type": "path", "hide_emitters": True})
    image = tr.render(scene, spp=4096, seed=6).double()
    # Le / (1 - a) without the directly seen Le.
    assert float(image.mean()) == pytest.approx(1.0, rel=5e-3)


def test05_same_image_for_one_and_two_threads(shared):
    scene = tr.load_file(shared / "cbox/cbox.xml", res=24)
    with torch_threads(1):
        one = tr.render(scene, spp=8, seed=5)
    with torch_threads(2):
        two = tr.render(scene, spp=8, seed=5)
    assert torch.equal(one, two)


def test05b_same_derivative_image_for_one_and_two_threads(shared):
    # Forward mode splats tangents too (the film's tangent sums), in the same fixed order.
    scene = tr.load_file(shared / "cbox/cbox.xml", res=32)
    tangents = {"red.reflectance.value": torch.tensor([1.0, 0.0, 0.0])}
    with torch_threads(1):
        one = tr.render_forward(scene, tangents=tangents, spp=8, seed=5)
    with torch_threads(2):
        two = tr.render_forward(scene, tangents=tangents, spp=8, seed=5)
    assert one.abs().sum() > 0 and torch.equal(one, two)


def test06_bands_of_rows_equal_the_full_image(shared):
    scene = tr.load_file(shared / "cbox/cbox.xml", res=16)
    full = tr.render(scene, spp=4, seed=9)
    parts = torch.cat([tr.render(scene, spp=4, seed=9, rows=(a, b)) for a, b in [(0, 5), (5, 16)]])
    assert torch.equal(full, parts)


def test07_seed_changes_noise_not_expectation():
    scene = tr.load_file(ROOT / "torch_rbpt/scenes/cornell_box.xml", res=16)
    a, b = tr.render(scene, spp=64, seed=0), tr.render(scene, spp=64, seed=1)
    assert not torch.equal(a, b)
    # Compare away from the light, whose partly covered pixels dominate the variance.
    lit = (a.sum(-1) > 3) | (b.sum(-1) > 3)
    assert float(a[~lit].mean()) == pytest.approx(float(b[~lit].mean()), rel=0.05)


def test08_crop_window_renders_the_same_pixels(shared):
    scene = tr.load_file(shared / "cbox/cbox.xml", res=16)
    full = tr.render(scene, spp=4, seed=2)
    scene.sensor.film.crop = (3, 5, 6, 4)
    crop = tr.render(scene, spp=4, seed=2)
    assert crop.shape == (4, 6, 3)
    # Box-filtered pixels are identical; with the tent filter only edge pixels may differ
    # (samples stay inside the crop window, as in Mitsuba).
    torch.testing.assert_close(crop[1:-1, 1:-1], full[6:8, 4:8])


def test09_bad_arguments_raise():
    scene = furnace_scene(0.5, res=4)
    with pytest.raises(ValueError, match="spp must be a positive int"):
        tr.render(scene, spp=0)
    with pytest.raises(ValueError, match="seed"):
        tr.render(scene, spp=1, seed=-1)


@pytest.mark.parametrize("integrator", [{"type": "path", "max_depth": 2}, {"type": "direct"}])
def test10_no_shadow_ray_towards_an_emitter_the_bsdf_cannot_reflect(integrator):
    # A diffuse floor seen from above, lit by a point light below it: the BSDF is zero for
    # every emitter sample, so no shadow ray is cast (only camera rays and BSDF rays), and
    # the image is black. With the light above, every floor sample also casts a shadow ray.
    from torch_rbpt.render import render_with_stats

    def floor_scene(light_y):
        return tr.load_dict({
            "type": "scene", "integrator": integrator,
            "sensor": {"type": "perspective", "fov": 30,
                       "to_world": tr.Transform.look_at([0, 5, 0.01], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}}},
            "floor": {"type": "rectangle",
                      "to_world": tr.Transform.rotate([1, 0, 0], -90) @ tr.Transform.scale([10, 10, 10]),
                      "bsdf": {"type": "diffuse"}},
            "light": {"type": "point", "position": [0, light_y, 0], "intensity": 1.0},
        })

    samples = 4 * 4 * 8
    image, dark_rays = render_with_stats(floor_scene(-1.0), 8)
    # Camera rays, and the BSDF rays (which escape) where they are traced: path_li traces
    # them, the wavefront none (no shape emits, so they cannot find an emitter).
    assert dark_rays in (samples, 2 * samples)
    assert float(image.abs().max()) == 0.0
    image, rays = render_with_stats(floor_scene(1.0), 8)
    assert rays == dark_rays + samples  # a shadow ray per sample
    assert float(image.min()) > 0.0
