"""Tiny assets the fuzzed scenes can refer to, and the seed corpora of the fuzz targets.

`python fuzz/seeds.py` (re)writes fuzz/seeds/<target>/; the targets call `write_assets`
to put tri.obj, tri.ply, tex.png, tex.exr and part.xml in their working folder.
"""
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
BUNDLED = HERE.parent / "torch_rbpt" / "scenes" / "cornell_box.xml"

# Image target inputs are one byte choosing the extension (and raw, bit 7), then the file.
IMAGE_SUFFIXES = (".png", ".exr", ".jpg")

OBJ_SEEDS = {
    "tri.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "quad_vt_vn.obj": ("# quad with texture coordinates and normals\no quad\n"
                       "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n"
                       "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n"
                       "f 1/1/1 2/2/1 3/3/1 4/4/1\n"),
    "negative_vn_only.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 2\nf -3//-1 -2//-1 -1//-1\n",
    "mixed_pentagon.obj": ("v 0 0 0\nv 1 0 0\nv 1.5 1 0\nv 0.5 2 0.3\nv -0.5 1 0\nvt 0.5 0.5\n"
                           "s off\ng g\nusemtl m\nf 1/1 2/1 3/1 4/1 5/1\nf 1 3 5\n"),
}

PLY_POSITIONS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float32)


def ply_bytes(text: bool, byte_order: str = "<", normals=False, uv=("u", "v"),
              polygons=((0, 1, 2), (0, 2, 3)), list_name="vertex_indices") -> bytes:
    import io

    import plyfile
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")] if normals else []
    fields += [(uv[0], "f4"), (uv[1], "f4")] if uv else []
    vertex = np.zeros(len(PLY_POSITIONS), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = PLY_POSITIONS.T
    if normals:
        vertex["nz"] = 1
    if uv:
        vertex[uv[0]], vertex[uv[1]] = PLY_POSITIONS[:, 0], PLY_POSITIONS[:, 1]
    face = np.empty(len(polygons), dtype=[(list_name, "O")])
    face[list_name] = [np.array(p, dtype=np.int32) for p in polygons]
    data = plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex"),
                            plyfile.PlyElement.describe(face, "face")],
                           text=text, byte_order=byte_order)
    out = io.BytesIO()
    data.write(out)
    return out.getvalue()


def ply_seeds() -> dict:
    return {
        "ascii_uv.ply": ply_bytes(True),
        "binary_le_normals.ply": ply_bytes(False, "<", normals=True, uv=None),
        "binary_be_st.ply": ply_bytes(False, ">", uv=("s", "t"), list_name="vertex_index"),
        "ascii_polygon.ply": ply_bytes(True, polygons=((0, 1, 2, 3),)),
    }


def image_files(folder: Path) -> dict:
    """Write tiny images with torch_rbpt's writer; returns name -> bytes."""
    import torch

    from torch_rbpt.images import write_image
    rgb = torch.tensor([[[0.0, 0.2, 1.0], [0.5, 0.5, 0.5]], [[1.0, 0.0, 0.0], [0.1, 0.9, 0.3]]])
    rgba = torch.cat([rgb, torch.full((2, 2, 1), 0.5)], dim=2)
    todo = {"tex.png": rgb, "rgba.png": rgba, "gray.png": rgb[:, :, :1], "tex.exr": rgb,
            "rgba.exr": rgba, "tex.jpg": rgb}
    out = {}
    for name, image in todo.items():
        write_image(folder / name, image)
        out[name] = (folder / name).read_bytes()
    return out


PART_XML = ('<scene version="3.0.0">\n  <bsdf type="diffuse" id="part">\n'
            '    <rgb name="reflectance" value="0.5"/>\n  </bsdf>\n</scene>\n')

FEATURES_XML = """<scene version="3.0.0">
    <default name="res" value="8"/>
    <path value="."/>
    <include filename="part.xml"/>
    <integrator type="direct">
        <integer name="emitter_samples" value="2"/>
        <boolean name="hide_emitters" value="true"/>
    </integrator>
    <sensor type="perspective">
        <float name="focal_length" value="35"/>
        <transform name="to_world">
            <matrix value="1 0 0 0 0 1 0 0 0 0 1 4 0 0 0 1"/>
            <rotate value="0 1 0" angle="180"/>
        </transform>
        <sampler type="independent"><integer name="sample_count" value="2"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="$res"/>
            <integer name="height" value="6"/>
            <integer name="crop_offset_x" value="1"/>
            <integer name="crop_width" value="4"/>
            <rfilter type="gaussian"><float name="stddev" value="0.3"/></rfilter>
        </film>
    </sensor>
    <texture type="bitmap" id="tex">
        <string name="filename" value="tex.png"/>
        <string name="wrap_mode" value="mirror"/>
    </texture>
    <bsdf type="twosided" id="two">
        <bsdf type="roughplastic">
            <ref name="diffuse_reflectance" id="tex"/>
            <float name="alpha" value="0.2"/>
            <string name="distribution" value="ggx"/>
            <string name="int_ior" value="water"/>
        </bsdf>
    </bsdf>
    <shape type="obj">
        <string name="filename" value="tri.obj"/>
        <boolean name="face_normals" value="true"/>
        <ref id="two"/>
    </shape>
    <shape type="ply">
        <string name="filename" value="tri.ply"/>
        <transform name="to_world"><scale value="0.5"/><translate x="1"/></transform>
        <bsdf type="dielectric"><float name="int_ior" value="1.33"/></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" x="0" y="1" z="0"/>
        <float name="radius" value="0.25"/>
        <bsdf type="roughconductor"><rgb name="specular_reflectance" value="0.9 0.8 0.7"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="3"/></emitter>
    </shape>
    <shape type="cube"><ref id="part"/><boolean name="flip_normals" value="true"/></shape>
    <shape type="rectangle"><bsdf type="conductor"/></shape>
    <emitter type="point"><point name="position" value="0, 2, 2"/><rgb name="intensity" value="5"/></emitter>
    <emitter type="constant"><float name="radiance" value="0.1"/></emitter>
</scene>
"""


