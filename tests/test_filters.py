"""Reconstruction filters with negative lobes (csrc/camera.h Filter: mitchell, catmullrom,
lanczos) and the film around them: Mitsuba's parameters and radii, pixel = sum w L / sum w
with negative weights as Mitsuba's film does, the backward pass's adjoint gather, and
hdrfilm's pixel_format. The images themselves are compared with Mitsuba's in
test_mitsuba_agreement.py (filter_* references); here each reference must also tell the
filters apart."""
import math

import pytest
import torch

import torch_rbpt as tr
from conftest import REFERENCES, torch_threads
from test_mitsuba_agreement import block_mean, metric

SCENE = REFERENCES / "scenes" / "filters.xml"
FILTERS = ["mitchell", "catmullrom", "lanczos", "gaussian"]


@pytest.mark.parametrize("name", ["mitchell", "catmullrom", "lanczos"])
def test01_each_reference_tells_the_filters_apart(name):
    # Our render with the reference's filter is close to it; with any other filter it is not
    # (errors 0.08 to 0.27 at blocks of 2x2, against < 0.01): a wrong B, C, lobe count or
    # radius would show.
    ref = block_mean(tr.read_image(REFERENCES / f"filter_{name}.exr"), 2)
    errors = {f: metric(block_mean(tr.render(tr.load_file(SCENE, filter=f), spp=512, seed=3), 2), ref)
              for f in FILTERS}
    print(name, {f: round(e, 4) for f, e in errors.items()})
    assert errors[name] < 0.015
    assert all(e > 0.05 for f, e in errors.items() if f != name)


def test02_negative_lobes_give_negative_pixels_as_in_mitsuba():
    # Next to a bright edge on black, the negative lobes make pixels negative; Mitsuba divides
    # by the weight sum whatever its sign, and so do we.
    ref = tr.read_image(REFERENCES / "filter_lanczos.exr")
    ours = tr.render(tr.load_file(SCENE, filter="lanczos"), spp=256, seed=1)
    assert float(ref.min()) < -0.3 and float(ours.min()) < -0.3
    strongly_negative = ref < -0.1
    assert bool((ours[strongly_negative] < 0).float().mean() > 0.95)


def test03_parameters_and_radii():
    def film(rfilter):
        return tr.load_dict({"type": "scene", "sensor": {"type": "perspective", "film": {
            "type": "hdrfilm", "width": 4, "height": 4, "rfilter": rfilter}}}).sensor.film

    f = film({"type": "mitchell"})
    assert (f.filter_radius, f.filter_b, f.filter_c) == (2.0, pytest.approx(1 / 3), pytest.approx(1 / 3))
    f = film({"type": "mitchell", "B": 0.5, "C": 0.25})
    assert (f.filter_b, f.filter_c) == (0.5, 0.25)
    assert film({"type": "catmullrom"}).filter_radius == 2.0
    assert (film({"type": "lanczos"}).filter_radius, film({"type": "lanczos", "lobes": 2}).filter_radius) == (3.0, 2.0)
    # As in Mitsuba (an unreferenced property): these filters take no radius.
    for rfilter in ({"type": "mitchell", "radius": 3}, {"type": "catmullrom", "B": 0.2}, {"type": "lanczos", "radius": 1}):
        with pytest.raises(tr.SceneError, match="unsupported parameter"):
            film(rfilter)
    with pytest.raises(tr.SceneError, match="lobes must be positive"):
        film({"type": "lanczos", "lobes": 0})


def _lit_plane(rfilter, res=5):
    return tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 50,
                   "to_world": tr.Transform.look_at([0, 1, 2.5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": rfilter}},
        "plane": {"type": "rectangle", "to_world": tr.Transform.rotate([1, 0, 0], -90),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.5, 0.3]}}},
        "light": {"type": "sphere", "center": [0.3, 0.8, 0.2], "radius": 0.2,
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [6, 5, 4]}}},
    }, dtype=torch.float64)


