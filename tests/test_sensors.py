"""The sensors (csrc/camera.h): `orthographic` and `thinlens` rays against Mitsuba 3.9.1's
`sensor.sample_ray` (tests/references/sensors_samplers/rays.json), their geometry (parallel
rays, the focal plane), their parameters and errors, and renders against Mitsuba's
references (tests/references/make_sensor_sampler_references.py)."""
import json

import numpy as np
import pytest
import torch

import torch_rbpt as tr
from conftest import REFERENCES

FOLDER = REFERENCES / "sensors_samplers"
RAYS = json.loads((FOLDER / "rays.json").read_text())["sensors"]
REFS = json.loads((FOLDER / "references.json").read_text())["references"]
T = tr.Transform


def load_sensor(desc: dict):
    """Our sensor for a rays.json description (film 64 x 48, optional crop)."""
    d = {k: v for k, v in desc.items() if k not in ("to_world", "crop")}
    film = {"type": "hdrfilm", "width": 64, "height": 48}
    if "crop" in desc:
        x, y, w, h = desc["crop"]
        film.update(crop_offset_x=x, crop_offset_y=y, crop_width=w, crop_height=h)
    d["film"] = film
    if "to_world" in desc:
        kind, *args = desc["to_world"]
        d["to_world"] = (T.scale(args[0]) if kind == "scale" else
                         T.look_at(args[0], args[1], args[2]) @ T.scale(args[3]))
    return tr.load_dict({"type": "scene", "sensor": d}).sensor


def rays(sensor, positions, apertures):
    """Our rays for position samples in [0, 1]^2 of the crop window: (o, d, tmin, tmax)."""
    x, y, w, h = sensor.film.crop_window()
    pixels = torch.tensor(positions, dtype=torch.float32) * torch.tensor([w, h]) + torch.tensor([x, y])
    return tr._C.camera_rays(sensor.native(), pixels, torch.tensor(apertures, dtype=torch.float32))


@pytest.mark.parametrize("name", list(RAYS))
def test01_rays_match_mitsuba(name):
    """Mitsuba's rays start on the near plane with maxt = distance to the far plane; ours
    start at o + tmin d and end at o + tmax d. Origins, directions and lengths agree."""
    entry = RAYS[name]
    sensor = load_sensor(entry["sensor"])
    o, d, tmin, tmax = rays(sensor, [r["position"] for r in entry["rays"]], [r["aperture"] for r in entry["rays"]])
    start = o + tmin[:, None] * d
    expected_o = torch.tensor([r["o"] for r in entry["rays"]])
    scale = float(expected_o.abs().max())
    torch.testing.assert_close(start, expected_o, rtol=0, atol=2e-6 * max(scale, 1.0))
    torch.testing.assert_close(d, torch.tensor([r["d"] for r in entry["rays"]]), rtol=0, atol=2e-6)
    torch.testing.assert_close(tmax - tmin, torch.tensor([r["maxt"] for r in entry["rays"]]), rtol=2e-6, atol=1e-6)
    # Every ray's weight is 1 (we apply none).
    assert all(r["weight"] == [1.0, 1.0, 1.0] for r in entry["rays"])


def test02_orthographic_rays_are_parallel_and_span_the_scaled_region():
    sensor = load_sensor({"type": "orthographic", "to_world": ("scale", [2.5, 0.5, 1])})
    u = np.random.default_rng(0).random((64, 2)).tolist()
    o, d, tmin, tmax = rays(sensor, u, [[0.5, 0.5]] * 64)
    assert torch.equal(d, torch.tensor([[0.0, 0.0, 1.0]]).expand(64, 3))
    # x in [-2.5, 2.5] (left to right: +x is image left), y in [-0.5 * 48/64, ...] (top to bottom).
    u = torch.tensor(u)
    torch.testing.assert_close(o[:, 0], 2.5 * (1 - 2 * u[:, 0]))
    torch.testing.assert_close(o[:, 1], 0.5 * 0.75 * (1 - 2 * u[:, 1]))
    assert torch.all(tmin == 0)


