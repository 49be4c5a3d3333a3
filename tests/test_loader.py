"""Scene loading (torch_rbpt/loader.py, mitsuba_xml.py): the shared Mitsuba 3 scenes, the
dict format, parameter keys, and errors that name the culprit."""
import re

import numpy as np
import pytest
import torch

import torch_rbpt as tr
from conftest import ROOT

SHARED_SCENES = [
    ("cbox/cbox.xml", {"res": 16}),
    ("cornell-box/scene_v3.xml", {"resx": 16, "resy": 16}),
    ("veach-mis/integrator_direct_both.xml", {}),
    ("veach-mis/integrator_direct_bsdf.xml", {}),
    ("veach-mis/integrator_direct_lum.xml", {}),
]


@pytest.mark.parametrize("path,defaults", SHARED_SCENES)
def test01_shared_scenes_load_and_render_finite(shared, path, defaults):
    scene = tr.load_file(shared / path, **defaults)
    if "veach" in path:
        assert (scene.sensor.film.width, scene.sensor.film.height) == (768, 512)
        scene.sensor.film.width, scene.sensor.film.height = 24, 16
    image = tr.render(scene, spp=4)
    assert image.dtype == torch.float32
    assert image.shape == (scene.sensor.film.height, scene.sensor.film.width, 3)
    assert torch.isfinite(image).all()
    assert image.mean() > 0.01


def test02_cbox_parameters_and_settings(shared):
    scene = tr.load_file(shared / "cbox/cbox.xml", res=32, spp=7, max_depth=3)
    p = scene.params
    torch.testing.assert_close(p["red.reflectance.value"], torch.tensor([0.570068, 0.0430135, 0.0443706]))
    torch.testing.assert_close(p["light.emitter.radiance.value"], torch.tensor([18.387, 13.9873, 6.75357]))
    assert p["mirror.specular_reflectance.value"].shape == (1,)
    assert scene.sensor.spp == 7 and scene.integrator.max_depth == 3
    assert scene.sensor.film.filter == "tent" and scene.sensor.fov_axis == "smaller"
    assert (scene.sensor.film.width, scene.sensor.film.height) == (32, 32)


def test03_keys_of_nested_and_unnamed_objects(shared):
    scene = tr.load_file(shared / "cornell-box/scene_v3.xml", resx=8, resy=8)
    assert "LeftWallBSDF.brdf_0.reflectance.value" in scene.params
    assert "Light.emitter.radiance.value" in scene.params
    veach = tr.load_file(shared / "veach-mis/integrator_direct_both.xml")
    assert "sphere_4.emitter.radiance.value" in veach.params
    # roughplastic keys its roughness without ".value", as Mitsuba does.
    assert "obj_0.bsdf.alpha" in veach.params
    torch.testing.assert_close(veach.params["obj_3.bsdf.alpha"], torch.tensor([0.1]))


def test04_params_are_live_and_checked(shared):
    scene = tr.load_file(shared / "cbox/cbox.xml", res=8)
    before = tr.render(scene, spp=4)
    scene.params["light.emitter.radiance.value"].mul_(2.0)
    after = tr.render(scene, spp=4)
    torch.testing.assert_close(after, 2 * before, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match=r"red\.reflectance\.value.*shape \(3,\)"):
        scene.params["red.reflectance.value"] = torch.zeros(4)
    with pytest.raises(ValueError, match=r"red\.reflectance\.value.*dtype"):
        scene.params["red.reflectance.value"] = torch.zeros(3, dtype=torch.float64)
    with pytest.raises(KeyError, match="no scene parameter 'nope'"):
        scene.params["nope"]
    scene.params["red.reflectance.value"] = torch.tensor([0.1, 0.2, 0.3])
    assert scene.params["red.reflectance.value"][1] == pytest.approx(0.2)


def test04b_geometry_and_iors_are_read_only(shared):
    scene = tr.load_file(shared / "cbox/cbox.xml", res=8)
    assert scene.params["redwall.vertex_positions"].shape == (12,)
    torch.testing.assert_close(scene.params["glass.eta"], torch.tensor([1.5046 / 1.000277]))
    with pytest.raises(ValueError, match="'glass.eta' cannot be changed"):
        scene.params["glass.eta"] = torch.tensor([1.3])
    scene.params["redwall.vertex_positions"].add_(1.0)
    with pytest.raises(ValueError, match="'redwall.vertex_positions' was edited.*geometry is fixed"):
        tr.render(scene, spp=1)


