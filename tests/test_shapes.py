"""Analytic disks and cylinders (csrc/shapes.h) with Mitsuba 3's semantics, against ray hits
and renders that Mitsuba 3.9.1 made (tests/references/make_shape_references.py; Mitsuba is
not needed here), and area lights on them against the renderer's own BSDF sampling."""
import json
import math

import numpy as np
import pytest
import torch

import torch_rbpt as tr
from conftest import REFERENCES, directional_derivatives

SHAPES = REFERENCES / "shapes"


def hit_cases():
    return json.loads((SHAPES / "analytic_hits.json").read_text())["cases"]


def load_case(case):
    node = dict(type=case["type"], **case["params"])
    if case["to_world"] is not None:
        node["to_world"] = case["to_world"]
    return tr.load_dict({"type": "scene", "s": node})


@pytest.mark.parametrize("index", range(9))
def test01_hits_match_mitsuba(index):
    """Hit or miss agrees on every ray (silhouettes); p, n and uv agree to float rounding.
    Every interaction's wi, in world space, is -d: a hit's through its shading frame, an
    escaped ray's as it is (what an environment emitter looks up)."""
    case = hit_cases()[index]
    scene = load_case(case)
    o = torch.tensor(case["origins"], dtype=torch.float32)
    d = torch.tensor(case["directions"], dtype=torch.float32)
    t, shape, p, n, uv, wi = tr._C.interact_rays(scene._native, o, d)
    np.testing.assert_allclose(wi.numpy(), -torch.nn.functional.normalize(d, dim=1).numpy(), atol=2e-6)
    hit = np.array([h[0] is not None for h in case["hits"]])
    assert 20 < hit.sum() < len(hit) - 20, "the rays should both hit and miss"
    assert np.array_equal(np.isfinite(t.numpy()), hit)
    ref_t = np.array([h[0] for h in case["hits"] if h[0] is not None])
    ref_p, ref_n, ref_uv = (np.array([h[k] for h in case["hits"] if h[0] is not None]) for k in (1, 2, 3))
    scale = np.abs(ref_p).max() + 1
    np.testing.assert_allclose(t.numpy()[hit], ref_t, rtol=1e-4, atol=1e-5 * scale)
    np.testing.assert_allclose(p.numpy()[hit], ref_p, atol=1e-4 * scale)
    np.testing.assert_allclose(n.numpy()[hit], ref_n, atol=1e-4)
    duv = np.abs(uv.numpy()[hit] - ref_uv)
    angle = 1 if case["type"] == "disk" else 0  # the coordinate that is phi / 2pi wraps at 1
    duv[:, angle] = np.minimum(duv[:, angle], 1 - duv[:, angle])
    assert duv.max() < 1e-4


def _lit_scene(integrator, light):
    return tr.load_dict({
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "perspective", "fov": 60,
                   "to_world": tr.Transform.look_at([0, -4, 3], [0, 0, 0.5], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 16, "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": tr.Transform.scale(3)},
        "light": dict(light, emitter={"type": "area", "radiance": 5.0}),
    })


@pytest.mark.parametrize("light", [
    {"type": "disk", "flip_normals": True,
     "to_world": tr.Transform.translate([0.3, 0, 1.5]) @ tr.Transform.rotate([1, 0, 0], 30) @ tr.Transform.scale([0.8, 0.4, 1])},
    {"type": "cylinder", "p0": [-0.5, 0.5, 0.3], "p1": [0.6, 0.2, 1.4], "radius": 0.2},
], ids=["disk", "cylinder"])
def test02_area_light_sampling_matches_bsdf_sampling(light):
    """Emitter sampling (area density converted to solid angle) and BSDF sampling estimate
    the same direct light: image means agree within 4 standard errors (from 4 seeds each)."""
    means = {}
    for name, (es, bs) in {"emitter": (1, 0), "bsdf": (0, 1)}.items():
        scene = _lit_scene({"type": "direct", "emitter_samples": es, "bsdf_samples": bs}, light)
        m = torch.stack([tr.render(scene, spp=256, seed=s)[8:].mean() for s in range(4)]).double()
        means[name] = (m.mean(), m.std() / 2)
    (a, sa), (b, sb) = means["emitter"], means["bsdf"]
    assert a > 0.02
    assert abs(a - b) < 4 * float(torch.sqrt(sa ** 2 + sb ** 2)), means


