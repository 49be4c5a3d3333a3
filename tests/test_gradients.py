"""Gradients (csrc/render.cpp render_bwd / render_jvp, torch_rbpt/render.py _Render):
exact checks in replay mode (gradcheck, reverse = forward mode), unbiasedness of independent
backward seeds against finite differences, the bias of replay for a nonlinear loss, and
gradient images."""
import math

import pytest
import torch

import torch_rbpt as tr
from conftest import ROOT, directional_derivatives, l2_gradient_samples

D = torch.float64


def _camera(res, fov=40.0, origin=(0, 0, 3.9)):
    return {"type": "perspective", "fov": fov,
            "to_world": tr.Transform.look_at(list(origin), [0, 0, 0], [0, 1, 0]),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}}


def glossy_box(res=8, max_depth=4, texture=None, rough_floor=False):
    """An open box with several bounces, every differentiable parameter kind in it: diffuse
    walls (one textured), a rough conductor and a rough plastic block, an area light, a
    point light and a constant sky seen through the open front."""
    floor = {"type": "diffuse", "reflectance": 0.6}
    if rough_floor:  # glossy floor and back wall: roughness then shapes much of the image
        floor = {"type": "ref", "id": "metal"}
    if texture is not None:
        floor = {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": str(texture), "raw": True}}
    T = tr.Transform
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth},
        "sensor": _camera(res),
        "red": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.1, 0.1]}},
        "metal": {"type": "roughconductor", "alpha": 0.3, "distribution": "ggx",
                  "specular_reflectance": {"type": "rgb", "value": [0.9, 0.7, 0.4]}},
        "plastic": {"type": "roughplastic", "alpha": 0.2,
                    "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.4, 0.6]}},
        "floor": {"type": "rectangle", "to_world": T.translate([0, -1, 0]) @ T.rotate([1, 0, 0], -90), "bsdf": floor},
        "back": {"type": "rectangle", "to_world": T.translate([0, 0, -1]),
                 "bsdf": {"type": "ref", "id": "plastic"} if rough_floor else {"type": "diffuse", "reflectance": 0.7}},
        "left": {"type": "rectangle", "to_world": T.translate([-1, 0, 0]) @ T.rotate([0, 1, 0], 90), "bsdf": {"type": "ref", "id": "red"}},
        "right": {"type": "rectangle", "to_world": T.translate([1, 0, 0]) @ T.rotate([0, 1, 0], -90), "bsdf": {"type": "ref", "id": "metal"}},
        "block": {"type": "cube", "to_world": T.translate([-0.3, -0.6, 0]) @ T.scale(0.35), "bsdf": {"type": "ref", "id": "plastic"}},
        "light": {"type": "rectangle", "to_world": T.translate([0, 0.99, 0]) @ T.rotate([1, 0, 0], 90) @ T.scale(0.3),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [8, 7, 6]}}},
        "lamp": {"type": "point", "position": [0.5, 0.5, 0.5], "intensity": {"type": "rgb", "value": [1, 2, 1]}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.4, 0.5]}},
    }


def _texture(tmp_path, h=2, w=2):
    g = torch.Generator().manual_seed(0)
    path = tmp_path / "tex.exr"
    tr.write_image(path, 0.2 + 0.6 * torch.rand(h, w, 3, generator=g))
    return path


# -- 1. exact checks in replay mode ----------------------------------------------------------

def _gradcheck(scene, key, spp=2, eps=1e-6, atol=1e-5, rtol=1e-3):
    x0 = scene.params[key].detach().clone()

    def f(x):
        scene.params[key] = x
        return tr.render(scene, spp=spp, seed=7, seed_grad=7)

    x = x0.clone().requires_grad_()
    ok = torch.autograd.gradcheck(f, (x,), eps=eps, atol=atol, rtol=rtol, nondet_tol=0.0)
    scene.params[key] = x0
    return ok


@pytest.mark.parametrize("key", ["red.reflectance.value", "light.emitter.radiance.value",
                                 "lamp.intensity.value", "sky.radiance.value",
                                 "metal.specular_reflectance.value"])
def test01_gradcheck_replay(key):
    # max_depth 4 < rr_depth 5: no Russian roulette decision depends on a parameter.
    scene = tr.load_dict(glossy_box(res=3), dtype=D)
    assert _gradcheck(scene, key)


def test02_gradcheck_texture_texels(tmp_path):
    scene = tr.load_dict(glossy_box(res=3, texture=_texture(tmp_path)), dtype=D)
    assert scene.params["floor.bsdf.reflectance.data"].shape == (2, 2, 3)
    assert _gradcheck(scene, "floor.bsdf.reflectance.data")