def test05_float64_scenes_render_float64(shared):
    scene = tr.load_file(shared / "cbox/cbox.xml", res=8, dtype=torch.float64)
    image = tr.render(scene, spp=2)
    assert image.dtype == torch.float64
    image32 = tr.render(tr.load_file(shared / "cbox/cbox.xml", res=8), spp=2)
    torch.testing.assert_close(image.float(), image32, rtol=1e-3, atol=1e-4)


def _dict_box(**overrides):
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": tr.Transform.look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 12, "height": 8}},
        "red": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.1, 0.1]}},
        "wall": {"type": "rectangle", "bsdf": {"type": "ref", "id": "red"},
                 "to_world": tr.Transform.scale([2, 2, 1])},
        "light": {"type": "point", "position": [0, 0, 2], "intensity": {"type": "rgb", "value": [5, 5, 5]}},
    }
    scene.update(overrides)
    return scene


def test06_dict_format_with_transforms_and_matrices():
    scene = tr.load_dict(_dict_box())
    assert set(scene.params) == {"red.reflectance.value", "light.intensity.value", "wall.to_world"}
    image = tr.render(scene, spp=4)
    assert image.shape == (8, 12, 3) and float(image[..., 0].mean()) > 0
    # The same scene with a plain 4x4 matrix for to_world.
    m = tr.Transform.look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]).matrix.tolist()
    d = _dict_box()
    d["sensor"]["to_world"] = m
    torch.testing.assert_close(tr.render(tr.load_dict(d), spp=4), image)


def test07_point_light_on_plane_matches_analytic_value():
    # Irradiance from a point light I at height h onto a diffuse plane: E = I / h^2 at the
    # foot; radiance = rho / pi * E.
    scene = tr.load_dict(_dict_box(sensor={
        "type": "perspective", "fov": 1.0,
        "to_world": tr.Transform.look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}}}))
    image = tr.render(scene, spp=16)
    expected = torch.tensor([0.8, 0.1, 0.1]) / np.pi * 5 / 4
    torch.testing.assert_close(image[0, 0], expected, rtol=2e-3, atol=0)


def test08_transform_conventions():
    t = tr.Transform.translate([1, 2, 3]) @ tr.Transform.rotate([0, 0, 1], 90) @ tr.Transform.scale(2)
    np.testing.assert_allclose(t.apply_point([1, 0, 0]), [1, 4, 3], atol=1e-12)
    cam = tr.Transform.look_at([0, 0, 4], [0, 0, 0], [0, 1, 0])
    np.testing.assert_allclose(cam.matrix[:3, 2], [0, 0, -1])  # looks along -z
    np.testing.assert_allclose(cam.matrix[:3, 0], [-1, 0, 0])  # local x points left
    # Chained as in Mitsuba 3 (T().translate(v).rotate(...)): each call composes on the
    # right, instead of starting a new transform that drops what came before.
    chained = tr.Transform.translate([1, 2, 3]).rotate([0, 0, 1], 90).scale(2)
    np.testing.assert_allclose(chained.matrix, t.matrix, atol=1e-12)
    np.testing.assert_allclose(tr.Transform().scale(3).matrix, np.diag([3, 3, 3, 1]))
    np.testing.assert_allclose(cam.translate([0, 0, 1]).apply_point([0, 0, 0]), [0, 0, 3])


# -- errors --------------------------------------------------------------------------------

def _write(tmp_path, body, name="scene.xml"):
    path = tmp_path / name
    path.write_text(f'<scene version="3.0.0">\n{body}\n</scene>\n')
    return path


def test09_unknown_plugin_names_file_line_and_supported(tmp_path):
    path = _write(tmp_path, '    <bsdf type="diffuse" id="a"/>\n    <bsdf type="velvet" id="b"/>')
    with pytest.raises(tr.SceneError, match=re.escape(f"{path}:3") + ".*velvet.*supported: .*diffuse"):
        tr.load_file(path)


def test10_unknown_parameter_is_named(tmp_path):
    path = _write(tmp_path, '<bsdf type="diffuse">\n  <float name="roughness" value="1"/>\n</bsdf>')
    with pytest.raises(tr.SceneError, match=r"scene\.xml:2: diffuse: unsupported parameter 'roughness'"):
        tr.load_file(path)


def test11_missing_mesh_file(tmp_path):
    path = _write(tmp_path, '<shape type="obj">\n  <string name="filename" value="nothere.obj"/>\n</shape>')
    with pytest.raises(tr.SceneError, match=r"scene\.xml:2: obj: file 'nothere.obj' not found"):
        tr.load_file(path)