@pytest.mark.parametrize("count", [5, 12])
def test02b_mesh_light_sampling_matches_bsdf_sampling(tmp_path, count):
    """A mesh light whose triangles have very different areas (a fan over a bent arc): its
    emitter samples pick triangles by area (a count over the CDF up to 8 triangles, a binary
    search above) and match BSDF sampling, as in test02."""
    angles = [0.0] + [math.pi * (k / count) ** 2 for k in range(1, count + 1)]
    lines = ["v 0 0 0"] + [f"v {math.cos(a):.6f} {math.sin(a):.6f} {0.3 * math.sin(3 * a):.6f}" for a in angles]
    lines += [f"f 1 {k + 3} {k + 2}" for k in range(count)]  # facing down, towards the floor
    (tmp_path / "fan.obj").write_text("\n".join(lines) + "\n")
    light = {"type": "obj", "filename": str(tmp_path / "fan.obj"),
             "to_world": tr.Transform.translate([0, 0, 1.5]) @ tr.Transform.scale(0.8)}
    test02_area_light_sampling_matches_bsdf_sampling(light)


def test03_keys_and_read_only_geometry():
    """Mitsuba's keys (bsdf..., to_world); to_world is read-only, as for spheres."""
    for case in hit_cases()[:9]:
        scene = load_case(case)
        assert "s.bsdf.reflectance.value" in scene.params
        # Mitsuba's value: a flipped disk's to_world @ scale(1, 1, -1); a cylinder's
        # to_world @ translate(p0) @ to_frame(p1 - p0) @ scale(radius, radius, length)
        np.testing.assert_allclose(scene.params["s.to_world"].numpy(), case["traverse_to_world"], atol=1e-5)
    for index in (2, 8):
        scene = load_case(hit_cases()[index])
        scene.params["s.to_world"].add_(1.0)
        with pytest.raises(ValueError, match="'s.to_world' was edited.*geometry is fixed"):
            tr.render(scene, spp=1)


@pytest.mark.parametrize("node, pattern", [
    ({"type": "cylinder", "to_world": tr.Transform.scale([2, 1, 1])}, "scale the cross-section uniformly"),
    ({"type": "cylinder", "to_world": tr.Transform.scale([1, 1, -1])}, "must not mirror"),
    ({"type": "cylinder", "p0": [0, 0, 1], "p1": [0, 0, 1]}, r"radius and \|p1 - p0\| must be positive"),
    ({"type": "disk", "to_world": tr.Transform.scale([1, 1, 0])}, "to_world must be finite and invertible"),
    ({"type": "disk", "radius": 2.0}, "unsupported parameter 'radius'"),
])
def test04_unsupported_transforms_are_scene_errors(node, pattern):
    with pytest.raises(tr.SceneError, match=pattern):
        tr.load_dict({"type": "scene", "s": node})


@pytest.mark.parametrize("name", ["analytic_shapes", "cylinder_light"])
def test05_agrees_with_mitsuba(name):
    """Textured disks and cylinders, serialized meshes, lit by a disk light
    (analytic_shapes.xml) or a cylinder light (cylinder_light.xml), against Mitsuba's
    converged renders, as test_mitsuba_agreement does: mean relative error of 4 x 4 block
    means under 0.02, our own noise under 0.007."""
    entry = json.loads((SHAPES / "renders.json").read_text())[name]
    scene = tr.load_file(SHAPES / entry["scene"])
    ref = tr.read_image(SHAPES / entry["exr"])
    assert ref.shape == (48, 64, 3)

    def blocks(img):
        return img.reshape(12, 4, 16, 4, 3).mean(dim=(1, 3))

    def metric(img, r):
        return float(((img - r).abs() / r.abs().clamp(min=0.02)).mean())

    a = blocks(tr.render(scene, spp=1024, seed=11))
    b = blocks(tr.render(scene, spp=1024, seed=12))
    noise, error = metric(a, b) / 2, metric((a + b) / 2, blocks(ref))
    print(f"{name}: error {error:.4f}, our noise {noise:.4f}")
    assert noise < 0.007
    assert error < 0.02