def test03_thinlens_rays_through_a_pixel_meet_on_the_focal_plane():
    """All lens samples of one film position reach the same point at depth focus_distance
    (local z), the point the pinhole (perspective) ray reaches; and a lens point lies on the
    aperture disk."""
    desc = {"type": "thinlens", "aperture_radius": 0.2, "focus_distance": 3.0, "fov": 50,
            "to_world": ("lookat_scale", [1, 2, 3], [0, 0, 0], [0, 1, 0], [1, 1, 1])}
    sensor = load_sensor(desc)
    pinhole = tr.load_dict({"type": "scene", "sensor": {
        "type": "perspective", "fov": 50, "to_world": T.look_at([1, 2, 3], [0, 0, 0], [0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 64, "height": 48}}}).sensor
    rng = np.random.default_rng(1)
    lens = rng.random((32, 2)).tolist()
    forward = -torch.tensor([1.0, 2, 3]) / np.sqrt(14)
    for pos in ([0.5, 0.5], [0.1, 0.8], [0.93, 0.02]):
        o, d, _, _ = rays(sensor, [pos] * 32, lens)
        t = 3.0 / (d @ forward)  # depth along the optical axis
        focus = o + t[:, None] * d
        po, pd, _, _ = rays(pinhole, [pos], [[0.5, 0.5]])
        expected = po + (3.0 / float(pd[0] @ forward)) * pd
        torch.testing.assert_close(focus, expected.expand(32, 3), rtol=0, atol=2e-5)
        r = (o - torch.tensor([1.0, 2, 3])).norm(dim=1)
        assert float(r.max()) <= 0.2 + 1e-6 and float(r.max()) > 0.15
        assert torch.allclose(o @ forward, torch.tensor([1.0, 2, 3]) @ forward, atol=1e-5)


def test04_parameters_defaults_and_errors():
    s = load_sensor({"type": "thinlens", "aperture_radius": 0.1, "far_clip": 100.0})
    assert (s.type, s.aperture_radius, s.focus_distance) == ("thinlens", 0.1, 100.0)  # far_clip
    assert abs(s.x_fov() - RAYS["thinlens_default"]["traverse_values"]["x_fov"]) < 1e-4  # 50 mm
    assert load_sensor({"type": "thinlens", "aperture_radius": 0.0}).aperture_radius == 2.0 ** -24
    with pytest.raises(tr.SceneError, match="missing parameter 'aperture_radius'"):
        load_sensor({"type": "thinlens"})
    with pytest.raises(tr.SceneError, match="scale factors in to_world are not allowed"):
        load_sensor({"type": "thinlens", "aperture_radius": 0.1, "to_world": ("scale", [2, 2, 2])})
    with pytest.raises(tr.SceneError, match="orthographic: unsupported parameter 'fov'"):
        load_sensor({"type": "orthographic", "fov": 30})
    with pytest.raises(tr.SceneError, match="orthographic: to_world must be invertible"):
        load_sensor({"type": "orthographic", "to_world": ("scale", [1, 0, 1])})
    with pytest.raises(tr.SceneError, match="unsupported sensor plugin 'radiancemeter'"):
        tr.load_dict({"type": "scene", "sensor": {"type": "radiancemeter"}})


@pytest.mark.parametrize("name", ["orthographic", "thinlens"])
def test05_renders_agree_with_mitsuba(name):
    """As test_mitsuba_agreement.py: 4 x 4 block means of ours (two seeds) against Mitsuba's
    converged render, mean relative error under 0.02 with our own noise well below it; the
    orthographic scene's near plane cuts into a ball and its far plane removes the back of
    the floor, the thin lens blurs the box in front of the focal plane."""
    entry = REFS[name]
    scene = tr.load_file(FOLDER / entry["scene"])
    ref = tr.read_image(FOLDER / entry["exr"])
    blocks = lambda img: img.reshape(12, 4, 16, 4, 3).mean(dim=(1, 3))  # noqa: E731
    a, b = tr.render(scene, spp=256, seed=11), tr.render(scene, spp=256, seed=12)
    metric = lambda x, y: float(((x - y).abs() / y.abs().clamp(min=0.02)).mean())  # noqa: E731
    noise, error = metric(blocks(a), blocks(b)) / 2, metric(blocks((a + b) / 2), blocks(ref))
    print(f"{name}: error {error:.4f}, our noise {noise:.4f}")
    assert noise < 0.007
    assert error < 0.02
    assert abs(float((a + b).mean() / 2) / entry["mean"] - 1) < 0.005


def test06_thinlens_blurs_what_is_out_of_focus():
    """With a tiny aperture the thin lens renders what the perspective sensor of the same
    pose and fov renders (samplers.xml) within noise; a wide one (radius 1) changes the box
    in front of the focal plane far beyond noise and blurs its edges (the mean absolute
    difference of neighbouring pixels drops to ~0.69 of the pinhole's; 0.86 on the ball in
    focus, which only loses the edges it shares with the floor behind it)."""
    def render(aperture):
        scene = tr.load_file(FOLDER / "thinlens.xml")
        scene.sensor.aperture_radius = aperture
        return tr.render(scene, spp=256, seed=3)
    pinhole = tr.render(tr.load_file(FOLDER / "samplers.xml"), spp=256, seed=3)
    noise = tr.render(tr.load_file(FOLDER / "samplers.xml"), spp=256, seed=4)
    tiny, wide = render(1e-5), render(1.0)
    box, ball = (slice(30, 48), slice(36, 60)), (slice(12, 36), slice(9, 34))

    def diff(x, y, region):
        return float((x[region] - y[region]).abs().mean())

    def sharpness(x, region):
        y = x[region]
        return float((y[:, 1:] - y[:, :-1]).abs().mean() + (y[1:] - y[:-1]).abs().mean())
    assert diff(tiny, pinhole, box) < 1.3 * diff(noise, pinhole, box)
    assert diff(wide, pinhole, box) > 4 * diff(noise, pinhole, box)
    assert sharpness(wide, box) < 0.8 * sharpness(pinhole, box)
    assert sharpness(wide, ball) > sharpness(wide, box) / sharpness(pinhole, box) * sharpness(pinhole, ball) * 1.1


@pytest.mark.parametrize("name", ["orthographic", "thinlens"])
def test07_backward_retraces_the_same_rays(name):
    """Replaying the forward samples (seed_grad = seed), the reverse-mode gradient of
    sum(w * image) equals the forward-mode derivative of the same render: the backward pass
    re-creates every ray, lens samples included."""
    scene = tr.load_file(FOLDER / f"{name}.xml", dtype=torch.float64)
    scene.sensor.film.width, scene.sensor.film.height = 16, 12
    key = "red_ball.bsdf.reflectance.value"
    w = torch.rand(12, 16, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    direction = torch.tensor([1.0, 0.3, 0.2], dtype=torch.float64)
    x = scene.params[key].detach().clone().requires_grad_()
    scene.params[key] = x
    (g,) = torch.autograd.grad((w * tr.render(scene, spp=8, seed=5, seed_grad=5)).sum(), [x])
    scene.params[key] = x.detach()
    jvp = (w * tr.render_forward(scene, {key: direction}, spp=8, seed=5)).sum()
    assert float(jvp) > 0.1
    torch.testing.assert_close((g * direction).sum(), jvp, rtol=1e-9, atol=1e-12)