def _point_lit_plane(bsdf):
    # Only emitter sampling of a point light contributes (max_depth 2): no sampled direction
    # can change what is seen when the roughness moves.
    return tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 2},
        "sensor": _camera(3, fov=60, origin=(0.3, 1.5, 2.0)),
        "plane": {"type": "rectangle", "to_world": tr.Transform.rotate([1, 0, 0], -90) @ tr.Transform.scale(3), "bsdf": bsdf},
        "lamp": {"type": "point", "position": [-0.5, 1.0, -0.3], "intensity": 3.0},
    }, dtype=D)


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
def test03_gradcheck_roughconductor_alpha(dist):
    scene = _point_lit_plane({"type": "roughconductor", "alpha": 0.3, "distribution": dist})
    assert _gradcheck(scene, "plane.bsdf.alpha.value")


def test04_gradcheck_roughplastic_alpha():
    # The rough-interface tables are float quadratures of alpha: a wider finite-difference
    # step keeps their float rounding out of gradcheck's numerical derivative.
    scene = _point_lit_plane({"type": "roughplastic", "alpha": 0.2})
    assert _gradcheck(scene, "plane.bsdf.alpha", eps=1e-4, atol=1e-4, rtol=2e-2)


def test05_reverse_equals_forward_mode_on_the_same_paths(tmp_path):
    scene = tr.load_dict(glossy_box(res=6, max_depth=8, texture=_texture(tmp_path)), dtype=D)
    keys = [k for k in scene.params if k not in scene.params._fixed]
    for k in keys:
        scene.params[k].requires_grad_()
    w = torch.rand(6, 6, 3, generator=torch.Generator().manual_seed(1), dtype=D)
    image = tr.render(scene, spp=8, seed=3, seed_grad=3)
    grads = torch.autograd.grad((w * image).sum(), [scene.params[k] for k in keys])
    g = torch.Generator().manual_seed(2)
    for k, grad in zip(keys, grads):
        tangent = torch.randn(scene.params[k].shape, generator=g, dtype=D)
        jvp = tr.render_forward(scene, {k: tangent}, spp=8, seed=3)
        torch.testing.assert_close((w * jvp).sum(), (grad * tangent).sum(), rtol=1e-9, atol=1e-12, msg=k)


def test06_torch_forward_ad_and_func_jvp():
    scene = tr.load_dict(glossy_box(res=4), dtype=D)
    key = "red.reflectance.value"
    x = scene.params[key].detach().clone()
    t = torch.tensor([1.0, 0.5, -0.2], dtype=D)
    expected = tr.render_forward(scene, {key: t}, spp=4, seed=1)

    def f(v):
        scene.params[key] = v
        return tr.render(scene, spp=4, seed=1)

    _, jvp = torch.func.jvp(f, (x,), (t,))
    torch.testing.assert_close(jvp, expected)
    import torch.autograd.forward_ad as fwAD
    with fwAD.dual_level():
        out = f(fwAD.make_dual(x, t))
        torch.testing.assert_close(fwAD.unpack_dual(out).tangent, expected)
    scene.params[key] = x


def test07_gradients_are_deterministic_and_follow_dtype():
    for dtype in (torch.float32, torch.float64):
        scene = tr.load_dict(glossy_box(res=6), dtype=dtype)
        p = scene.params["red.reflectance.value"].requires_grad_()
        grads = []
        for _ in range(2):
            (g,) = torch.autograd.grad(tr.render(scene, spp=4, seed=1).sum(), [p])
            grads.append(g)
        assert grads[0].dtype == dtype and torch.equal(grads[0], grads[1])


def test08_default_seed_grad_differs_from_seed():
    # The bundled Cornell box has one light, so the image is linear in its radiance.
    scene = tr.load_file(ROOT / "torch_rbpt/scenes/cornell_box.xml", res=6, dtype=D)
    p = scene.params["light.emitter.radiance.value"].requires_grad_()
    (g_default,) = torch.autograd.grad(tr.render(scene, spp=2, seed=5).sum(), [p])
    (g_replay,) = torch.autograd.grad(tr.render(scene, spp=2, seed=5, seed_grad=5).sum(), [p])
    assert not torch.equal(g_default, g_replay)
    # Replayed, the gradient is exactly image / radiance (per channel).
    image = tr.render(scene, spp=2, seed=5).detach()
    torch.testing.assert_close(g_replay, image.sum(dim=(0, 1)) / p.detach())