def test12_malformed_xml_reports_its_line(tmp_path):
    path = tmp_path / "bad.xml"
    path.write_text('<scene version="3.0.0">\n  <bsdf type="diffuse">\n  </shape>\n</scene>\n')
    with pytest.raises(tr.SceneError, match=r"bad\.xml:3: malformed XML"):
        tr.load_file(path)


def test13_defaults_and_overrides(tmp_path):
    path = _write(tmp_path, '<default name="w" value="5"/>\n<sensor type="perspective">'
                            '<film type="hdrfilm"><integer name="width" value="$w"/>'
                            '<integer name="height" value="3"/></film></sensor>')
    assert tr.load_file(path).sensor.film.width == 5
    assert tr.load_file(path, w=7).sensor.film.width == 7
    # As Mitsuba: a keyword argument that no attribute uses is an error, even with a <default>.
    with pytest.raises(tr.SceneError, match=r"parameter\(s\) h given as keyword arguments are not used"):
        tr.load_file(path, h=7)
    bad = _write(tmp_path, '<bsdf type="diffuse"><float name="reflectance" value="$x"/></bsdf>', "b.xml")
    with pytest.raises(tr.SceneError, match=r"b\.xml:2: undefined parameter \$x"):
        tr.load_file(bad)
    # ... and a $name needs no <default> when it is given as a keyword argument.
    assert tr.load_file(bad, x=0.25).params["diffuse_0.reflectance.value"].tolist() == [0.25]


def test14_wrong_category_and_missing_reference(tmp_path):
    path = _write(tmp_path, '<shape type="diffuse"/>')
    with pytest.raises(tr.SceneError, match="'diffuse' is a bsdf, not a shape|unsupported shape plugin 'diffuse'"):
        tr.load_file(path)
    path = _write(tmp_path, '<shape type="sphere"><ref id="nothing"/></shape>', "r.xml")
    with pytest.raises(tr.SceneError, match="unknown id 'nothing'"):
        tr.load_file(path)


def test15_include_and_path(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "mat.xml").write_text(
        '<scene version="3.0.0"><bsdf type="diffuse" id="m"><rgb name="reflectance" value="0.25"/></bsdf></scene>')
    path = _write(tmp_path, '<path value="parts"/>\n<include filename="mat.xml"/>')
    scene = tr.load_file(path)
    torch.testing.assert_close(scene.params["m.reflectance.value"], torch.full((3,), 0.25))


def test16_fov_axis_and_focal_length():
    s = tr.load_dict({"type": "scene", "sensor": {"type": "perspective", "fov": 40, "fov_axis": "y",
                      "film": {"type": "hdrfilm", "width": 200, "height": 100}}}).sensor
    assert s.x_fov() == pytest.approx(np.degrees(2 * np.arctan(np.tan(np.radians(20)) * 2)))
    s.fov_axis = "smaller"  # wider than tall: the smaller axis is y
    assert s.x_fov() == pytest.approx(np.degrees(2 * np.arctan(np.tan(np.radians(20)) * 2)))
    s.fov_axis = "larger"
    assert s.x_fov() == pytest.approx(40)
    # No fov: Mitsuba's 50 mm lens on a 36 x 24 mm film, along the diagonal (values read
    # off Mitsuba 3.9.1's x_fov for 64x32 and 32x64 films).
    for size, x_fov in [((64, 32), 42.31171), ((32, 64), 21.90214)]:
        s = tr.load_dict({"type": "scene", "sensor": {"type": "perspective", "film": {
            "type": "hdrfilm", "width": size[0], "height": size[1]}}}).sensor
        assert s.x_fov() == pytest.approx(x_fov, abs=1e-4)


def test17_bundled_scene_loads():
    scene = tr.load_file(ROOT / "torch_rbpt/scenes/cornell_box.xml", res=16)
    assert "red.reflectance.value" in scene.params and "light.emitter.radiance.value" in scene.params
    assert torch.isfinite(tr.render(scene, spp=4)).all()


