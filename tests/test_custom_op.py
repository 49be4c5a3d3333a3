"""The renderer as PyTorch custom operators (torch_rbpt/ops.py): registration and opcheck, fake
tensors, torch.compile against eager, torch.func transforms, double backward, and scene
handles."""
import pytest
import torch
from torch._subclasses.fake_tensor import FakeTensorMode

import torch_rbpt as tr
from torch_rbpt import ops
from conftest import ROOT

CBOX = ROOT / "torch_rbpt/scenes/cornell_box.xml"
KEY = "red.reflectance.value"


def _cbox(res=8, dtype=torch.float64):
    return tr.load_file(CBOX, res=res, dtype=dtype)


def _op_args(scene, spp=2, seed=3, requires_grad=()):
    params = [p.detach().clone() for p in scene.differentiable_inputs()]
    for i in requires_grad:
        params[i].requires_grad_()
    _, _, w, h = scene.sensor.film.crop_window()
    return params, scene._handle, h, w, spp, seed


def test01_operators_are_registered_with_schemas():
    schemas = {name: str(getattr(torch.ops.torch_rbpt, name).default._schema)
               for name in ("render", "render_bwd", "render_jvp")}
    assert schemas["render"].startswith("torch_rbpt::render(Tensor[] params, SymInt scene, SymInt sensor, "
                                        "SymInt height, SymInt width, SymInt spp, SymInt seed")
    assert schemas["render"].endswith("-> Tensor")
    assert "Tensor grad_image, bool[] needs_grad" in schemas["render_bwd"]
    assert schemas["render_bwd"].endswith("-> Tensor[]")
    assert "Tensor?[] tangents" in schemas["render_jvp"]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test02_opcheck_render(dtype):
    scene = _cbox(dtype=dtype)
    params, handle, h, w, spp, seed = _op_args(scene, requires_grad=(0, 2))
    # A seed above 2**63 travels as a negative int64.
    torch.library.opcheck(torch.ops.torch_rbpt.render.default,
                          (params, handle, 0, h, w, spp, ops.signed_seed(2 ** 64 - 3), spp, 11))


