"""Mitsuba 3 references for torch_rbpt's shape plugins (serialized, disk, cylinder).

    python tests/references/make_shape_references.py [--spp-scale S] [--no-render]

Writes into tests/references/shapes/:

- ``meshes.serialized``: three meshes written by ``torch_rbpt.meshes.write_serialized`` (format
  version 4, float64 values; with and without normals, texture coordinates, vertex colours and
  the file's face-normals flag), and ``meshes_v3.serialized`` (the same, version 3, float32);
- ``serialized_mitsuba.json``: what Mitsuba 3 loads from them (``mi.traverse`` arrays) for each
  shape_index, with and without ``face_normals``, under the identity and under ``TO_WORLD``;
- ``objects.serialized`` and ``stripes.exr``: the mesh file and texture of analytic_shapes.xml;
  ``vertex_colors.ply`` and ``face_colors.ply``: the meshes of mesh_attributes.xml;
- ``analytic_hits.json``: rays at disks and cylinders (HIT_CASES) and at instances.xml, and
  Mitsuba's hits;
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

# Mitsuba's LLVM variant needs libLLVM 19 (see benchmarks/mitsuba_ref.py), set before import.
if os.path.exists("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"):
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "shapes")
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
sys.path.insert(0, HERE)

from torch_rbpt.meshes import cube, write_serialized  # noqa: E402

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
    "cylinder_light": ("cylinder_light.xml", 65536),
    "mesh_attributes": ("mesh_attributes.xml", 65536),
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


def uv_sphere(n_theta=10, n_phi=16):
    """A low-poly sphere (no normals, no uvs: Mitsuba computes smooth normals)."""
    theta = np.linspace(0, np.pi, n_theta + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    ring = np.stack([np.outer(np.sin(theta), np.cos(phi)), np.outer(np.sin(theta), np.sin(phi)),
                     np.outer(np.cos(theta), np.ones_like(phi))], -1).reshape(-1, 3)
    positions = np.vstack([[0, 0, 1], ring, [0, 0, -1]])
    faces, last = [], len(positions) - 1
    idx = lambda i, j: 1 + i * n_phi + j % n_phi
    for j in range(n_phi):
        faces.append([0, idx(0, j), idx(0, j + 1)])
        faces.append([last, idx(n_theta - 2, j + 1), idx(n_theta - 2, j)])
        for i in range(n_theta - 2):
            faces.append([idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)])
            faces.append([idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)])
    return positions, np.array(faces)


def write_color_ply(path, colors, per_face):
    """A 4 x 4 vertex grid on [-1, 1]^2 (18 triangles) with float colours per vertex or face."""
    g = np.linspace(-1, 1, 4)
    positions = np.array([[x, y, 0.0] for y in g for x in g])
    faces = []
    for j in range(3):
        for i in range(3):
            a = 4 * j + i
            faces += [[a, a + 1, a + 5], [a, a + 5, a + 4]]
    lines = ["ply", "format ascii 1.0", "element vertex 16", "property float x", "property float y",
             "property float z"]
    if not per_face:
        lines += ["property float red", "property float green", "property float blue"]
    lines += ["element face %d" % len(faces), "property list uchar int vertex_indices"]
    if per_face:
        lines += ["property float r", "property float g", "property float b"]
    lines.append("end_header")
    for k, p in enumerate(positions):
        lines.append(" ".join("%g" % v for v in list(p) + ([] if per_face else list(colors[k]))))
    for k, f in enumerate(faces):
        lines.append("3 %d %d %d" % tuple(f) + ("".join(" %g" % v for v in colors[k]) if per_face else ""))
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def make_scene_files():
    """objects.serialized (a cube with normals and uvs, a sphere without) and stripes.exr."""
    import make_references as mr
    c = cube()
    sphere_p, sphere_f = uv_sphere()
    write_serialized(os.path.join(OUT, "objects.serialized"),
                     [dict(positions=c.positions, faces=c.faces, normals=c.normals, uvs=c.uvs),
                      dict(positions=sphere_p, faces=sphere_f)], version=4)
    u = (np.arange(16) + 0.5) / 16
    img = np.zeros((16, 16, 3), np.float32)
    img[..., 0] = 0.15 + 0.7 * (np.floor(u * 4) % 2)[None, :]   # 4 stripes along u (columns)
    img[..., 1] = 0.2 + 0.6 * u[:, None]                        # a ramp along v (rows)
    img[..., 2] = 0.3
    mr.write_exr(os.path.join(OUT, "stripes.exr"), img)
    rng = np.random.default_rng(5)
    write_color_ply(os.path.join(OUT, "vertex_colors.ply"), np.round(rng.uniform(0.05, 0.95, (16, 3)), 3), False)
    write_color_ply(os.path.join(OUT, "face_colors.ply"), np.round(rng.uniform(0.05, 0.95, (18, 3)), 3), True)


# Analytic shapes whose ray hits are recorded: (type, parameters; to_world as (translate,
# axis, angle, scale) applied scale first).
HIT_CASES = [
    ("disk", {}), ("disk", {"flip_normals": True}),
    ("disk", {"to_world": ([0.5, -1, 2], AXIS, 30, [2, 1, 0.5])}),
    ("disk", {"to_world": ([0, 0, 0], [0, 0, 1], 0, [1, 1, -1])}),
    ("cylinder", {}), ("cylinder", {"flip_normals": True}),
    ("cylinder", {"radius": 0.5, "p0": [0, 0, 0], "p1": [1, 2, 2]}),
    ("cylinder", {"radius": 0.3, "p0": [0.2, 0.1, 1], "p1": [0.2, 0.3, -1]}),
    ("cylinder", {"to_world": ([0.5, -1, 2], AXIS, 30, [2, 2, 0.5]), "p1": [0, 0, 3]}),
]


def make_hits(mi, n=120):
    """Rays at each HIT_CASES shape (origins around it, aimed into its box) and Mitsuba's
    hits: t (inf for a miss), p, n, uv."""
    rng = np.random.default_rng(1)
    cases = []
    for kind, params in HIT_CASES:
        props = dict(params)
        if "to_world" in props:
            tw, axis, angle, scale = props["to_world"]
            props["to_world"] = (mi.ScalarTransform4f().translate(tw) @
                                 mi.ScalarTransform4f().rotate(axis, angle) @
                                 mi.ScalarTransform4f().scale(scale))
        scene = mi.load_dict({"type": "scene", "s": dict(type=kind, **props)})
        bb = scene.bbox()
        lo, hi = np.array(bb.min), np.array(bb.max)
        c, ext = (lo + hi) / 2, np.linalg.norm(hi - lo)
        # (rounded to 5 decimals, so that the json's decimals give the same float32 rays)
        o = np.round(c + rng.normal(size=(n, 3)) * ext * 2, 5)
        d = (c + (rng.uniform(size=(n, 3)) - 0.5) * (hi - lo) * 1.2) - o
        d = np.round(d / np.linalg.norm(d, axis=1, keepdims=True), 5)
        o, d = o.astype(np.float32), d.astype(np.float32)
        hits = []
        for i in range(n):
            si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*o[i]), mi.Vector3f(*d[i])))
            r6 = lambda v: np.round(np.array(v, dtype=np.float64), 6).tolist()
            hits.append([round(float(si.t), 6) if si.is_valid() else None, r6(si.p), r6(si.n),
                         r6(si.uv)])
        matrix = np.array(props["to_world"].matrix).tolist() if "to_world" in props else None
        key = np.array(mi.traverse(scene.shapes()[0])["to_world"].matrix).tolist()
        cases.append(dict(type=kind, params={k: v for k, v in params.items() if k != "to_world"},
                          to_world=matrix, traverse_to_world=key,
                          origins=np.round(o.astype(np.float64), 5).tolist(),
                          directions=np.round(d.astype(np.float64), 5).tolist(), hits=hits))
    # instances.xml, as a whole scene: hits report the flattened shapes' p, n, uv
    scene = mi.load_file(os.path.join(OUT, "instances.xml"))
    bb = scene.bbox()
    lo, hi = np.array(bb.min), np.array(bb.max)
    c, ext = (lo + hi) / 2, np.linalg.norm(hi - lo)
    o = np.round(c + rng.normal(size=(4 * n, 3)) * ext, 5)
    d = (c + (rng.uniform(size=(4 * n, 3)) - 0.5) * (hi - lo)) - o
    d = np.round(d / np.linalg.norm(d, axis=1, keepdims=True), 5)
    hits = []
    for oi, di in zip(o.astype(np.float32), d.astype(np.float32)):
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*oi), mi.Vector3f(*di)))
        r6 = lambda v: np.round(np.array(v, dtype=np.float64), 6).tolist()
        hits.append([round(float(si.t), 6) if si.is_valid() else None, r6(si.p), r6(si.n), r6(si.uv)])
    keys = sorted(k for k in mi.traverse(scene).keys() if "to_world" in k or "vertex_positions" in k)
    cases.append(dict(type="scene", file="instances.xml", traverse_keys=keys,
                      origins=o.tolist(), directions=d.tolist(), hits=hits))
    with open(os.path.join(OUT, "analytic_hits.json"), "w") as f:
        json.dump(dict(mitsuba_version=mi.__version__, variant=mi.variant(), cases=cases), f)
    print("wrote analytic_hits.json")


def make_renders(spp_scale, only=None):
    import make_references as mr
    import mitsuba_ref
    path = os.path.join(OUT, "renders.json")
    meta = json.load(open(path)) if os.path.exists(path) else {}
    for name, (xml, spp) in RENDERS.items():
        if only and name not in only:
            continue
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
    ap.add_argument("--hits-only", action="store_true", help="only the serialized and hit files")
    ap.add_argument("--only", nargs="*", default=None, help="names of the renders to (re)make")
    args = ap.parse_args()
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    t0 = time.time()
    make_serialized(mi)
    make_hits(mi)
    if args.hits_only:
        return
    make_scene_files()
    if not args.no_render:
        make_renders(args.spp_scale, args.only)
    print("total %.1f s" % (time.time() - t0))


if __name__ == "__main__":
    main()