def test18_include_cycle_names_the_include_and_the_cycle(tmp_path):
    a = _write(tmp_path, '<include filename="b.xml"/>', "a.xml")
    b = _write(tmp_path, '\n<include filename="a.xml"/>', "b.xml")
    with pytest.raises(tr.SceneError, match=re.escape(f"{b}:3: <include> cycle: {a} -> {b} -> {a}")):
        tr.load_file(a)
    me = _write(tmp_path, '<include filename="self.xml"/>', "self.xml")
    with pytest.raises(tr.SceneError, match=re.escape(f"{me}:2: <include> cycle: {me} -> {me}")):
        tr.load_file(me)
    # Including one file twice, side by side, is not a cycle.
    (tmp_path / "m.xml").write_text('<scene version="3.0.0"><default name="x" value="1"/></scene>')
    tr.load_file(_write(tmp_path, '<include filename="m.xml"/><include filename="m.xml"/>', "twice.xml"))


def test19_unknown_nested_plugin_lists_the_supported_ones_of_its_kind(tmp_path):
    bsdfs = "supported: conductor, dielectric, diffuse, roughconductor, roughplastic, twosided"
    with pytest.raises(tr.SceneError, match=re.escape(f"unsupported bsdf plugin 'plastic' ({bsdfs})")):
        tr.load_dict({"type": "scene", "s": {"type": "sphere", "bsdf": {"type": "plastic"}}})
    with pytest.raises(tr.SceneError, match=r"'film': unsupported film plugin 'ldrfilm' \(supported: hdrfilm\)"):
        tr.load_dict({"type": "scene", "s": {"type": "perspective", "film": {"type": "ldrfilm"}}})
    # A key that names no kind: all supported plugins are listed.
    with pytest.raises(tr.SceneError, match=r"unsupported plugin 'plastic' \(supported: area, .*twosided\)"):
        tr.load_dict({"type": "scene", "s": {"type": "sphere", "mat": {"type": "plastic"}}})
    # XML: the kind comes from the tag, the location is the nested element's line.
    path = _write(tmp_path, '<shape type="sphere">\n  <bsdf type="plastic"/>\n</shape>')
    with pytest.raises(tr.SceneError, match=re.escape(f"{path}:3: sphere: 'bsdf': unsupported bsdf "
                                                      f"plugin 'plastic' ({bsdfs})")):
        tr.load_file(path)


@pytest.mark.parametrize("change, pattern", [
    # Found by fuzz/fuzz_dict.py: each raised TypeError, KeyError, a numpy ValueError or
    # (for out-of-range ints) a pybind11 RuntimeError at render time.
    ({"wall": {"type": ["rectangle"]}}, r"'wall': the plugin type must be a string, got list"),
    ({"wall": {"type": np.array([1.0, 2.0])}}, r"'wall': the plugin type must be a string"),
    ({"wall": {"type": "rectangle", "bsdf": {"type": {"a": 1}}}}, r"'bsdf': the plugin type must be a string"),
    ({"red": {"type": "diffuse", "reflectance": {"type": "rgb"}}}, r"'reflectance': an rgb needs a 'value'"),
    ({"wall": {"type": "rectangle", "bsdf": {"type": "ref", "id": ["red"]}}}, r"a ref needs a string 'id'"),
    ({"red": {"type": "diffuse", "reflectance": {"type": "rgb", "value": {"x": 1}}}},
     r"parameter 'reflectance' must be numbers"),
    ({"red": {"type": "diffuse", "reflectance": [0.5, "x", 0.5]}}, r"diffuse: parameter 'reflectance' must be numbers"),
    ({"light": {"type": "point", "position": [0, {}, 2]}}, r"point: parameter 'position' must be numbers"),
    ({"wall": {"type": "rectangle", "to_world": [[{}]]}}, r"rectangle: .*to_world"),
    ({"integrator": {"type": "path", "max_depth": 2 ** 40}}, r"path: parameter 'max_depth' must fit in 32 bits"),
    ({"sensor": {"type": "perspective", "sampler": {"type": "independent", "sample_count": 1e300}}},
     r"independent: parameter 'sample_count' must fit in 32 bits"),
])
def test20_dict_values_of_wrong_type_are_scene_errors(change, pattern):
    with pytest.raises(tr.SceneError, match=r"<dict>: .*" + pattern):
        tr.load_dict(_dict_box(**change))