def test09_non_differentiable_parameters_raise():
    scene = tr.load_dict(glossy_box(res=4))
    scene.params["plastic.eta"].requires_grad_()
    with pytest.raises(ValueError, match="'plastic.eta' cannot be differentiated.*index of refraction"):
        tr.render(scene, spp=1)
    scene = tr.load_dict(glossy_box(res=4))
    scene.params["block.vertex_positions"].requires_grad_()
    with pytest.raises(ValueError, match="'block.vertex_positions' cannot be differentiated.*geometry"):
        tr.render(scene, spp=1)
    with pytest.raises(ValueError, match="cannot be differentiated"):
        tr.render_forward(scene, {"floor.to_world": torch.zeros(4, 4)})


def test10_zero_adjoint_pixels_trace_nothing():
    scene = tr.load_dict(glossy_box(res=8), dtype=D)
    params = scene.param_list()
    mask = [k == "red.reflectance.value" for k in scene._keys]
    args = (scene._native, scene.sensor.native(), scene.integrator.native(), params, mask)
    zero = tr._C.render_bwd(*args, torch.zeros(8, 8, 3, dtype=D), 4, 1)
    assert float(zero[mask.index(True)].abs().sum()) == 0
    # One pixel's adjoint: the gradient of that pixel alone, equal to forward mode's pixel.
    onehot = torch.zeros(8, 8, 3, dtype=D)
    onehot[3, 2, 0] = 1
    g = tr._C.render_bwd(*args, onehot, 4, 1)[mask.index(True)]
    jvp = tr.render_forward(scene, {"red.reflectance.value": torch.tensor([1.0, 0, 0], dtype=D)}, spp=4, seed=1)
    torch.testing.assert_close(g[0], jvp[3, 2, 0])