def test06_instances_match_mitsuba():
    """instances.xml (a shapegroup of a sphere, a serialized mesh, a disk and a cylinder
    instanced rigidly and with a uniform scale; a group without spheres instanced with a
    non-uniform scale) flattened at load: hit or miss agrees with Mitsuba on every ray; p, n
    and uv to float rounding; geometry keys as Mitsuba's mi.traverse."""
    case = hit_cases()[-1]
    assert case["file"] == "instances.xml"
    scene = tr.load_file(SHAPES / case["file"])
    keys = set(scene.params.keys())
    assert set(case["traverse_keys"]) <= keys, set(case["traverse_keys"]) - keys
    o = torch.tensor(case["origins"], dtype=torch.float32)
    d = torch.tensor(case["directions"], dtype=torch.float32)
    t, shape, p, n, uv, _ = tr._C.interact_rays(scene._native, o, d)
    hit = np.array([h[0] is not None for h in case["hits"]])
    assert 100 < hit.sum() < len(hit) - 100
    assert np.array_equal(np.isfinite(t.numpy()), hit)
    ref_p, ref_n, ref_uv = (np.array([h[k] for h in case["hits"] if h[0] is not None]) for k in (1, 2, 3))
    np.testing.assert_allclose(p.numpy()[hit], ref_p, atol=1e-4)
    np.testing.assert_allclose(n.numpy()[hit], ref_n, atol=2e-4)
    duv = np.abs(uv.numpy()[hit] - ref_uv)
    assert np.minimum(duv, 1 - duv).max() < 2e-3  # (phi of disks near their centre)


def test07_shapegroup_errors_and_shared_parameters():
    group = {"type": "shapegroup", "s": {"type": "sphere", "bsdf": {"type": "diffuse", "reflectance": 0.3}}}

    def scene(**instances):
        return tr.load_dict({"type": "scene", "grp": dict(group, __id__="grp"),
                             **{k: dict(type="instance", shape={"type": "ref", "id": "grp"}, **v)
                                for k, v in instances.items()}})

    s = scene(a={"to_world": tr.Transform.translate([2, 0, 0])}, b={})
    # one BSDF shared by both copies, keyed as Mitsuba keys the group's shape
    assert "grp.s.bsdf.reflectance.value" in s.params and "a.to_world" in s.params and "b.to_world" in s.params
    with pytest.raises(tr.SceneError, match="ellipsoid"):
        scene(a={"to_world": tr.Transform.scale([2, 1, 1])})
    with pytest.raises(tr.SceneError, match="Instancing of emitters is not supported"):
        tr.load_dict({"type": "scene", "g": {"type": "shapegroup", "__id__": "g", "s": {
            "type": "sphere", "emitter": {"type": "area"}}}})
    with pytest.raises(tr.SceneError, match="Nested ShapeGroup"):
        tr.load_dict({"type": "scene", "g": {"type": "shapegroup", "h": {"type": "shapegroup"}}})
    with pytest.raises(tr.SceneError, match="Only a shapegroup"):
        tr.load_dict({"type": "scene", "i": {"type": "instance", "s": {"type": "sphere"}}})


# -- mesh_attribute textures ------------------------------------------------------------------

