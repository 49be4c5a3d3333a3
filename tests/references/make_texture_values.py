"""Record Mitsuba 3 values for torch_rbpt's spectrum and texture tests.

    python tests/references/make_texture_values.py

Writes ``texture_values.json`` (and the small texture ``scenes/texels.exr`` it uses) next to
this file, with Mitsuba 3.9.1's ``scalar_rgb`` variant:

- ``spectra``: ``<spectrum>`` values as Mitsuba's XML parser turns them into RGB, read back
  with ``mi.traverse``: on a diffuse ``reflectance`` (not emitted) and on an area emitter's
  ``radiance`` (emitted), for constants, wavelength:value lists and a ``.spd`` file.
- ``textures``: ``texture.eval(si)`` at a list of uv for checkerboards and bitmaps with and
  without ``to_uv`` (the XML of each texture is stored, so a test can load the same one).
"""

import json
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = os.path.join(HERE, "scenes")

SPECTRA = [
    "0.5", "2", "-1",
    "400:0.1, 500:0.5, 600:0.8, 700:0.2",
    "400:0.5, 700:0.5",
    "360:1, 830:1",
    "380:0.9 450:0.05 520:0.7 610:0.3 780:0.6",
    "400:2, 700:2",
    "400:1, 500:2",
    "450:0.0, 550:1.0, 650:0.0",
]
SPD = "# wavelength value\n400 0.2\n500 0.4\n600 0.9\n700 0.3\n"

TEXTURES = {
    "checker_default": '<texture type="checkerboard"/>',
    "checker_rgb_rotated": (
        '<texture type="checkerboard"><rgb name="color0" value="0.9, 0.1, 0.1"/>'
        '<float name="color1" value="0.7"/><transform name="to_uv"><rotate z="1" angle="30"/>'
        '<scale x="2" y="3" z="4"/><translate x="0.1" y="0.2" z="0.3"/></transform></texture>'),
    "checker_spectrum": (
        '<texture type="checkerboard"><spectrum name="color0" value="400:0.2, 700:0.9"/>'
        '<spectrum name="color1" value="0.3"/><transform name="to_uv"><scale x="4" y="4"/>'
        '</transform></texture>'),
    "bitmap_to_uv": (
        '<texture type="bitmap"><string name="filename" value="scenes/texels.exr"/>'
        '<transform name="to_uv"><scale x="2" y="0.5"/><translate x="0.25" y="-0.1"/></transform>'
        '</texture>'),
    "bitmap_to_uv_nearest_mirror": (
        '<texture type="bitmap"><string name="filename" value="scenes/texels.exr"/>'
        '<string name="filter_type" value="nearest"/><string name="wrap_mode" value="mirror"/>'
        '<transform name="to_uv"><rotate z="1" angle="-40"/><scale x="3" y="2"/></transform>'
        '</texture>'),
}


def write_texels():
    import OpenImageIO as oiio
    rng = np.random.default_rng(7)
    img = rng.uniform(0.05, 0.95, (6, 8, 3)).astype(np.float32)
    path = os.path.join(SCENES, "texels.exr")
    spec = oiio.ImageSpec(8, 6, 3, oiio.FLOAT)
    spec.attribute("compression", "zip")
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    out.write_image(img)
    out.close()


def main():
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    os.makedirs(SCENES, exist_ok=True)
    write_texels()
    with open(os.path.join(SCENES, "test.spd"), "w") as f:
        f.write(SPD)
    cwd = os.getcwd()
    os.chdir(HERE)  # relative file names in the XML snippets
    try:
        spectra = []
        for text in SPECTRA + ["file:scenes/test.spd"]:
            attr = (f'filename="{text[5:]}"' if text.startswith("file:") else f'value="{text}"')
            entry = {"value": text}
            bsdf = mi.load_string(f'<bsdf version="3.0.0" type="diffuse">'
                                  f'<spectrum name="reflectance" {attr}/></bsdf>')
            entry["reflectance"] = np.atleast_1d(np.array(
                mi.traverse(bsdf)["reflectance.value"])).astype(float).tolist()
            em = mi.load_string(f'<emitter version="3.0.0" type="area">'
                                f'<spectrum name="radiance" {attr}/></emitter>')
            entry["radiance"] = np.atleast_1d(np.array(
                mi.traverse(em)["radiance.value"])).astype(float).tolist()
            spectra.append(entry)

        rng = np.random.default_rng(3)
        uvs = np.concatenate([rng.uniform(-1.5, 2.5, (40, 2)),
                              [[0.1, 0.1], [0.3, 0.1], [0.6, 0.6], [0.1, 0.6]]]).tolist()
        textures = {}
        for name, xml in TEXTURES.items():
            tex = mi.load_string(xml.replace("<texture ", '<texture version="3.0.0" ', 1))
            values = []
            for uv in uvs:
                si = mi.SurfaceInteraction3f()
                si.uv = mi.Point2f(*uv)
                values.append([float(c) for c in tex.eval(si)])
            params = {k: np.atleast_1d(np.array(v)).astype(float).tolist()
                      for k, v in mi.traverse(tex).items() if k.endswith(".value")}
            textures[name] = {"xml": xml, "eval": values, "params": params}
    finally:
        os.chdir(cwd)
    doc = {
        "description": "Mitsuba 3 spectrum conversions and texture lookups; made by "
                       "tests/references/make_texture_values.py",
        "mitsuba_version": mi.__version__, "variant": mi.variant(),
        "spectra": spectra, "uvs": uvs, "textures": textures,
    }
    with open(os.path.join(HERE, "texture_values.json"), "w") as f:
        json.dump(doc, f, indent=1)
    print("wrote texture_values.json")


if __name__ == "__main__":
    main()