@pytest.mark.parametrize("rfilter", [{"type": "lanczos"}, {"type": "mitchell", "B": 0.2, "C": 0.6}])
def test04_gradients_through_negative_weights(rfilter):
    # The adjoint each sample gathers, sum_p w_p(x) dL_p / W_p, is the exact transpose of the
    # splat when weights are negative too: replay gradcheck, and reverse = forward mode.
    scene = _lit_plane(rfilter)
    key = "plane.bsdf.reflectance.value"
    x0 = scene.params[key].detach().clone()

    def f(x):
        scene.params[key] = x
        return tr.render(scene, spp=3, seed=2, seed_grad=2)

    assert torch.autograd.gradcheck(f, (x0.clone().requires_grad_(),), eps=1e-6, atol=1e-6, rtol=1e-4)
    w = torch.randn(5, 5, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x = x0.clone().requires_grad_()
    scene.params[key] = x
    (g,) = torch.autograd.grad((w * tr.render(scene, spp=3, seed=2, seed_grad=2)).sum(), [x])
    scene.params[key] = x0
    tangent = torch.tensor([0.3, -1.0, 0.7], dtype=torch.float64)
    jvp = tr.render_forward(scene, {key: tangent}, spp=3, seed=2)
    assert math.isclose(float((w * jvp).sum()), float((g * tangent).sum()), rel_tol=1e-9, abs_tol=1e-12)


def test05_pixel_format_is_accepted_and_render_stays_linear_rgb():
    images = []
    for fmt in ["rgb", "RGBA", "luminance", "luminance_alpha", "xyz", "xyza"]:
        scene = tr.load_dict({"type": "scene", "sensor": {"type": "perspective", "film": {
            "type": "hdrfilm", "width": 6, "height": 4, "pixel_format": fmt}},
            "s": {"type": "sphere", "center": [0, 0, 3]},
            "sky": {"type": "constant"}})
        assert scene.sensor.film.pixel_format == fmt.lower()
        images.append(tr.render(scene, spp=4, seed=0))
    assert all(img.shape == (4, 6, 3) and torch.equal(img, images[0]) for img in images)
    with pytest.raises(tr.SceneError, match="pixel_format must be one of rgb, rgba, luminance"):
        tr.load_dict({"type": "scene", "sensor": {"type": "perspective", "film": {
            "type": "hdrfilm", "pixel_format": "y"}}})


def _profile(film, x):
    """Mitsuba's 1D filter profiles in float64, for the weights eval_row computes."""
    r = film.filter_radius
    if film.filter == "gaussian":
        a = -1 / (2 * film.filter_stddev ** 2)
        return torch.clamp(torch.exp(a * x * x) - math.exp(a * r * r), min=0)
    if film.filter == "tent":
        return torch.clamp(1 - x.abs() / r, min=0)
    b, c, ax = film.filter_b, film.filter_c, x.abs()
    inner = (12 - 9 * b - 6 * c) * ax ** 3 + (-18 + 12 * b + 6 * c) * ax ** 2 + (6 - 2 * b)
    outer = (-b - 6 * c) * ax ** 3 + (6 * b + 30 * c) * ax ** 2 + (-12 * b - 48 * c) * ax + (8 * b + 24 * c)
    return torch.where(ax < 1, inner, torch.where(ax < 2, outer, torch.zeros_like(x))) / 6


@pytest.mark.parametrize("rfilter", [{"type": "gaussian"}, {"type": "gaussian", "stddev": 0.13},
                                     {"type": "gaussian", "stddev": 1.7}, {"type": "tent", "radius": 1.5},
                                     {"type": "mitchell"}])
def test06_splat_weights_follow_the_profile(rfilter):
    # The weights of a splat's row (the gaussian's from two exps per row and a table) equal
    # the profile at every offset, for sample positions all over a pixel.
    sensor = tr.load_dict({"type": "scene", "sensor": {"type": "perspective", "film": {
        "type": "hdrfilm", "width": 4, "height": 4, "rfilter": rfilter}}}).sensor
    film = sensor.film
    b = max(0, math.ceil(film.filter_radius - 0.5))
    n = 2 * b + 1
    frac = torch.linspace(0, 1, 1001, dtype=torch.float64)[:-1]
    x0 = -b + 0.5 - frac  # the first pixel centre's offset from a sample at px + frac
    w = tr._C.filter_weights(sensor.native(), x0.float(), n).double()
    x = x0.float().double()[:, None] + torch.arange(n, dtype=torch.float64)
    expected = _profile(film, x)
    assert w.shape == (1000, n)
    # Float evaluation: within a few ulps of 1 (Mitchell's cubic cancels more).
    tolerance = 2e-6 if film.filter == "mitchell" else 3e-7
    assert float((w - expected).abs().max()) < tolerance * float(expected.abs().max())
    assert float(w.sum(1).min()) > 0


@pytest.mark.parametrize("rfilter", [{"type": "gaussian"}, {"type": "lanczos"}])
def test07_tiles_splat_across_their_borders(rfilter):
    # A 37 x 35 film is 3 x 3 tiles of 16 pixels, the last ones partial; every tile splats
    # into its neighbours. The splat's transpose holds exactly across tile edges (reverse mode
    # with replay = forward mode, per pixel), on any thread count and on bands of rows.
    scene = _lit_plane(rfilter, res=37)
    scene.sensor.film.height = 35
    key = "plane.bsdf.reflectance.value"
    x0 = scene.params[key].detach().clone()
    tangent = torch.tensor([0.3, -1.0, 0.7], dtype=torch.float64)
    with torch_threads(1):
        image = tr.render(scene, spp=2, seed=4)
        jvp = tr.render_forward(scene, {key: tangent}, spp=2, seed=4)
    with torch_threads(2):
        assert torch.equal(tr.render(scene, spp=2, seed=4), image)
        assert torch.equal(tr.render_forward(scene, {key: tangent}, spp=2, seed=4), jvp)
    band = torch.cat([tr.render(scene, spp=2, seed=4, rows=r) for r in [(0, 15), (15, 17), (17, 35)]])
    assert torch.equal(band, image)
    # Each pixel's derivative from reverse mode (its own one-hot adjoint) equals forward mode's;
    # a sample splat into a neighbour tile and left out of its sums, or gathered from a
    # neighbour whose weights it left out, breaks this near the tile edges.
    x = x0.clone().requires_grad_()
    scene.params[key] = x
    out = tr.render(scene, spp=2, seed=4, seed_grad=4)
    for py, px in [(15, 15), (16, 16), (15, 16), (0, 17), (31, 32), (34, 36), (20, 8)]:
        (g,) = torch.autograd.grad(out[py, px].sum(), [x], retain_graph=True)
        assert math.isclose(float((g * tangent).sum()), float(jvp[py, px].sum()), rel_tol=1e-9, abs_tol=1e-12), (py, px)
    scene.params[key] = x0


@pytest.mark.parametrize("res", [(23, 19), (16, 16)])
def test08_tent_splats_sum_as_the_dual_film_does(res):
    # The primal film adds the tent's 2 x 2 splats on paths of its own (Film::splat_run_tent:
    # a pixel's run of samples into its 3 x 3 sums held in registers; Film::add_2x2 at the
    # film's edges: a row's two pixels in one vector with AVX-512); the dual film of forward
    # mode adds them in its general loop. With only emission seen directly (max_depth 1) of radiance 1,
    # differentiated along a tangent of 1, every sample has L = dL/dt = 1, so the image and its
    # derivative are the same weighted sums over the same weights: bitwise equal. The lights'
    # edges (pixels between 0 and 1) show a splat with a column or row of weights swapped or
    # misplaced; the film's edges and the pixels whose window is 1 wide take the general loop.
    scene = tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 1},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": tr.Transform.look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res[0], "height": res[1], "rfilter": {"type": "tent"}}},
        "light": {"type": "rectangle",
                  "to_world": tr.Transform.translate([0.3, -0.2, 0]) @ tr.Transform.rotate([0, 0, 1], 20)
                  @ tr.Transform.scale([0.7, 0.5, 1]),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1, 1, 1]}}},
    })
    key = "light.emitter.radiance.value"
    image = tr.render(scene, spp=5, seed=3)
    jvp = tr.render_forward(scene, {key: torch.ones(3)}, spp=5, seed=3)
    edge = (image > 0.02) & (image < 0.98)
    assert int(edge[..., 0].sum()) > 10
    assert bool((image == 1).any()) and bool((image == 0).any())
    assert torch.equal(image, jvp)