def _colored_quads(tmp_path, dtype=torch.float64, res=3, max_depth=3):
    """A vertex-coloured and a face-coloured PLY quad lit by a rectangle light."""
    import make_shape_references as msr
    rng = np.random.default_rng(2)
    msr.write_color_ply(tmp_path / "v.ply", rng.uniform(0.2, 0.8, (16, 3)), False)
    msr.write_color_ply(tmp_path / "f.ply", rng.uniform(0.2, 0.8, (18, 3)), True)
    attr = lambda name: {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": name}}  # noqa: E731
    return tr.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": max_depth},
        "sensor": {"type": "perspective", "fov": 60,
                   "to_world": tr.Transform.look_at([0, -3, 3], [0, 0, 0], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "vq": {"type": "ply", "filename": "v.ply", "to_world": tr.Transform.translate([-1, 0, 0]), "bsdf": attr("vertex_color")},
        "fq": {"type": "ply", "filename": "f.ply", "to_world": tr.Transform.translate([1, 0, 0]), "bsdf": attr("face_color")},
        "light": {"type": "rectangle", "to_world": tr.Transform.translate([0, 0, 2]) @ tr.Transform.rotate([1, 0, 0], 180),
                  "emitter": {"type": "area", "radiance": 4.0}},
    }, dtype=dtype, base_dir=tmp_path)


@pytest.fixture
def colored(tmp_path):
    import sys
    sys.path.insert(0, str(REFERENCES))
    return lambda **kw: _colored_quads(tmp_path, **kw)


def test08_mesh_attributes_agree_with_mitsuba():
    """PLY vertex colours (red, green, blue: interpolated with the barycentrics) and face
    colours (r, g, b: constant per triangle) read by mesh_attribute, against Mitsuba."""
    test05_agrees_with_mitsuba("mesh_attributes")


def test09_mesh_attribute_keys_and_errors(colored, tmp_path):
    scene = colored(dtype=torch.float32)
    # Mitsuba's keys and layout: flat, 3 values per vertex (16) or per triangle (18)
    assert scene.params["vq.vertex_color"].shape == (48,)
    assert scene.params["fq.face_color"].shape == (54,)
    (tmp_path / "rgba.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "property float r\nproperty float g\nproperty float b\nproperty float alpha\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n0 0 0 1 0 0 1\n1 0 0 0 1 0 1\n0 1 0 0 0 1 1\n3 0 1 2\n")
    for node, pattern in [
        ({"type": "sphere", "bsdf": {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}},
         "does not have"),
        ({"type": "ply", "filename": "v.ply", "bsdf": {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "face_color"}}},
         "reads the mesh attribute 'face_color'"),
        ({"type": "ply", "filename": "v.ply", "bsdf": {"type": "roughplastic", "diffuse_reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}},
         "supported as a diffuse reflectance"),
        ({"type": "ply", "filename": "v.ply", "bsdf": {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_foo"}}},
         "must be one of vertex_color, face_color"),
        ({"type": "ply", "filename": "rgba.ply", "bsdf": {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}},
         "has 4 channels"),
    ]:
        with pytest.raises(tr.SceneError, match=pattern):
            tr.load_dict({"type": "scene", "s": node}, base_dir=tmp_path)


@pytest.mark.parametrize("key", ["vq.vertex_color", "fq.face_color"])
def test10_mesh_attribute_gradcheck_replay(colored, key):
    """Exact in replay mode (float64): the interpolation weights scatter the adjoint into the
    three vertices (or the face) of each hit, as the lookup gathered them."""
    scene = colored(res=3)
    x0 = scene.params[key].detach().clone()

    def f(x):
        scene.params[key] = x
        return tr.render(scene, spp=2, seed=7, seed_grad=7)

    x = x0.clone().requires_grad_()
    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-5, rtol=1e-3, nondet_tol=0.0)


def test11_mesh_attribute_gradients_are_unbiased(colored):
    """Independent backward seeds: the mean gradient of a linear loss along a random direction
    agrees with central finite differences (common random numbers) within 4 standard errors,
    and is resolved away from zero (as tests/test_gradients.py::test11)."""
    import math
    res, spp, n_seeds = 6, 4, 64
    scene = colored(res=res, max_depth=4)
    w = torch.rand(res, res, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    g = torch.Generator().manual_seed(5)
    for key in ("vq.vertex_color", "fq.face_color"):
        p = scene.params[key]
        direction = torch.rand(p.shape, generator=g, dtype=torch.float64) + 0.5
        h = 1e-2 * float(p.abs().mean())
        d = directional_derivatives(scene, key, w, direction, spp, n_seeds, h=h)
        rev, fd = d["backward"], d["fd"]
        se = math.sqrt(rev.var() / n_seeds + fd.var() / n_seeds)
        print(f"{key}: backward {rev.mean():+.4f} finite diff. {fd.mean():+.4f} (stderr {se:.4f})")
        assert abs(rev.mean() - fd.mean()) < 4 * se
        assert abs(float(rev.mean())) > 4 * float(rev.std()) / math.sqrt(n_seeds)