# Mitsuba features of its own scene files: a version 2.0.0 file, <spectrum> (constant, list),
# checkerboard and bitmap to_uv, a filter with negative lobes, objects referenced before
# their declaration.
MITSUBA_XML = """<scene version="2.0.0">
    <sensor type="perspective">
        <ref id="samp"/>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="6"/>
            <string name="pixel_format" value="rgba"/><rfilter type="lanczos"><integer name="lobes" value="2"/></rfilter></film>
    </sensor>
    <sampler type="independent" id="samp"><integer name="sample_count" value="2"/></sampler>
    <texture type="checkerboard" id="checks">
        <spectrum name="color0" value="400:0.1, 550:0.8, 700:0.3"/><rgb name="color1" value="0.8, 0.2, 0.1"/>
        <transform name="to_uv"><rotate z="1" angle="20"/><scale x="3" y="2"/></transform>
    </texture>
    <shape type="rectangle" id="floor">
        <transform name="to_world"><rotate x="1" angle="-90"/><translate y="-1"/></transform>
        <bsdf type="roughplastic"><ref name="diffuse_reflectance" id="checks"/></bsdf>
    </shape>
    <shape type="sphere" id="ball"><ref id="paint"/><ref id="light"/></shape>
    <bsdf type="diffuse" id="paint">
        <texture type="bitmap" name="reflectance"><string name="filename" value="tex.exr"/>
            <transform name="to_uv"><scale x="2" y="0.5"/></transform></texture>
    </bsdf>
    <emitter type="area" id="light"><spectrum name="radiance" value="0.5"/></emitter>
    <emitter type="constant"><spectrum name="radiance" value="400:0.2 700:0.9"/></emitter>
    <rfilter type="mitchell" id="unused_filter"><float name="B" value="0.2"/><float name="C" value="0.4"/></rfilter>
</scene>
"""


def write_assets(folder) -> None:
    """The files fuzzed scenes may name: tri.obj, tri.ply, tex.png, tex.exr, part.xml."""
    folder = Path(folder)
    (folder / "tri.obj").write_text(OBJ_SEEDS["tri.obj"])
    (folder / "tri.ply").write_bytes(ply_bytes(False))
    (folder / "part.xml").write_text(PART_XML)
    image_files(folder)


def main() -> None:
    import tempfile
    seeds = HERE / "seeds"
    xml = {"cornell_box.xml": BUNDLED.read_text(), "features.xml": FEATURES_XML,
           "part.xml": PART_XML, "mitsuba_features.xml": MITSUBA_XML}
    # The bundled scene's defaults are for the demo: keep the seeds cheap to load.
    xml["cornell_box.xml"] = xml["cornell_box.xml"].replace('value="128"', 'value="8"')
    with tempfile.TemporaryDirectory() as tmp:
        images = image_files(Path(tmp))
    corpora = {
        "xml": {k: v.encode() for k, v in xml.items()},
        # Mesh target inputs are one flags byte (face_normals, flip_tex_coords), then the file.
        "obj": {k: bytes([i % 4]) + v.encode() for i, (k, v) in enumerate(OBJ_SEEDS.items())},
        "ply": {k: bytes([i % 4]) + v for i, (k, v) in enumerate(ply_seeds().items())},
        "image": {name: bytes([IMAGE_SUFFIXES.index(Path(name).suffix)]) + data
                  for name, data in images.items()},
        # The dict target's bytes drive a FuzzedDataProvider: any bytes will do; the first
        # byte even starts from the bundled scene.
        "dict": {"bundled": b"\x00" * 16, "bundled_mutated": bytes(range(0, 256, 3)),
                 "generated": bytes([1]) + bytes(range(255, 0, -7))},
    }
    for target, files in corpora.items():
        folder = seeds / target
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            (folder / name).write_bytes(data)
        print(f"{folder}: {len(files)} seeds")


if __name__ == "__main__":
    main()
