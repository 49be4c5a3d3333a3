"""Scenes pickle and deep-copy (torch_rbpt/scene.py: the C++ scene is rebuilt from the calls
that built it), and copies render in worker processes."""
import copy
import pickle

import pytest
import torch
import torch.multiprocessing as mp

import torch_rbpt as tr
from conftest import ROOT
from test_gradients import _texture, glossy_box

KEY = "red.reflectance.value"


def _edited_scene(tmp_path, dtype=torch.float32):
    """Every kind of shape, BSDF, emitter, a bitmap and a checkerboard with to_uv, with
    parameters edited in place."""
    d = glossy_box(res=8, max_depth=6, texture=_texture(tmp_path))
    d["back"]["bsdf"] = {"type": "diffuse", "reflectance": {
        "type": "checkerboard", "color0": 0.2, "color1": 0.8,
        "to_uv": tr.Transform.scale([4, 3, 1]) @ tr.Transform.translate([0.25, 0, 0])}}
    scene = tr.load_dict(d, dtype=dtype)
    assert "back.bsdf.reflectance.to_uv" in scene.params
    with torch.no_grad():
        scene.params[KEY].mul_(0.5)
        scene.params["floor.bsdf.reflectance.data"][0, 0] = 0.9
        scene.params["metal.alpha.value"].fill_(0.15)
    scene.params["sky.radiance.value"].requires_grad_()
    scene.sensor.fov = 35.0
    scene.integrator.max_depth = 5
    return scene


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("how", ["pickle", "deepcopy"])
def test01_round_trip_renders_bitwise_the_same(tmp_path, how, dtype):
    scene = _edited_scene(tmp_path, dtype)
    copied = pickle.loads(pickle.dumps(scene)) if how == "pickle" else copy.deepcopy(scene)
    assert copied._handle != scene._handle and copied._native is not scene._native
    assert copied.dtype == dtype and copied.params["sky.radiance.value"].requires_grad
    assert copied.sensor.fov == 35.0 and copied.integrator.max_depth == 5
    expected = tr.render(scene, spp=4, seed=9)
    assert torch.equal(tr.render(copied, spp=4, seed=9), expected)
    # The copy's parameters are its own.
    with torch.no_grad():
        copied.params[KEY].zero_()
    assert torch.equal(tr.render(scene, spp=4, seed=9), expected)
    assert not torch.equal(tr.render(copied, spp=4, seed=9), expected)


def test02_copies_keep_gradients_and_the_fixed_parameter_check(tmp_path):
    scene = _edited_scene(tmp_path, torch.float64)
    grads = []
    for s in (scene, copy.deepcopy(scene)):
        p = s.params["sky.radiance.value"]
        (g,) = torch.autograd.grad(tr.render(s, spp=2, seed=3).sum(), [p])
        grads.append(g)
    assert torch.equal(grads[0], grads[1]) and float(grads[0].abs().sum()) > 0
    # An in-place edit of fixed geometry is an error in the copy too (tensor versions restart).
    scene.params["block.vertex_positions"].add_(1.0)
    with pytest.raises(ValueError, match="'block.vertex_positions' was edited"):
        tr.render(pickle.loads(pickle.dumps(scene)), spp=1)


def test03_file_scenes_with_meshes_round_trip(shared):
    scene = tr.load_file(shared / "cbox/cbox.xml", res=16)
    copied = pickle.loads(pickle.dumps(scene))
    assert copied._native.triangle_count == scene._native.triangle_count > 0
    assert torch.equal(tr.render(copied, spp=2, seed=5), tr.render(scene, spp=2, seed=5))


@pytest.mark.parametrize("name", ["analytic_shapes", "mesh_attributes", "instances"])
def test03b_scenes_with_analytic_shapes_instances_and_mesh_attributes_round_trip(name, tmp_path):
    # Disks, cylinders, serialized meshes, flattened instances and mesh attributes (which the
    # loader sets on the C++ scene with set_mesh_attribute) are rebuilt by the copy too.
    folder = ROOT / "tests/references/shapes"
    path = folder / f"{name}.xml"
    if name == "instances":  # a shapes-only file: light it and look at it
        xml = path.read_text().replace("</scene>", '<emitter type="constant"/>\n'
                                       '<sensor type="perspective"><transform name="to_world">'
                                       '<lookat origin="0, -6, 4" target="0, 0, 0.3" up="0, 0, 1"/>'
                                       '</transform></sensor>\n</scene>')
        path = tmp_path / "instances.xml"
        path.write_text(xml)
        (tmp_path / "objects.serialized").write_bytes((folder / "objects.serialized").read_bytes())
    scene = tr.load_file(path)
    scene.sensor.film.width, scene.sensor.film.height = 16, 12
    copied = pickle.loads(pickle.dumps(scene))
    image = tr.render(scene, spp=2, seed=5)
    assert float(image.sum()) > 0
    assert torch.equal(tr.render(copied, spp=2, seed=5), image)


def _render_copy(args):
    scene, seed = args
    return tr.render(scene, spp=2, seed=seed)


def test04_worker_processes_render_copies():
    scene = tr.load_file(ROOT / "torch_rbpt/scenes/cornell_box.xml", res=8)
    with torch.no_grad():
        scene.params[KEY].copy_(torch.tensor([0.1, 0.7, 0.2]))
    seeds = [1, 2]
    with mp.get_context("spawn").Pool(2) as pool:
        images = pool.map(_render_copy, [(scene, s) for s in seeds])
    for image, seed in zip(images, seeds):
        assert torch.equal(image, tr.render(scene, spp=2, seed=seed))
    assert not torch.equal(images[0], images[1])