def test21_boolean_parameters_reject_arrays_and_tensors():
    # Found by fuzz/fuzz_dict.py: a tensor sample_visible raised torch's RuntimeError
    # "Boolean value of Tensor ... is ambiguous".
    bsdf = {"type": "roughconductor", "sample_visible": torch.tensor([1.0, 0.0])}
    with pytest.raises(tr.SceneError, match=r"<dict>: roughconductor: parameter 'sample_visible' must be a bool"):
        tr.load_dict(_dict_box(red=bsdf))
    with pytest.raises(tr.SceneError, match=r"<dict>: rectangle: parameter 'flip_normals' must be a bool"):
        tr.load_dict(_dict_box(wall={"type": "rectangle", "flip_normals": np.array([True, False])}))
    assert tr.load_dict(_dict_box(red={"type": "roughconductor", "sample_visible": "true"}))
    # The same for a conductor's material given as an array (numpy's "truth value ... ambiguous").
    with pytest.raises(tr.SceneError, match=r"<dict>: conductor: parameter 'material' must be a string"):
        tr.load_dict(_dict_box(red={"type": "conductor", "material": np.array([1.0, 2.0])}))


def test22_errors_of_the_core_name_the_plugin():
    # Found by fuzz/fuzz_dict.py: a second constant emitter was a bare ValueError from the
    # C++ side ("only one constant emitter is supported") without the plugin's name.
    with pytest.raises(tr.SceneError, match=r"<dict>: constant: only one constant emitter is supported"):
        tr.load_dict(_dict_box(sky={"type": "constant"}, sky2={"type": "constant"}))


@pytest.mark.parametrize("to_world", [np.diag([1.0, 1.0, 1.0, 2.0]), np.diag([1.0, np.nan, 1.0, 1.0])])
def test23_to_world_must_be_affine_and_finite(to_world):
    # Found by fuzz/fuzz_dict.py: a last row other than (0, 0, 0, 1) was a MeshError from
    # Mesh.transformed without the shape's name.
    with pytest.raises(tr.SceneError, match=r"<dict>: rectangle: to_world must be an affine transform"):
        tr.load_dict(_dict_box(wall={"type": "rectangle", "to_world": to_world}))


def test24_singular_to_world_names_the_shape():
    # Found by fuzz/fuzz_dict.py: a MeshError from Mesh.transformed without the shape's name.
    with pytest.raises(tr.SceneError, match=r"<dict>: cube: to_world: .*singular"):
        tr.load_dict(_dict_box(box={"type": "cube", "to_world": np.diag([1.0, 0.0, 1.0, 1.0])}))


@pytest.mark.parametrize("body, pattern", [
    # Found by fuzz/fuzz_xml.py: ValueErrors from Transform or float() without file and line.
    ('<transform name="to_world">\n<rotate value="0 0 0" angle="3"/></transform>',
     r":3: <rotate>: rotate: the axis must not be zero"),
    ('<transform name="to_world">\n<translate x="one"/></transform>', r":3: <translate>: .*'one'"),
    ('<transform name="to_world">\n<lookat origin="1 1 1" target="1 1 1"/></transform>',
     r":3: <lookat>: look_at: origin and target coincide"),
    ('<point name="center" x="0" y="up" z="0"/>', r":2: center\.y: cannot parse a number from 'up'"),
])
def test25_xml_transform_and_point_errors_name_file_and_line(tmp_path, body, pattern):
    path = _write(tmp_path, f'<shape type="sphere">{body}</shape>')
    with pytest.raises(tr.SceneError, match=re.escape(str(path)) + pattern):
        tr.load_file(path)


def test26_singular_camera_transform_is_refused(tmp_path):
    # Found by fuzz/fuzz_xml.py: a camera to_world with a zero column loaded and then
    # crashed the interpreter (segmentation fault) in the renderer.
    path = _write(tmp_path, '<sensor type="perspective">\n<transform name="to_world">\n'
                            '<matrix value="0 0 0 0 0 1 0 0 0 0 1 4 0 0 0 1"/></transform></sensor>')
    with pytest.raises(tr.SceneError, match=re.escape(f"{path}:2: perspective: to_world must be invertible")):
        tr.load_file(path)


def test27_filenames_must_be_strings_the_file_system_accepts():
    # Found by fuzz/fuzz_dict.py: a dict as filename became a name too long for the file
    # system, and Path.exists raised a bare OSError.
    with pytest.raises(tr.SceneError, match=r"<dict>: obj: parameter 'filename' must be a string"):
        tr.load_dict(_dict_box(mesh={"type": "obj", "filename": {"type": "rgb", "value": 1}}))
    with pytest.raises(tr.SceneError, match=r"<dict>: obj: cannot access file 'xxxx.*File name too long"):
        tr.load_dict(_dict_box(mesh={"type": "obj", "filename": "x" * 5000}))