@pytest.mark.parametrize("crop", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test10b_sparse_adjoints_skip_the_pixels_they_do_not_reach(dtype, crop):
    # The backward pass skips the pixels (and whole tiles of 16 x 16) whose samples reach no
    # pixel of nonzero adjoint, their splats' weights included. The gradient is linear in the
    # adjoint: the adjoint cut into its tiles' own pixels gives nine sparse passes, which
    # must add up to the dense one; under a gaussian (samples reaching two pixels into the
    # next tile) a skipped neighbour's samples, or their weights in a pixel's normalisation,
    # would be missing from the sum. Also in a crop window, whose pixels are not the film's.
    # (float32 takes the lanes, float64 the tape.)
    d = glossy_box(res=40)
    d["sensor"]["film"]["rfilter"] = {"type": "gaussian"}
    if crop:
        d["sensor"]["film"].update(width=52, height=47, crop_offset_x=7, crop_offset_y=5, crop_width=40, crop_height=40)
    scene = tr.load_dict(d, dtype=dtype)
    keys = ["red.reflectance.value", "light.emitter.radiance.value"]
    params = scene.param_list()
    mask = [k in keys for k in scene._keys]
    args = (scene._native, scene.sensor.native(), scene.integrator.native(), params, mask)
    adjoint = torch.rand(40, 40, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64).to(dtype)
    dense = tr._C.render_bwd(*args, adjoint, 4, 1)
    parts = []
    for ty in range(3):
        for tx in range(3):
            part = torch.zeros_like(adjoint)
            part[16 * ty:16 * (ty + 1), 16 * tx:16 * (tx + 1)] = adjoint[16 * ty:16 * (ty + 1), 16 * tx:16 * (tx + 1)]
            parts.append(tr._C.render_bwd(*args, part, 4, 1))
    for i, key in enumerate(scene._keys):
        if not mask[i]:
            continue
        total = sum(p[i].double() for p in parts)
        assert float(dense[i].abs().max()) > 0, key
        torch.testing.assert_close(total, dense[i].double(), rtol=1e-5, atol=1e-6 * float(dense[i].abs().max()), msg=key)


# -- 2. unbiasedness with independent backward seeds ---------------------------------------

DIFFERENTIABLE = ["red.reflectance.value", "floor.bsdf.reflectance.data", "metal.alpha.value",
                  "metal.specular_reflectance.value", "plastic.alpha",
                  "plastic.diffuse_reflectance.value", "light.emitter.radiance.value",
                  "lamp.intensity.value", "sky.radiance.value"]


def test11_independent_seeds_are_unbiased(tmp_path):
    """For a linear loss sum(w * image), the mean over seeds of the backward gradient (with
    its own seeds) matches forward mode (dual numbers, other seeds) and central finite
    differences with common random numbers (which include every sampling decision's
    dependence on the parameters), within 4 standard errors of each difference. Paths stop
    before rr_depth so that Russian roulette does not make the finite differences explode."""
    res, spp, n_seeds = 6, 4, 128
    textured = tr.load_dict(glossy_box(res=res, max_depth=4, texture=_texture(tmp_path)), dtype=D)
    glossy = tr.load_dict(glossy_box(res=res, max_depth=4, rough_floor=True), dtype=D)
    w = torch.rand(res, res, 3, generator=torch.Generator().manual_seed(4), dtype=D)
    g = torch.Generator().manual_seed(5)
    for key in DIFFERENTIABLE:
        # Roughness is tested where glossy surfaces fill much of the view.
        scene = glossy if "alpha" in key else textured
        p = scene.params[key]
        direction = torch.rand(p.shape, generator=g, dtype=D) + 0.5
        h = 1e-2 * float(p.abs().mean())
        d = directional_derivatives(scene, key, w, direction, spp, n_seeds, h=h, forward_seed=5000)
        rev, fwd, fd = d["backward"], d["forward"], d["fd"]
        se = lambda a, b: math.sqrt(a.var() / n_seeds + b.var() / n_seeds)  # noqa: E731
        print(f"{key:36s} backward {rev.mean():+.4f}  forward {fwd.mean():+.4f}  "
              f"finite diff. {fd.mean():+.4f}  (stderr {se(rev, fd):.4f})")
        assert abs(rev.mean() - fd.mean()) < 4 * se(rev, fd), f"{key}: backward vs finite differences"
        assert abs(rev.mean() - fwd.mean()) < 4 * se(rev, fwd), f"{key}: backward vs forward mode"
        # The comparison has power: the gradient is resolved well away from zero.
        assert abs(float(rev.mean())) > 4 * float(rev.std()) / math.sqrt(n_seeds), f"{key}: gradient not resolved"


def test12_replay_is_biased_for_nonlinear_losses_independent_seeds_are_not():
    """The report's claim: for an L2 loss at low spp, replay (seed_grad = seed) correlates the
    image with its own derivative, E[2 (I - T) dI] = 2 (E[I] - T) E[dI] + 2 Cov(I, dI);
    independent seeds remove the covariance."""
    scene = tr.load_file(ROOT / "torch_rbpt/scenes/cornell_box.xml", res=8, dtype=D)
    n = 400
    expected, replay, independent = l2_gradient_samples(scene, "light.emitter.radiance.value",
                                                        spp=1, n=n, mean_spp=8192)
    se_r, se_i = float(replay.std()) / math.sqrt(n), float(independent.std()) / math.sqrt(n)
    assert abs(float(independent.mean()) - expected) < 4 * se_i, (independent.mean(), expected, se_i)
    assert float(replay.mean()) - expected > 4 * se_r, (replay.mean(), expected, se_r)


# -- 3. gradient images ------------------------------------------------------------------

def test13_gradient_image_reverse_matches_dual_numbers(shared):
    """The per-pixel gradient of cbox's image with respect to the red wall's reflectance (red
    channel), by reverse mode with a one-hot adjoint per pixel (independent seeds), agrees
    with the dual-number image within noise."""
    res, spp = 12, 64
    scene = tr.load_file(shared / "cbox/cbox.xml", res=res, dtype=D)
    key = "red.reflectance.value"
    tangent = {key: torch.tensor([1.0, 0.0, 0.0], dtype=D)}
    dual_a = tr.render_forward(scene, tangent, spp=spp, seed=1)[..., 0]
    dual_b = tr.render_forward(scene, tangent, spp=spp, seed=2)[..., 0]
    params = scene.param_list()
    mask = [k == key for k in scene._keys]
    reverse = torch.zeros(res, res, dtype=D)
    for i in range(res):
        for j in range(res):
            onehot = torch.zeros(res, res, 3, dtype=D)
            onehot[i, j, 0] = 1
            g = tr._C.render_bwd(scene._native, scene.sensor.native(), scene.integrator.native(),
                                 params, mask, onehot, spp, 3)
            reverse[i, j] = g[mask.index(True)][0]
    assert float(dual_a.abs().max()) > 0.1  # the red wall matters
    noise = float((dual_a - dual_b).abs().mean())  # mean |difference| of two independent estimates
    assert float((reverse - dual_a).abs().mean()) < 1.5 * noise
    assert float((reverse - 0.5 * (dual_a + dual_b)).abs().mean()) < noise