def test03_opcheck_render_bwd_and_render_jvp():
    scene = _cbox()
    params, handle, h, w, spp, seed = _op_args(scene)
    grad_image = torch.rand(h, w, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    needs = [i in (0, 3) for i in range(len(params))]
    torch.library.opcheck(torch.ops.torch_rbpt.render_bwd.default,
                          (params, grad_image, needs, handle, 0, h, w, spp, seed))
    tangents = [torch.ones_like(p) if i == 1 else None for i, p in enumerate(params)]
    torch.library.opcheck(torch.ops.torch_rbpt.render_jvp.default,
                          (params, tangents, handle, 0, h, w, spp, seed))


def test04_fake_tensors_get_the_shape_without_the_scene():
    with FakeTensorMode():
        params = [torch.empty(3, dtype=torch.float64), torch.empty(4, 5, 3, dtype=torch.float64)]
        # Handle 0 names no scene: the fake kernels never look the scene up.
        image = torch.ops.torch_rbpt.render(params, 0, 0, 5, 7, 1, 0, 1, 0)
        grads = torch.ops.torch_rbpt.render_bwd(params, image, [False, True], 0, 0, 5, 7, 1, 0)
        tangent = torch.ops.torch_rbpt.render_jvp(params, [None, params[1]], 0, 0, 5, 7, 1, 0)
    assert image.shape == tangent.shape == (5, 7, 3) and image.dtype == torch.float64
    assert [g.shape for g in grads] == [(4, 5, 3)]


def test05_seeds_up_to_2_64_keep_their_meaning():
    scene = _cbox(dtype=torch.float32)
    for seed in (0, 2 ** 63 - 1, 2 ** 63, 2 ** 64 - 1):
        direct, _ = tr._C.render_fwd(scene._native, scene.sensor.native(), scene.integrator.native(),
                                     scene.param_list(), 2, seed, 0, -1)
        assert torch.equal(tr.render(scene, spp=2, seed=seed), direct), seed
    assert not torch.equal(tr.render(scene, spp=2, seed=2 ** 63), tr.render(scene, spp=2, seed=0))
    with pytest.raises(ValueError, match="seed must be an int in"):
        tr.render(scene, spp=2, seed=2 ** 64)


def test06_handles_name_live_scenes_and_check_the_image_size():
    scene = _cbox()
    params, handle, h, w, spp, seed = _op_args(scene)
    with pytest.raises(ValueError, match="image size 3x8 given to the operator is not the crop window "
                                         "of the scene's sensor 0, 8x8"):
        torch.ops.torch_rbpt.render(params, handle, 0, 3, 8, spp, seed, spp, seed)
    with pytest.raises(ValueError, match="sensor 1 given to the operator, but the scene has 1 sensor"):
        torch.ops.torch_rbpt.render(params, handle, 1, h, w, spp, seed, spp, seed)
    del scene
    with pytest.raises(ValueError, match=f"no live scene has handle {handle}"):
        torch.ops.torch_rbpt.render(params, handle, 0, h, w, spp, seed, spp, seed)


# -- torch.compile --------------------------------------------------------------------------

def _fit_setup(res=16):
    scene = _cbox(res=res, dtype=torch.float32)
    target = tr.render(scene, spp=16, seed=1000)
    red = scene.params[KEY]
    with torch.no_grad():
        red.copy_(torch.tensor([0.01, 0.2, 0.9]))
    red.requires_grad_()
    return scene, red, target


def test07_compiled_fullgraph_training_step_matches_eager():
    """render, L2 loss, backward and an Adam step in one graph. torch.optim.Adam.step()
    graph-breaks by design in torch 2.13 (and backward needs trace_autograd_ops), so the
    step is Adam's update written out. Images and gradients must be bitwise eager's at
    the same parameters; the update itself is inductor's arithmetic (rounding may differ)."""

    def make_step(scene, red, target):
        m, v, t = torch.zeros_like(red), torch.zeros_like(red), torch.zeros(())

        def step(it):
            red.grad = None
            image = tr.render(scene, spp=4, seed=it)
            loss = ((image - target) ** 2).mean()
            loss.backward()
            with torch.no_grad():
                g = red.grad
                t.add_(1)
                m.lerp_(g, 0.1)
                v.mul_(0.999).addcmul_(g, g, value=0.001)
                red.sub_(0.05 * (m / (1 - 0.9 ** t)) / ((v / (1 - 0.999 ** t)).sqrt() + 1e-8))
                red.clamp_(0, 1)
            return image.detach(), g.clone()

        return step

    scene_e, red_e, target = _fit_setup()
    scene_c, red_c, _ = _fit_setup()
    eager = make_step(scene_e, red_e, target)
    with torch._dynamo.config.patch(trace_autograd_ops=True):
        compiled = torch.compile(make_step(scene_c, red_c, target), fullgraph=True)
        for it in range(4):  # the second call recompiles with a dynamic seed
            with torch.no_grad():
                red_e.copy_(red_c)
            image_e, grad_e = eager(it)
            image_c, grad_c = compiled(it)
            assert torch.equal(image_c, image_e) and torch.equal(grad_c, grad_e), it
            assert float(grad_e.abs().sum()) > 0
            torch.testing.assert_close(red_c, red_e, rtol=1e-5, atol=1e-7)


def test08_compiled_render_and_loss_with_torch_optim_adam_matches_eager_bitwise():
    """The everyday form: the loss compiled with fullgraph=True, backward and the optimizer
    eager. The whole trajectory is bitwise eager's."""
    trajectories = []
    for compile_it in (False, True):
        scene, red, target = _fit_setup()
        opt = torch.optim.Adam([red], lr=0.05)

        def loss_fn(it):
            image = tr.render(scene, spp=4, seed=it)
            return ((image - target) ** 2).mean(), image

        f = torch.compile(loss_fn, fullgraph=True) if compile_it else loss_fn
        images, grads = [], []
        for it in range(3):
            opt.zero_grad()
            loss, image = f(it)
            loss.backward()
            opt.step()
            images.append(image.detach())
            grads.append(red.grad.clone())
        trajectories.append((images, grads, red.detach().clone()))
    (ie, ge, re), (ic, gc, rc) = trajectories
    assert all(torch.equal(a, b) for a, b in zip(ie, ic))
    assert all(torch.equal(a, b) for a, b in zip(ge, gc))
    assert torch.equal(re, rc)


def test09_compiled_render_reads_the_sensor_when_it_runs():
    scene = _cbox()
    f = torch.compile(lambda s: tr.render(s, spp=2, seed=1), fullgraph=True)
    before = f(scene)
    scene.sensor.fov = 30.0  # read by the kernel at run time: no recompilation needed
    after = f(scene)
    assert not torch.equal(before, after) and torch.equal(after, tr.render(scene, spp=2, seed=1))
    scene.sensor.film.crop = (1, 2, 5, 3)  # the image size is guarded: recompiles
    cropped = f(scene)
    assert cropped.shape == (3, 5, 3) and torch.equal(cropped, tr.render(scene, spp=2, seed=1))
    scene.params["tallbox.vertex_positions"].add_(1.0)  # checked when the operator runs
    with pytest.raises(ValueError, match="'tallbox.vertex_positions' was edited"):
        f(scene)


# -- torch.func, forward mode, double backward -------------------------------------------------

def test10_vmap_over_a_batch_of_parameter_values_equals_a_loop():
    scene = _cbox()
    x0 = scene.params[KEY].detach().clone()
    batch = torch.stack([x0, 0.5 * x0, torch.tensor([0.1, 0.9, 0.3], dtype=torch.float64)])

    def f(v):
        scene.params[KEY] = v
        return tr.render(scene, spp=2, seed=4)

    images = torch.func.vmap(f)(batch)
    assert images.shape == (3, 8, 8, 3)
    for i in range(3):
        assert torch.equal(images[i], f(batch[i].clone()))
    assert not torch.equal(images[0], images[2])
    # Forward mode under vmap: a batch of tangents.
    scene.params[KEY] = x0
    tangents = torch.eye(3, dtype=torch.float64)
    jvps = torch.func.vmap(lambda t: torch.func.jvp(f, (x0,), (t,))[1])(tangents)
    for i in range(3):
        torch.testing.assert_close(jvps[i], tr.render_forward(scene, {KEY: tangents[i]}, spp=2, seed=4),
                                   rtol=0, atol=0)


def test11_second_derivatives_are_a_clear_error():
    """Double backward, and reverse mode while the parameters carry forward-mode tangents
    (forward-over-reverse), would need render's second derivatives."""
    import torch.autograd.forward_ad as fwAD
    scene = _cbox()
    p = scene.params[KEY].requires_grad_()
    image = tr.render(scene, spp=2, seed=1)
    (g,) = torch.autograd.grad(((image - 0.3) ** 2).sum(), [p], create_graph=True)
    with pytest.raises(RuntimeError, match="render's gradients are not differentiable"):
        g.sum().backward()
    # A linear loss: only the parameters carry the second derivative.
    (g,) = torch.autograd.grad(tr.render(scene, spp=2, seed=1).sum(), [p], create_graph=True)
    with pytest.raises(RuntimeError, match="render's gradients are not differentiable"):
        g.sum().backward()
    with fwAD.dual_level():
        scene.params[KEY] = fwAD.make_dual(p, torch.ones(3, dtype=torch.float64))
        image = tr.render(scene, spp=2, seed=1)
        with pytest.raises(RuntimeError, match="render's gradients are not differentiable"):
            torch.autograd.grad(image.sum(), [p])
    scene.params[KEY] = p


def test12_torch_func_grad_and_vmap_of_grad():
    scene = _cbox()
    x0 = scene.params[KEY].detach().clone()

    def loss(v):
        scene.params[KEY] = v
        return ((tr.render(scene, spp=2, seed=1) - 0.2) ** 2).sum()

    batch = torch.stack([x0, torch.tensor([0.1, 0.9, 0.3], dtype=torch.float64)])
    per_entry = torch.func.vmap(torch.func.grad(loss))(batch)
    for i in range(2):
        v = batch[i].clone().requires_grad_()
        (expected,) = torch.autograd.grad(loss(v), [v])
        assert torch.equal(torch.func.grad(loss)(batch[i]), expected)
        assert torch.equal(per_entry[i], expected)
    assert not torch.equal(per_entry[0], per_entry[1])


def test13_concurrent_backward_passes_through_one_image():
    """One-hot adjoints from several threads at once (examples/gradient_image.py) give what
    they give one at a time."""
    from concurrent.futures import ThreadPoolExecutor
    scene = _cbox()
    p = scene.params[KEY].requires_grad_()
    image = tr.render(scene, spp=2, seed=1)

    def pixel_grad(k):
        onehot = torch.zeros_like(image)
        onehot.view(-1, 3)[k, 0] = 1
        return torch.autograd.grad(image, p, onehot, retain_graph=True)[0]

    pixels = list(range(0, 64, 2))
    sequential = [pixel_grad(k) for k in pixels]
    with ThreadPoolExecutor(4) as pool:
        concurrent = list(pool.map(pixel_grad, pixels))
    assert all(torch.equal(a, b) for a, b in zip(sequential, concurrent))
    assert sum(float(g.abs().sum()) > 0 for g in sequential) > 8