def test28_duplicate_ids_name_file_and_line(tmp_path):
    # Found by fuzz_xml: the error named the parameter key but not where it came from.
    path = tmp_path / "dup.xml"
    path.write_text('<scene version="3.0.0">\n  <bsdf type="diffuse" id="part"/>\n'
                    '  <bsdf type="diffuse" id="part"/>\n</scene>\n')
    with pytest.raises(tr.SceneError, match=r"dup\.xml:3: two parameters share the key 'part\.reflectance\.value'"):
        tr.load_file(path)


def test29_non_finite_values_are_refused_at_load():
    # Found by fuzz_dict: -inf loaded, and only the render refused it.
    scene = {"type": "scene", "s": {"type": "sphere", "bsdf": {
        "type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, float("-inf"), 0.0]}}}}
    with pytest.raises(tr.SceneError, match=r"<dict>: 's\.bsdf\.reflectance\.value' has a non-finite value"):
        tr.load_dict(scene)


def test30_overflowing_transform_is_refused_not_a_crash(tmp_path):
    # Found by fuzz_xml: a translation beyond float32 made the vertices infinite and the BVH
    # build crashed the interpreter.
    path = tmp_path / "huge.xml"
    path.write_text('<scene version="3.0.0">\n  <shape type="cube">\n    <transform name="to_world">\n'
                    '      <translate x="-2e124"/>\n    </transform>\n  </shape>\n</scene>\n')
    with pytest.warns(RuntimeWarning):
        with pytest.raises(tr.SceneError, match=r"huge\.xml:2: cube: mesh vertex positions must be finite"):
            tr.load_file(path)


def test40_serialized_shape_loads_with_mitsuba_keys_and_errors(tmp_path):
    from torch_rbpt.meshes import write_serialized
    write_serialized(tmp_path / "m.serialized", [
        dict(positions=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]]),
        dict(positions=[[0, 0, 0], [2, 0, 0], [0, 2, 0]], faces=[[0, 1, 2]])])
    scene = tr.load_dict({"type": "scene", "m": {"type": "serialized", "filename": "m.serialized",
                                                "shape_index": 1, "to_world": tr.Transform.translate([0, 0, 1])}},
                         base_dir=tmp_path)
    assert torch.equal(scene.params["m.vertex_positions"],
                       torch.tensor([0, 0, 1, 2, 0, 1, 0, 2, 1], dtype=torch.float32))
    # Mitsuba 3.9.1 rejects these too ("unreferenced property")
    for extra in ({"max_smooth_angle": 30.0}, {"flip_tex_coords": True}):
        with pytest.raises(tr.SceneError, match=f"unsupported parameter '{list(extra)[0]}'"):
            tr.load_dict({"type": "scene", "m": {"type": "serialized", "filename": "m.serialized", **extra}},
                         base_dir=tmp_path)
    with pytest.raises(tr.SceneError, match="serialized: .*shape_index 2 is out of range"):
        tr.load_dict({"type": "scene", "m": {"type": "serialized", "filename": "m.serialized",
                                             "shape_index": 2}}, base_dir=tmp_path)
    with pytest.raises(tr.SceneError, match="shape_index must be >= 0"):
        tr.load_dict({"type": "scene", "m": {"type": "serialized", "filename": "m.serialized",
                                             "shape_index": -1}}, base_dir=tmp_path)


# -- Mitsuba 3's own scene files: versions, $name, top-level objects (MITSUBA_FACTS.md, n) --

def _versioned(tmp_path, version, body, name="v.xml"):
    path = tmp_path / name
    path.write_text(f'<scene version="{version}">\n{body}\n</scene>\n')
    return path


def test31_versions_2x_load_like_3x_and_pre_2_names_are_upgraded(tmp_path):
    body = ('<integrator type="path"><integer name="{}" value="3"/></integrator>\n'
            '<sensor type="perspective"><string name="{}" value="y"/><float name="fov" value="30"/></sensor>')
    for version in ("2.0.0", "2.1.0", "3.0.0", "3.5.2"):
        scene = tr.load_file(_versioned(tmp_path, version, body.format("max_depth", "fov_axis")))
        assert (scene.integrator.max_depth, scene.sensor.fov_axis) == (3, "y")
    # Before 2.0.0, parameter names were camelCase; Mitsuba renames them (not <default> names).
    old = _versioned(tmp_path, "0.5.0", '<default name="myDepth" value="4"/>\n' +
                     body.format("maxDepth", "fovAxis").replace('value="3"', 'value="$myDepth"'))
    scene = tr.load_file(old)
    assert (scene.integrator.max_depth, scene.sensor.fov_axis) == (4, "y")
    # ... but a 2.x file keeps its names, and a camelCase name there is unsupported.
    with pytest.raises(tr.SceneError, match="unsupported parameter 'maxDepth'"):
        tr.load_file(_versioned(tmp_path, "2.0.0", body.format("maxDepth", "fov_axis")))
    for bad in ("3.0", "3", "2.x"):  # Mitsuba: "Invalid version number"
        with pytest.raises(tr.SceneError, match=rf"v\.xml:1: invalid version number '{re.escape(bad)}'"):
            tr.load_file(_versioned(tmp_path, bad, ""))
    path = tmp_path / "none.xml"
    path.write_text("<scene>\n</scene>\n")
    with pytest.raises(tr.SceneError, match=r"none\.xml:1: <scene> needs a version attribute"):
        tr.load_file(path)


def test32_parameters_without_default_come_from_keyword_arguments(tmp_path):
    path = _write(tmp_path, '<sensor type="perspective"><sampler type="independent">'
                            '<integer name="sample_count" value="$spp"/></sampler>'
                            '<film type="hdrfilm"><integer name="width" value="$res"/></film></sensor>')
    scene = tr.load_file(path, spp=16, res="12")
    assert (scene.sensor.spp, scene.sensor.film.width) == (16, 12)
    with pytest.raises(tr.SceneError, match=r"scene\.xml:2: undefined parameter \$res"):
        tr.load_file(path, spp=16)
    with pytest.raises(tr.SceneError, match="parameter\\(s\\) foo given as keyword arguments are not used"):
        tr.load_file(path, spp=16, res=12, foo=1)


def test33_top_level_emitters_samplers_films_and_filters_are_referenced(tmp_path):
    # Mitsuba's cbox declares its area light after the shape that references it. The keys
    # follow Mitsuba's traversal: an object declared before its first user keeps its id,
    # one declared after is named through that user (lamp.emitter, lamp.bsdf).
    path = _write(tmp_path, '''
    <emitter type="area" id="early"><rgb name="radiance" value="1, 2, 3"/></emitter>
    <shape type="rectangle" id="lamp"><ref id="light"/><ref id="late"/></shape>
    <shape type="sphere" id="ball"><ref id="early"/></shape>
    <emitter type="area" id="light"><rgb name="radiance" value="4, 5, 6"/></emitter>
    <bsdf type="diffuse" id="late"><rgb name="reflectance" value="0.1, 0.2, 0.3"/></bsdf>
    <emitter type="area" id="unused"/>
    <sampler type="independent" id="samp"><integer name="sample_count" value="7"/></sampler>
    <rfilter type="tent" id="filt"><float name="radius" value="1.5"/></rfilter>
    <film type="hdrfilm" id="film"><integer name="width" value="8"/><integer name="height" value="6"/><ref id="filt"/></film>
    <sensor type="perspective"><ref id="samp"/><ref id="film"/></sensor>''')
    scene = tr.load_file(path)
    p = scene.params
    assert p["lamp.emitter.radiance.value"].tolist() == [4, 5, 6]
    assert p["early.radiance.value"].tolist() == [1, 2, 3]
    assert p["lamp.bsdf.reflectance.value"].tolist() == pytest.approx([0.1, 0.2, 0.3])
    assert "light.radiance.value" not in p and "late.reflectance.value" not in p
    assert (scene.sensor.spp, scene.sensor.film.width, scene.sensor.film.filter,
            scene.sensor.film.filter_radius) == (7, 8, "tent", 1.5)
    twice = _write(tmp_path, '<emitter type="area" id="l"/>\n<shape type="sphere" id="a"><ref id="l"/></shape>\n'
                             '<shape type="sphere" id="b"><ref id="l"/></shape>', "twice.xml")
    with pytest.raises(tr.SceneError, match=r"twice\.xml:4: sphere: its area emitter is already attached to 'a'"):
        tr.load_file(twice)


def test34_a_referenced_area_light_lights_the_scene(tmp_path):
    # The same scene with the light nested in its shape or declared after it and referenced
    # renders the same image.
    def scene_xml(light_nested):
        light = '<emitter type="area"><rgb name="radiance" value="5"/></emitter>'
        return f'''
        <sensor type="perspective"><transform name="to_world"><lookat origin="0, 2, 3" target="0, 0, 0"/></transform>
            <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
        <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/></transform></shape>
        <shape type="sphere" id="s"><point name="center" x="0" y="1" z="0"/><float name="radius" value="0.2"/>
            {light if light_nested else '<ref id="l"/>'}</shape>
        {'' if light_nested else light.replace('type="area"', 'type="area" id="l"')}'''
    a = tr.render(tr.load_file(_write(tmp_path, scene_xml(True), "a.xml")), spp=4)
    b = tr.render(tr.load_file(_write(tmp_path, scene_xml(False), "b.xml")), spp=4)
    assert torch.equal(a, b) and float(a.mean()) > 0.01


def test35_nested_objects_with_an_id_can_be_referenced(tmp_path):
    # Mitsuba 3.9.1: a BSDF declared inside shape `a` with id "inner" is usable by shape `b`;
    # its key is named through `a`, where it is first reached.
    path = _write(tmp_path, '<shape type="sphere" id="a"><bsdf type="diffuse" id="inner">'
                            '<rgb name="reflectance" value="0.1, 0.2, 0.3"/></bsdf></shape>\n'
                            '<shape type="sphere" id="b"><ref id="inner"/></shape>')
    scene = tr.load_file(path)
    assert [k for k in scene.params if k.endswith(".value")] == ["a.bsdf.reflectance.value"]


def test36_an_emitters_default_bsdf_is_black(tmp_path):
    # Mitsuba 3 gives a shape without a BSDF a diffuse one of reflectance 0.5, or 0 where the
    # shape carries an area emitter (nested or referenced): a light does not reflect.
    path = _write(tmp_path, '''
    <emitter type="area" id="l"><rgb name="radiance" value="10"/></emitter>
    <shape type="rectangle" id="near"><emitter type="area"><rgb name="radiance" value="1"/></emitter></shape>
    <shape type="rectangle" id="far"><ref id="l"/>
        <transform name="to_world"><scale value="20"/><rotate y="1" angle="180"/><translate z="4"/></transform></shape>
    <shape type="sphere" id="plain"><point name="center" x="0" y="0" z="-5"/></shape>
    <sensor type="perspective"><float name="fov" value="20"/>
        <transform name="to_world"><lookat origin="0, 0, 2" target="0, 0, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="6"/><integer name="height" value="6"/></film></sensor>''')
    scene = tr.load_file(path)
    p = scene.params
    assert p["near.bsdf.reflectance.value"].tolist() == [0] and p["far.bsdf.reflectance.value"].tolist() == [0]
    assert p["plain.bsdf.reflectance.value"].tolist() == [0.5]
    # The camera sees only `near`, lit by `far` (radiance 10) behind the camera: its own
    # radiance, nothing reflected (a reflectance of 0.5 would add about 2.5).
    image = tr.render(scene, spp=4)
    torch.testing.assert_close(image, torch.ones_like(image))
    assert tr.load_dict({"type": "scene", "s": {"type": "sphere", "emitter": {"type": "area"}}}
                        ).params["s.bsdf.reflectance.value"].tolist() == [0]


def test37_textured_emission_is_a_clear_error():
    for emitter, name in (({"type": "point"}, "intensity"), ({"type": "constant"}, "radiance")):
        scene = {"type": "scene", "e": {**emitter, name: {"type": "checkerboard"}}}
        with pytest.raises(tr.SceneError, match=rf"<dict>: {emitter['type']}: .*textured .* not supported"):
            tr.load_dict(scene)


@pytest.mark.parametrize("body, message", [
    ('<medium type="homogeneous" id="fog"/>', r"<medium>: participating media are not supported"),
    ('<integrator type="volpath"/>', r"plugin 'volpath': participating media are not supported"),
    ('<bsdf type="polarizer"/>', r"plugin 'polarizer': polarisation is not supported"),
    ('<bsdf type="hair"/>', r"plugin 'hair': hair BSDFs are not supported"),
    ('<shape type="bsplinecurve"/>', r"plugin 'bsplinecurve': curves are not supported"),
    ('<shape type="sdfgrid"/>', r"plugin 'sdfgrid': SDF grids are not supported"),
    ('<emitter type="area"><spectrum type="blackbody" name="radiance"/></emitter>',
     r'<spectrum type="blackbody">: spectrum plugins are not supported'),
])
def test38_capabilities_we_lack_are_named(tmp_path, body, message):
    # Media, polarisation, curves, SDF grids, hair and spectral rendering are refused with a
    # SceneError that says which capability is missing, at the file and line.
    with pytest.raises(tr.SceneError, match=r"scene\.xml:2: " + message):
        tr.load_file(_write(tmp_path, body))
