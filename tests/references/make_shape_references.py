"""Mitsuba 3 references for torch_rbpt's shape plugins (serialized, disk, cylinder).

    python tests/references/make_shape_references.py [--spp-scale S] [--no-render]

Writes into tests/references/shapes/:

- ``meshes.serialized``: three meshes written by ``torch_rbpt.meshes.write_serialized`` (format
  version 4, float64 values; with and without normals, texture coordinates, vertex colours and
  the file's face-normals flag), and ``meshes_v3.serialized`` (the same, version 3, float32);
- ``serialized_mitsuba.json``: what Mitsuba 3 loads from them (``mi.traverse`` arrays) for each
  shape_index, with and without ``face_normals``, under the identity and under ``TO_WORLD``;
- ``<name>.exr`` and ``renders.json``: converged renders of the scenes in this folder (64 x 48,
  float32 RGB, ZIP), the mean of two half-spp renders with seeds 1 and 2, with their noise as in
  make_references.py.
"""
import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "shapes")
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
sys.path.insert(0, HERE)

from torch_rbpt.meshes import write_serialized  # noqa: E402

# A rotation about a normalized axis (Mitsuba's rotate() does not normalize its axis), a
# non-uniform scale and a translation.
AXIS = (np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)).tolist()
TO_WORLD = dict(rotate=(AXIS, 30.0), scale=[1.0, 2.0, 3.0], translate=[0.5, -1.0, 2.0])

P = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5], [0.5, 0.5, 1.0]])
F = np.array([[0, 1, 2], [0, 2, 3], [2, 4, 3]])
N = np.array([[0, 0, 2], [0, 0, 1], [0, 1, 1], [1, 0, 1], [0.3, 0.2, 1.0]])
UV = np.array([[0, 0.1], [1, 0.1], [1, 0.9], [0, 0.9], [0.5, 0.5]])
C = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0.5], [1, 1, 1]])
MESHES = [
    dict(positions=P, faces=F, normals=N, uvs=UV, colors=C, name="all_attributes"),
    dict(positions=P * 2 - 0.25, faces=F, uvs=UV, name="no_normals"),
    dict(positions=P * 3, faces=F, normals=N, face_normals=True, name="face_normals_flag"),
]

# Rendered scenes: name -> (xml file in this folder, total spp)
RENDERS = {
    "analytic_shapes": ("analytic_shapes.xml", 65536),
}


def to_world_transform(mi):
    t = mi.ScalarTransform4f().translate(TO_WORLD["translate"])
    t = t @ mi.ScalarTransform4f().rotate(*TO_WORLD["rotate"])
    return t @ mi.ScalarTransform4f().scale(TO_WORLD["scale"])


def make_serialized(mi):
    files = {"meshes.serialized": dict(version=4, double=True),
             "meshes_v3.serialized": dict(version=3, double=False)}
    for name, kw in files.items():
        write_serialized(os.path.join(OUT, name), MESHES, **kw)
    T = to_world_transform(mi)
    loads = []
    for name in files:
        for index in range(len(MESHES)):
            for face_normals in (False, True):
                for transformed in (False, True):
                    props = dict(type="serialized", filename=os.path.join(OUT, name),
                                 shape_index=index, face_normals=face_normals)
                    if transformed:
                        props["to_world"] = T
                    m = mi.load_dict(props)
                    t = {k: np.array(v).tolist() for k, v in mi.traverse(m).items()
                         if k.startswith("vertex_") or k == "faces"}
                    loads.append(dict(file=name, shape_index=index, face_normals=face_normals,
                                      to_world=transformed, has_normals=m.has_vertex_normals(),
                                      has_uvs=m.has_vertex_texcoords(), arrays=t))
    doc = dict(mitsuba_version=mi.__version__, variant=mi.variant(),
               to_world=dict(matrix=np.array(T.matrix).tolist(), **TO_WORLD), loads=loads)
    with open(os.path.join(OUT, "serialized_mitsuba.json"), "w") as f:
        json.dump(doc, f)
    print("wrote serialized files and serialized_mitsuba.json")


def make_renders(spp_scale):
    import make_references as mr
    import mitsuba_ref
    meta = {}
    for name, (xml, spp) in RENDERS.items():
        spp = int(round(spp * spp_scale / 2)) * 2
        scene = mitsuba_ref.load_scene(os.path.join(OUT, xml), None, None)
        print("[%s] %d spp ..." % (name, spp), flush=True)
        secs, a, b = mr.render_pair(scene, spp)
        ref = 0.5 * (a + b)
        d = mr.noise(a, b, ref)
        mr.write_exr(os.path.join(OUT, name + ".exr"), ref)
        meta[name] = dict(scene=xml, spp=spp, seeds=list(mr.SEEDS), render_seconds=round(secs, 2),
                          noise_half_diff=round(d, 5), noise_ref_est=round(d / 2, 5),
                          mitsuba_version=mitsuba_ref.version(), variant=mitsuba_ref.variant(),
                          exr=name + ".exr", width=int(ref.shape[1]), height=int(ref.shape[0]))
        print("   %.1f s, noise %.4f, mean %.5f" % (secs, d, float(ref.mean())), flush=True)
    with open(os.path.join(OUT, "renders.json"), "w") as f:
        json.dump(meta, f, indent=2)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--spp-scale", type=float, default=1.0)
    ap.add_argument("--no-render", action="store_true")
    args = ap.parse_args()
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    t0 = time.time()
    make_serialized(mi)
    if not args.no_render:
        make_renders(args.spp_scale)
    print("total %.1f s" % (time.time() - t0))


if __name__ == "__main__":
    main()
