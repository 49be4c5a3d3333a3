"""<spectrum> values (torch_rbpt/spectra.py): the RGB that Mitsuba 3.9.1's RGB variants make of
constants, wavelength:value lists and .spd files, on reflectances and on emitters, read off
Mitsuba (tests/references/make_texture_values.py -> texture_values.json); their keys, their
errors, and their derivatives."""
import json

import pytest
import torch

import torch_rbpt as tr
from conftest import REFERENCES

MITSUBA = json.loads((REFERENCES / "texture_values.json").read_text())


def _attr(value):
    return f'filename="{value[5:]}"' if value.startswith("file:") else f'value="{value}"'


def _scene(tmp_path, body, name="scene.xml", **kw):
    path = tmp_path / name
    path.write_text(f'<scene version="3.0.0">\n<path value="{REFERENCES}"/>\n{body}\n</scene>\n')
    return tr.load_file(path, **kw)


@pytest.mark.parametrize("entry", MITSUBA["spectra"], ids=lambda e: e["value"])
def test01_xml_spectra_match_mitsuba(tmp_path, entry):
    # Reflectances: D65-weighted, clamped to [0, 1]; a constant stays one (unclamped) value.
    # Emission: unweighted (a constant is times the equal-energy white), clamped below at 0.
    scene = _scene(tmp_path, f'<bsdf type="diffuse" id="m"><spectrum name="reflectance" {_attr(entry["value"])}/></bsdf>\n'
                             f'<shape type="sphere"><emitter type="area" id="e">'
                             f'<spectrum name="radiance" {_attr(entry["value"])}/></emitter></shape>')
    refl = scene.params["m.reflectance.value"]
    rad = scene.params["sphere_0.emitter.radiance.value"]
    assert refl.shape == (len(entry["reflectance"]),) and rad.shape == (3,)
    torch.testing.assert_close(refl, torch.tensor(entry["reflectance"]), rtol=2e-5, atol=2e-6)
    torch.testing.assert_close(rad, torch.tensor(entry["radiance"]), rtol=2e-5, atol=2e-6)


def test02_dict_spectra_equal_xml():
    pairs = [(400, 0.1), (500, 0.5), (600, 0.8), (700, 0.2)]
    entry = next(e for e in MITSUBA["spectra"] if e["value"].startswith("400:0.1"))
    scene = tr.load_dict({
        "type": "scene",
        "m": {"type": "diffuse", "reflectance": {"type": "spectrum", "value": pairs}},
        "c": {"type": "diffuse", "reflectance": {"type": "spectrum", "value": 0.3}},
        "p": {"type": "point", "intensity": {"type": "spectrum", "value": pairs}},
        "sky": {"type": "constant", "radiance": {"type": "spectrum", "value": 2.0}},
    })
    torch.testing.assert_close(scene.params["m.reflectance.value"], torch.tensor(entry["reflectance"]), rtol=2e-5, atol=2e-6)
    torch.testing.assert_close(scene.params["p.intensity.value"], torch.tensor(entry["radiance"]), rtol=2e-5, atol=2e-6)
    assert scene.params["c.reflectance.value"].tolist() == pytest.approx([0.3])
    # Mitsuba 3.9.1: a constant emitted spectrum of 2 is 2 x xyz_to_srgb(1, 1, 1).
    assert scene.params["sky.radiance.value"].tolist() == pytest.approx([2.409588, 1.896582, 1.817832], rel=1e-6)


@pytest.mark.parametrize("attr,message", [
    ('value="500:0.5"', "at least two"),
    ('value="600:0.5, 500:0.3"', "increasing"),
    ('value="0.5 0.6"', "cannot parse '0.5 0.6'"),
    ('value="400:a, 500:1"', "invalid spectrum entry '400:a'"),
    ('', "needs either 'value' or 'filename'"),
    ('filename="missing.spd"', "file 'missing.spd' not found"),
])
def test03_bad_spectra_name_file_and_line(tmp_path, attr, message):
    with pytest.raises(tr.SceneError, match=rf"scene\.xml:4: .*{message}"):
        _scene(tmp_path, f'<bsdf type="diffuse">\n<spectrum name="reflectance" {attr}/></bsdf>')


def test04_spectrum_parameters_are_differentiable(tmp_path):
    # Replay gradcheck in float64 through a spectrum-valued reflectance and emission.
    scene = _scene(tmp_path, '''
        <integrator type="path"><integer name="max_depth" value="3"/></integrator>
        <sensor type="perspective"><float name="fov" value="50"/>
            <transform name="to_world"><lookat origin="0, 1, 3" target="0, 0, 0"/></transform>
            <film type="hdrfilm"><integer name="width" value="3"/><integer name="height" value="3"/>
            <rfilter type="box"/></film></sensor>
        <shape type="rectangle" id="floor"><transform name="to_world"><scale value="2"/><rotate x="1" angle="-90"/></transform>
            <bsdf type="diffuse"><spectrum name="reflectance" value="400:0.2, 550:0.7, 700:0.4"/></bsdf></shape>
        <shape type="sphere" id="lamp"><point name="center" x="0" y="1.5" z="0"/><float name="radius" value="0.3"/>
            <emitter type="area"><spectrum name="radiance" value="3"/></emitter></shape>''', dtype=torch.float64)
    for key in ("floor.bsdf.reflectance.value", "lamp.emitter.radiance.value"):
        x0 = scene.params[key].detach().clone()

        def f(x):
            scene.params[key] = x
            return tr.render(scene, spp=2, seed=3, seed_grad=3)

        assert torch.autograd.gradcheck(f, (x0.clone().requires_grad_(),), eps=1e-6, atol=1e-5, rtol=1e-3)
        scene.params[key] = x0
