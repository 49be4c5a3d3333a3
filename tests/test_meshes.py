"""Tests for torch_rbpt.meshes: OBJ/PLY loading with Mitsuba 3 semantics, built-in shapes.

Reference values marked "Mitsuba 3.9.1" were obtained with ``mi.traverse`` of shapes
loaded by Mitsuba 3.9.1 (variant scalar_rgb); Mitsuba itself is not needed to run these.
"""

from pathlib import Path

import numpy as np
import plyfile
import pytest

from torch_rbpt.meshes import (
    Mesh,
    MeshError,
    compute_vertex_normals,
    cube,
    load_mesh,
    load_obj,
    load_ply,
    load_serialized,
    rectangle,
    write_serialized,
)

SCENES = Path(__file__).resolve().parents[2] / "shared" / "scenes"
SHAPE_REFS = Path(__file__).resolve().parent / "references" / "shapes"
CBOX = SCENES / "cbox" / "meshes"
needs_scenes = pytest.mark.skipif(not SCENES.is_dir(), reason=f"{SCENES} not present")


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def unit_rows(a):
    return np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-6)


# ---------------------------------------------------------------------------------------
# Shared scene files
# ---------------------------------------------------------------------------------------


@needs_scenes
@pytest.mark.parametrize("name", ["back", "ceiling", "floor", "greenwall", "redwall",
                                  "luminaire"])
def test_cbox_quads_become_two_triangles(name):
    mesh = load_obj(CBOX / f"cbox_{name}.obj")
    assert mesh.positions.dtype == np.float32 and mesh.faces.dtype == np.int32
    assert mesh.positions.shape == (4, 3) and mesh.faces.shape == (2, 3)
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]  # fan, as Mitsuba
    assert mesh.uvs is None
    assert mesh.computed_normals
    # Every wall is planar: vertex normals equal the geometric normal.
    fn = mesh.face_normals()
    assert np.allclose(fn[0], fn[1])
    assert np.allclose(mesh.normals, fn[0], atol=1e-6)


@needs_scenes
def test_cbox_red_wall_faces_minus_x():
    # Mitsuba 3.9.1: cbox_redwall.obj (the wall at x = +1) has vertex normals (-1, 0, 0),
    # i.e. facing into the box.
    mesh = load_obj(CBOX / "cbox_redwall.obj")
    assert np.allclose(mesh.positions[:, 0], 1.0)
    assert np.allclose(mesh.normals, [[-1, 0, 0]] * 4, atol=1e-6)
    assert np.allclose(mesh.face_normals(), [[-1, 0, 0]] * 2, atol=1e-6)
    assert mesh.area() == pytest.approx(4.0)


@needs_scenes
def test_cbox_green_wall_faces_plus_x():
    mesh = load_obj(CBOX / "cbox_greenwall.obj")
    assert np.allclose(mesh.positions[:, 0], -1.0)
    assert np.allclose(mesh.normals, [[1, 0, 0]] * 4, atol=1e-6)


@needs_scenes
@pytest.mark.parametrize("name", ["largebox", "smallbox"])
def test_cbox_boxes_use_file_normals(name):
    mesh = load_obj(CBOX / f"cbox_{name}.obj")
    assert mesh.positions.shape == (24, 3) and mesh.faces.shape == (12, 3)
    assert not mesh.computed_normals
    assert unit_rows(mesh.normals)
    # The file normals of these boxes agree with the winding.
    corner_normals = mesh.normals[mesh.faces[:, 0]]
    assert np.all(np.einsum("ij,ij->i", corner_normals, mesh.face_normals()) > 0.999)


@needs_scenes
def test_cbox_largebox_first_normal_is_normalized_file_normal():
    mesh = load_obj(CBOX / "cbox_largebox.obj")
    n = np.array([0.955649, 0.0, -0.294508])
    assert np.allclose(mesh.normals[4], n / np.linalg.norm(n), atol=1e-6)
    assert np.allclose(mesh.positions[0], [423, 330, 247])


@needs_scenes
def test_veach_floor_triangles():
    mesh = load_obj(SCENES / "veach-mis" / "meshes" / "veach" / "floor.obj")
    assert mesh.faces.shape == (4, 3) and mesh.positions.shape == (12, 3)


@needs_scenes
def test_rectangle_obj_matches_mitsuba_layout_and_flips_v():
    # Mitsuba 3.9.1 traverse of meshes/rectangle.obj: vertices numbered by first use
    # (file vertices 2, 3, 1, 4), texcoords (u, 1 - v).
    mesh = load_obj(SCENES / "meshes" / "rectangle.obj")
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 3, 1]]
    assert mesh.positions.tolist() == [[1, -1, 0], [-1, 1, 0], [-1, -1, 0], [1, 1, 0]]
    assert mesh.uvs.tolist() == [[1, 0], [0, 1], [0, 0], [1, 1]]
    assert np.allclose(mesh.normals, [[0, 0, 1]] * 4, atol=1e-6)


@needs_scenes
def test_bunny_binary_ply():
    mesh = load_ply(SCENES / "meshes" / "bunny.ply")
    assert mesh.faces.shape == (69451, 3)
    assert mesh.positions.shape == (35947, 3)
    assert mesh.faces.dtype == np.int32 and mesh.normals.dtype == np.float32
    assert mesh.uvs is None and mesh.computed_normals
    assert unit_rows(mesh.normals)
    # Mitsuba 3.9.1 keeps unreferenced PLY vertices (it warns about "1113 invalid
    # vertices") and gives them the placeholder normal (1, 0, 0).
    referenced = np.zeros(mesh.vertex_count, dtype=bool)
    referenced[mesh.faces.ravel()] = True
    assert (~referenced).sum() == 1113
    assert np.all(mesh.normals[~referenced] == [1, 0, 0])
    # First vertex normals from Mitsuba 3.9.1.
    assert np.allclose(mesh.normals[:3], [[0.1948689, 0.9727272, -0.12580894],
                                          [0.21519934, 0.94943964, -0.22859064],
                                          [0.058657326, 0.801092, 0.59566003]], atol=1e-5)


@needs_scenes
def test_teapot_ascii_ply():
    mesh = load_ply(SCENES / "meshes" / "teapot.ply")
    assert mesh.positions.shape == (1177, 3) and mesh.faces.shape == (2256, 3)
    assert np.allclose(mesh.positions[1], [1.4, 0, 2.4])
    assert load_mesh(SCENES / "meshes" / "teapot.ply").faces.shape == (2256, 3)


# ---------------------------------------------------------------------------------------
# OBJ semantics on small files
# ---------------------------------------------------------------------------------------

PENTAGON = """\
# a pentagon with texture coordinates and one unnormalized normal
o pentagon
g group
s 1
mtllib nothing.mtl
usemtl none
v 0 0 0
v 1 0 0
v 1.5 1 0
v 0.5 2 0
v -0.5 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 0.5
vn 0 0 2
f 1/1/1 2/2/1 3/3/1 4/4/1 5/5/1
"""


def test_pentagon_fan_uv_flip_and_normalized_normals(tmp_path):
    mesh = load_obj(write(tmp_path / "pentagon.obj", PENTAGON))
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 3, 4]]
    assert mesh.positions.shape == (5, 3)
    # v is flipped (Mitsuba's flip_tex_coords defaults to true for OBJ).
    assert mesh.uvs.tolist() == [[0, 1], [1, 1], [1, 0], [0, 0], [0.5, 0.5]]
    assert np.allclose(mesh.normals, [[0, 0, 1]] * 5)
    assert not mesh.computed_normals
    assert mesh.area() == pytest.approx(2.5)


def test_uv_flip_is_one_minus_v(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0.25 0.125\nvt 0.5 0.75\nvt 1 0.3\nf 1/1 2/2 3/3\n"
    mesh = load_obj(write(tmp_path / "uv.obj", text))
    assert np.allclose(mesh.uvs, [[0.25, 0.875], [0.5, 0.25], [1.0, 0.7]])


def test_obj_flip_tex_coords_false_keeps_v(tmp_path):
    # Mitsuba 3.9.1 obj with flip_tex_coords=false: the pentagon's uvs as in the file.
    mesh = load_obj(write(tmp_path / "pentagon.obj", PENTAGON), flip_tex_coords=False)
    assert mesh.uvs.tolist() == [[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5]]
    assert load_mesh(tmp_path / "pentagon.obj").uvs.tolist()[0] == [0, 1]


def test_negative_indices_are_relative(tmp_path):
    positive = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n"
    negative = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf -3/-3 -2/-2 -1/-1\n"
    a = load_obj(write(tmp_path / "pos.obj", positive))
    b = load_obj(write(tmp_path / "neg.obj", negative))
    for field in ("positions", "faces", "normals", "uvs"):
        assert np.array_equal(getattr(a, field), getattr(b, field))
    # -1 means "the last vertex defined so far", not the last one of the file.
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 0 0 1\nv 1 0 1\nv 0 1 1\nf -3 -2 -1\n"
    mesh = load_obj(write(tmp_path / "rel.obj", text))
    assert mesh.faces.tolist() == [[0, 1, 2], [3, 4, 5]]
    assert np.allclose(mesh.positions[3:, 2], 1.0) and np.allclose(mesh.positions[:3, 2], 0)


def test_vertices_dedup_by_index_triple_in_first_use_order(tmp_path):
    text = """\
v 0 0 0
v 1 0 0
v 0 1 0
v 1 1 0
v 9 9 9
vt 0 0
vt 1 0
vt 0 1
vt 1 1
f 4/4 2/2 3/3
f 3/3 2/2 1/1
f 4/1 3/3 2/2
"""
    mesh = load_obj(write(tmp_path / "dedup.obj", text))
    # (4,4), (2,2), (3,3), (1,1), (4,1): five distinct triples; unused v 9 9 9 dropped.
    assert mesh.positions.tolist() == [[1, 1, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0],
                                       [1, 1, 0]]
    assert mesh.faces.tolist() == [[0, 1, 2], [2, 1, 3], [4, 2, 1]]
    assert mesh.uvs.tolist() == [[1, 0], [1, 1], [0, 0], [0, 1], [0, 1]]


def test_vn_corner_forms_and_mixed_forms(tmp_path):
    uniform = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\n"
    a = load_obj(write(tmp_path / "a.obj", uniform))
    assert a.faces.tolist() == [[0, 1, 2]] and np.allclose(a.normals, [[0, 0, 1]] * 3)
    # Mixed corner forms take the per-corner path; same result for the shared corners.
    mixed = ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvn 0 0 1\n"
             "f 1//1 2//1 3//1\nf 2/1/1 4/1/1 3/1/1\n")
    b = load_obj(write(tmp_path / "b.obj", mixed))
    assert b.faces.tolist() == [[0, 1, 2], [3, 4, 5]]
    assert np.allclose(b.normals, [[0, 0, 1]] * 6)
    # Corners without vt in a textured mesh get uv (0, 0) (undefined in Mitsuba).
    assert np.allclose(b.uvs[:3], 0.0) and np.allclose(b.uvs[3:], [[0, 1]] * 3)


def test_extra_values_and_whitespace_are_tolerated(tmp_path):
    text = ("v 0 0 0 1.0\r\n\tv 1 0 0 0.5 0.5 0.5\r\nv   0  1   0 # comment\r\n"
            "vt 0 0 0\r\nl 1 2\r\nf 1 2 3\r\n")
    mesh = load_obj(write(tmp_path / "ws.obj", text))
    assert mesh.positions.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    # vt present but never referenced: no texture coordinates.
    assert mesh.uvs is None


def test_face_normals_option_drops_normals(tmp_path):
    path = write(tmp_path / "p.obj", PENTAGON)
    assert load_obj(path, face_normals=True).normals is None
    path = write(tmp_path / "t.obj", TETRAHEDRON)
    mesh = load_obj(path, face_normals=True)
    assert mesh.normals is None and not mesh.computed_normals


# A non-planar closed mesh; reference normals computed by Mitsuba 3.9.1.
TETRAHEDRON = """\
v 0 0 0
v 1 0 0
v 0 2 0
v 0.3 0.4 1.5
f 1 3 2
f 1 2 4
f 2 3 4
f 3 1 4
"""
# Mitsuba 3.9.1, mi.traverse(obj)['vertex_normals'] (vertices in first-use order:
# file vertices 1, 3, 2, 4).
TETRA_POSITIONS = [[0, 0, 0], [0, 2, 0], [1, 0, 0], [0.3, 0.4, 1.5]]
TETRA_FACES = [[0, 1, 2], [0, 2, 3], [2, 1, 3], [1, 0, 3]]
TETRA_NORMALS_MITSUBA = [[-0.6177676, -0.638757, -0.45864233],
                         [-0.21029653, 0.9447232, -0.25154212],
                         [0.7904941, -0.4815498, -0.3784561],
                         [-0.03188652, -0.11740943, 0.9925716]]
# Same file with to_world = scale(3, 1, 0.5): Mitsuba recomputes the normals from the
# transformed positions.
TETRA_SCALED_NORMALS_MITSUBA = [[-0.7426421, -0.62384224, -0.2435234],
                                [-0.47306603, 0.8708073, -0.13380307],
                                [0.9599099, -0.25601226, -0.11415159],
                                [-0.017219922, -0.18321718, 0.9829216]]


def test_recomputed_normals_match_mitsuba(tmp_path):
    mesh = load_obj(write(tmp_path / "tet.obj", TETRAHEDRON))
    assert np.array_equal(mesh.positions, np.float32(TETRA_POSITIONS))
    assert mesh.faces.tolist() == TETRA_FACES
    assert mesh.computed_normals
    assert np.allclose(mesh.normals, TETRA_NORMALS_MITSUBA, atol=1e-6)


def test_recomputed_normals_are_angle_not_area_weighted(tmp_path):
    mesh = load_obj(write(tmp_path / "tet.obj", TETRAHEDRON))
    p = mesh.positions.astype(np.float64)
    area = np.zeros_like(p)
    for f in mesh.faces:
        area[f] += np.cross(p[f[1]] - p[f[0]], p[f[2]] - p[f[0]])
    area /= np.linalg.norm(area, axis=1, keepdims=True)
    assert np.abs(area - mesh.normals).max() > 0.1


def test_transform_recomputes_computed_normals_like_mitsuba(tmp_path):
    mesh = load_obj(write(tmp_path / "tet.obj", TETRAHEDRON))
    world = mesh.transformed(np.diag([3.0, 1.0, 0.5, 1.0]))
    assert np.allclose(world.positions[3], [0.9, 0.4, 0.75])
    assert np.allclose(world.normals, TETRA_SCALED_NORMALS_MITSUBA, atol=1e-6)
    assert world.computed_normals


def test_compute_vertex_normals_degenerate_and_unreferenced():
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [5, 5, 5]], np.float32)
    faces = np.array([[0, 1, 2], [0, 1, 3]])  # second triangle has zero area
    n = compute_vertex_normals(positions, faces)
    assert np.allclose(n[:3], [[0, 0, 1]] * 3)
    assert n[3].tolist() == [1, 0, 0] and n[4].tolist() == [1, 0, 0]


# ---------------------------------------------------------------------------------------
# OBJ errors
# ---------------------------------------------------------------------------------------

TRI = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"


@pytest.mark.parametrize("body, pattern", [
    (TRI + "f 1 2 4\n", r"bad\.obj, line 4: vertex index 4 is out of range"),
    (TRI + "f 1 2 -4\n", r"bad\.obj, line 4: vertex index -4 is out of range"),
    (TRI + "f 1 2 0\n", r"bad\.obj, line 4: .*index 0"),
    (TRI + "f 1 2 3.5\n", r"bad\.obj, line 4: malformed index '3\.5'"),
    (TRI + "f 1/1/1/1 2 3\n", r"bad\.obj, line 4: malformed face corner '1/1/1/1'"),
    (TRI + "vt 0 0\nf 1/1 2/1 3/2\n", r"bad\.obj, line 5: texture coordinate index 2"),
    (TRI + "f 1//1 2//1 3//1\n", r"bad\.obj, line 4: normal index 1 is out of range"),
    (TRI + "\nf 1 2\n", r"bad\.obj, line 5: face has 2 vertices, expected at least 3"),
    ("v 0 0 0\nv 1 0 x\nv 0 1 0\nf 1 2 3\n", r"bad\.obj, line 2: malformed number 'x'"),
    ("v 0 0\nf 1 2 3\n", r"bad\.obj, line 1: expected 3 numbers after 'v', got 2"),
    ("v 0 0 0\n# only a vertex\n", r"bad\.obj: mesh has no faces"),
    ("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", r"bad\.obj, line 1: non-finite"),
])
def test_obj_errors_name_file_and_line(tmp_path, body, pattern):
    with pytest.raises(MeshError, match=pattern):
        load_obj(write(tmp_path / "bad.obj", body))


def test_missing_files_raise_mesh_error(tmp_path):
    with pytest.raises(MeshError, match=r"nope\.obj: OBJ file not found"):
        load_obj(tmp_path / "nope.obj")
    with pytest.raises(MeshError, match=r"nope\.ply: PLY file not found"):
        load_ply(tmp_path / "nope.ply")
    with pytest.raises(MeshError, match=r"x\.stl: unsupported mesh format"):
        load_mesh(tmp_path / "x.stl")
    assert issubclass(MeshError, ValueError)


# ---------------------------------------------------------------------------------------
# PLY
# ---------------------------------------------------------------------------------------

PLY_POSITIONS = np.array([[0, 0, 0], [1, 0, 0], [1.5, 1, 0], [0.5, 2, 0.3], [-0.5, 1, 0],
                          [9, 9, 9]], dtype=np.float32)
PLY_UVS = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6], [0.7, 0.8], [0.9, 0.15], [0, 0]],
                   dtype=np.float32)


def write_ply(path, polygons, uv_names=("u", "v"), normals=None, text=False,
              byte_order="<", list_name="vertex_indices"):
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if normals is not None:
        fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    if uv_names:
        fields += [(uv_names[0], "f4"), (uv_names[1], "f4")]
    vertex = np.empty(len(PLY_POSITIONS), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = PLY_POSITIONS.T
    if normals is not None:
        vertex["nx"], vertex["ny"], vertex["nz"] = np.asarray(normals, np.float32).T
    if uv_names:
        vertex[uv_names[0]], vertex[uv_names[1]] = PLY_UVS.T
    face = np.empty(len(polygons), dtype=[(list_name, "O")])
    face[list_name] = [np.array(p, dtype=np.int32) for p in polygons]
    elements = [plyfile.PlyElement.describe(vertex, "vertex"),
                plyfile.PlyElement.describe(face, "face")]
    plyfile.PlyData(elements, text=text, byte_order=byte_order).write(str(path))
    return path


TRIS = [[0, 1, 2], [0, 2, 3]]


def assert_same_mesh(a: Mesh, b: Mesh):
    for field in ("positions", "faces", "normals", "uvs"):
        x, y = getattr(a, field), getattr(b, field)
        assert (x is None) == (y is None), field
        if x is not None:
            assert x.dtype == y.dtype and np.array_equal(x, y), field


def test_ply_ascii_binary_and_endianness_agree(tmp_path):
    little = load_ply(write_ply(tmp_path / "le.ply", TRIS))
    big = load_ply(write_ply(tmp_path / "be.ply", TRIS, byte_order=">"))
    ascii_ = load_ply(write_ply(tmp_path / "a.ply", TRIS, text=True))
    assert_same_mesh(little, big)
    assert_same_mesh(little, ascii_)
    assert little.faces.tolist() == TRIS
    # PLY keeps all vertices, unreferenced ones too, in file order.
    assert np.array_equal(little.positions, PLY_POSITIONS)


def test_ply_uvs_are_not_flipped(tmp_path):
    mesh = load_ply(write_ply(tmp_path / "uv.ply", TRIS))
    assert np.array_equal(mesh.uvs, PLY_UVS)


def test_ply_flip_tex_coords_option(tmp_path):
    # Mitsuba 3.9.1 ply with flip_tex_coords=true gives (u, 1 - v); the default is false.
    path = write_ply(tmp_path / "uv.ply", TRIS)
    flipped = load_ply(path, flip_tex_coords=True)
    assert np.array_equal(flipped.uvs[:, 0], PLY_UVS[:, 0])
    assert np.array_equal(flipped.uvs[:, 1], np.float32(1) - PLY_UVS[:, 1])
    assert np.array_equal(load_mesh(path).uvs, PLY_UVS)


@pytest.mark.parametrize("names", [("u", "v"), ("s", "t"), ("texture_u", "texture_v")])
def test_ply_uv_property_names(tmp_path, names):
    mesh = load_ply(write_ply(tmp_path / "uv.ply", TRIS, uv_names=names))
    assert np.array_equal(mesh.uvs, PLY_UVS)


def test_ply_texture_s_t_is_ignored_like_mitsuba(tmp_path):
    # Mitsuba 3.9.1 does not treat texture_s/texture_t as texture coordinates.
    mesh = load_ply(write_ply(tmp_path / "st.ply", TRIS, uv_names=("texture_s", "texture_t")))
    assert mesh.uvs is None


def test_ply_polygons_are_fan_triangulated(tmp_path):
    poly = load_ply(write_ply(tmp_path / "poly.ply", [[0, 1, 2, 3, 4], [1, 2, 5]]))
    assert poly.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 3, 4], [1, 2, 5]]
    ascii_ = load_ply(write_ply(tmp_path / "polya.ply", [[0, 1, 2, 3, 4], [1, 2, 5]],
                                text=True))
    assert_same_mesh(poly, ascii_)


def test_ply_vertex_index_name_and_file_normals(tmp_path):
    normals = np.tile([0.0, 0.0, 3.0], (len(PLY_POSITIONS), 1))
    mesh = load_ply(write_ply(tmp_path / "n.ply", TRIS, uv_names=None, normals=normals,
                              list_name="vertex_index"))
    assert mesh.faces.tolist() == TRIS and mesh.uvs is None
    assert not mesh.computed_normals
    assert np.array_equal(mesh.normals, np.tile(np.float32([0, 0, 1]), (6, 1)))
    assert load_ply(tmp_path / "n.ply", face_normals=True).normals is None


def test_ply_computed_normals_match_obj(tmp_path):
    # Same triangles through both loaders: same angle-weighted normals.
    ply = load_ply(write_ply(tmp_path / "t.ply", TRIS, uv_names=None))
    lines = [f"v {x} {y} {z}" for x, y, z in PLY_POSITIONS[:4]] + ["f 1 2 3", "f 1 3 4"]
    obj = load_obj(write(tmp_path / "t.obj", "\n".join(lines) + "\n"))
    assert np.allclose(ply.normals[:4], obj.normals, atol=1e-7)
    assert ply.normals[5].tolist() == [1, 0, 0]  # unreferenced vertex: placeholder


PLY_HEADER = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
              "end_header\n")


@pytest.mark.parametrize("text, pattern", [
    (PLY_HEADER + "0 0 0\n1 0 0\n0 1 oops\n3 0 1 2\n",
     r"bad\.ply, line 12 \(element 'vertex' row 2 property 'z'\): malformed input"),
    (PLY_HEADER + "0 0 0\n1 0 0\n0 1 0\n", r"bad\.ply, line 13 .*early end-of-file"),
    (PLY_HEADER.replace("property float z", "property flot z"),
     r"bad\.ply, line 6: invalid PLY header"),
    ("not a ply\n", r"bad\.ply, line 1: invalid PLY header"),
    (PLY_HEADER + "0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
     r"bad\.ply: triangle 0 has vertex indices \[0, 1, 7\], expected indices in \[0, 3\)"),
    (PLY_HEADER + "0 0 0\n1 0 0\n0 1 0\n2 0 1\n", r"bad\.ply: face 0 has 2 vertices"),
    (PLY_HEADER.replace("property float z\n", "") + "0 0\n1 0\n0 1\n3 0 1 2\n",
     r"bad\.ply: element 'vertex' lacks properties z"),
    (PLY_HEADER.replace("vertex_indices", "corners") + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
     r"bad\.ply: element 'face' has no 'vertex_index' or 'vertex_indices'"),
])
def test_ply_errors_name_file(tmp_path, text, pattern):
    with pytest.raises(MeshError, match=pattern):
        load_ply(write(tmp_path / "bad.ply", text))


def test_fuzzed_huge_obj_index_is_a_mesh_error(tmp_path):
    # Found by fuzz/fuzz_obj.py: an index beyond int64 raised OverflowError.
    body = TRI + "vt 0 0\nf 1 2 3/88888888888888888888888881\n"
    with pytest.raises(MeshError, match=r"bad\.obj, line 5: index 88888888888888888888888881 .*out of range"):
        load_obj(write(tmp_path / "bad.obj", body))


def test_fuzzed_ply_list_length_beyond_its_type_is_a_mesh_error(tmp_path):
    # Found by fuzz/fuzz_ply.py: a list length of 300 for a uchar count raised plyfile's
    # OverflowError.
    text = PLY_HEADER + "0 0 0\n1 0 0\n0 1 0\n300 0 1 2\n"
    with pytest.raises(MeshError, match=r"bad\.ply: cannot parse PLY file .*300"):
        load_ply(write(tmp_path / "bad.ply", text))


def test_truncated_binary_ply(tmp_path):
    path = write_ply(tmp_path / "full.ply", TRIS)
    data = path.read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-5])
    with pytest.raises(MeshError, match=r"cut\.ply, element 'face' row .*end-of-file"):
        load_ply(tmp_path / "cut.ply")


# ---------------------------------------------------------------------------------------
# Built-in shapes, transforms, flipping
# ---------------------------------------------------------------------------------------


def test_rectangle_layout():
    mesh = rectangle()
    assert mesh.positions.shape == (4, 3) and mesh.faces.shape == (2, 3)
    assert np.all(mesh.positions[:, 2] == 0) and mesh.area() == pytest.approx(4.0)
    assert np.allclose(mesh.face_normals(), [[0, 0, 1]] * 2)
    assert np.allclose(mesh.normals, [[0, 0, 1]] * 4)
    # Mitsuba 3.9.1 analytic rectangle: si.uv = ((x + 1) / 2, (y + 1) / 2), e.g. a hit at
    # (0.9, -0.9) has uv (0.95, 0.05) and at (0.2, 0.7) uv (0.6, 0.85).
    assert np.allclose(mesh.uvs, (mesh.positions[:, :2] + 1) / 2)
    for point, uv in [((0.9, -0.9), (0.95, 0.05)), ((0.2, 0.7), (0.6, 0.85))]:
        assert np.allclose(interpolate_uv(mesh, point), uv)


def interpolate_uv(mesh: Mesh, xy):
    """Barycentric uv at planar point xy (z = 0) of the containing triangle."""
    for f in mesh.faces:
        a, b, c = mesh.positions[f, :2].astype(np.float64)
        m = np.column_stack([b - a, c - a])
        u, v = np.linalg.solve(m, np.asarray(xy) - a)
        if u >= -1e-9 and v >= -1e-9 and u + v <= 1 + 1e-9:
            return (1 - u - v) * mesh.uvs[f[0]] + u * mesh.uvs[f[1]] + v * mesh.uvs[f[2]]
    raise AssertionError("point outside the mesh")


def test_cube_layout_matches_mitsuba():
    mesh = cube()
    assert mesh.positions.shape == (24, 3) and mesh.faces.shape == (12, 3)
    assert mesh.area() == pytest.approx(24.0)
    # Mitsuba 3.9.1 mi.traverse(cube): first side (-y) and the face list pattern.
    assert mesh.positions[:4].tolist() == [[1, -1, -1], [1, -1, 1], [-1, -1, 1],
                                           [-1, -1, -1]]
    assert mesh.faces[:4].tolist() == [[0, 1, 2], [3, 0, 2], [4, 5, 6], [7, 4, 6]]
    sides = mesh.normals[::4].tolist()
    assert sides == [[0, -1, 0], [0, 1, 0], [1, 0, 0], [0, 0, 1], [-1, 0, 0], [0, 0, -1]]
    assert mesh.uvs[:4].tolist() == [[0, 1], [1, 1], [1, 0], [0, 0]]
    assert np.array_equal(mesh.uvs[4:8], mesh.uvs[:4])
    # Outward winding: geometric normals equal vertex normals and point away from 0.
    assert np.allclose(mesh.face_normals(), mesh.normals[mesh.faces[:, 0]])
    centers = mesh.positions[mesh.faces].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", centers, mesh.face_normals()) > 0)
    assert not mesh.computed_normals


def test_transform_positions_and_file_normals():
    matrix = np.array([[2, 0, 0, 1], [0, 1, 0, -2], [0, 0, 0.5, 3], [0, 0, 0, 1]], float)
    mesh = cube().transformed(matrix)
    assert np.allclose(mesh.bbox()[0], [-1, -3, 2.5]) and np.allclose(mesh.bbox()[1],
                                                                      [3, -1, 3.5])
    # Inverse transpose keeps the normals perpendicular to the (planar) sides.
    assert np.allclose(mesh.normals[mesh.faces[:, 0]], mesh.face_normals(), atol=1e-6)
    assert unit_rows(mesh.normals)
    assert np.array_equal(mesh.uvs, cube().uvs) and np.array_equal(mesh.faces, cube().faces)


def test_transform_with_shear_keeps_file_normals_perpendicular():
    matrix = np.array([[1, 0.7, 0, 0], [0, 1, 0.3, 0], [0.2, 0, 1, 0], [0, 0, 0, 1]], float)
    mesh = cube().transformed(matrix)
    assert np.allclose(mesh.normals[mesh.faces[:, 0]], mesh.face_normals(), atol=1e-6)


def test_mirror_transform_follows_mitsuba():
    # Mitsuba 3.9.1 keeps the winding under a mirroring to_world: the geometric normal
    # turns inward while stored normals (inverse transpose) keep pointing outward.
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mesh = cube().transformed(mirror)
    assert np.allclose(mesh.face_normals(), -mesh.normals[mesh.faces[:, 0]])
    assert np.allclose(mesh.normals[::4], [[0, -1, 0], [0, 1, 0], [-1, 0, 0], [0, 0, 1],
                                           [1, 0, 0], [0, 0, -1]])
    # Computed normals are recomputed from the winding: they agree with the geometric
    # normal (Mitsuba 3.9.1: the mirrored tetrahedron's normals are negated and mirrored).
    tet = Mesh(TETRA_POSITIONS, TETRA_FACES, TETRA_NORMALS_MITSUBA, computed_normals=True)
    flipped = tet.transformed(mirror)
    expected = -np.array(TETRA_NORMALS_MITSUBA) * [-1, 1, 1]
    assert np.allclose(flipped.normals, expected, atol=1e-6)


def test_flipped_reverses_winding_and_normals():
    mesh = cube()
    flipped = mesh.flipped()
    assert np.allclose(flipped.face_normals(), -mesh.face_normals())
    assert np.array_equal(flipped.normals, -mesh.normals)
    assert np.array_equal(flipped.uvs, mesh.uvs)
    assert np.array_equal(flipped.faces[:, 0], mesh.faces[:, 0])
    twice = flipped.flipped()
    assert np.array_equal(twice.faces, mesh.faces) and np.array_equal(twice.normals,
                                                                      mesh.normals)


def test_transformed_rejects_bad_matrices():
    with pytest.raises(MeshError, match=r"\(4, 4\)"):
        cube().transformed(np.eye(3))
    projective = np.eye(4)
    projective[3, 0] = 1
    with pytest.raises(MeshError, match="last row"):
        cube().transformed(projective)
    with pytest.raises(MeshError, match="singular"):
        cube().transformed(np.diag([1.0, 0.0, 1.0, 1.0]))


def test_mesh_validation():
    with pytest.raises(MeshError, match=r"positions: expected shape \(K, 3\)"):
        Mesh(np.zeros((3, 2)), [[0, 1, 2]])
    with pytest.raises(MeshError, match=r"face indices must lie in \[0, 3\)"):
        Mesh(np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(MeshError, match=r"normals: expected shape \(3, 3\)"):
        Mesh(np.zeros((3, 3)), [[0, 1, 2]], normals=np.zeros((2, 3)))
    with pytest.raises(MeshError, match="integer"):
        Mesh(np.zeros((3, 3)), [[0.0, 1.0, 2.0]])
    mesh = Mesh(np.zeros((3, 3), np.float64), np.array([[0, 1, 2]], np.int64))
    assert mesh.positions.dtype == np.float32 and mesh.faces.dtype == np.int32
    assert mesh.positions.flags.c_contiguous


def test_transformed_positions_are_bit_exact_with_mitsuba():
    # Mitsuba 3.9.1: bunny.ply vertices 0 and 1 under this to_world (vertex_positions of
    # mi.traverse); Mitsuba computes in float32 with fused multiply-adds.
    matrix = np.array([[3, 0.2, 0, 1], [0, 1, 0.5, 2], [0.1, 0, 0.5, 3], [0, 0, 0, 1]])
    local = [[-0.014685103669762611, 0.04038504511117935, -0.007524292450398207],
             [-0.02163480594754219, 0.04133204370737076, -0.01009399350732565],
             [0.0, 0.0, 0.0]]
    world = Mesh(local, [[0, 1, 2]]).transformed(matrix)
    assert world.positions[0].tolist() == [0.9640217423439026, 2.0366227626800537,
                                           2.994769334793091]
    assert world.positions[1].tolist() == [0.9433619976043701, 2.036284923553467,
                                           2.9927895069122314]


def test_ply_face_indices_declared_as_a_scalar(tmp_path):
    # Found by fuzz_ply: 'property int vertex_indices' (not a list) raised a TypeError.
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
              "property float y\nproperty float z\nelement face 1\nproperty int vertex_indices\n"
              "end_header\n").encode()
    body = np.array([0, 0, 0, 1, 0, 0, 0, 1, 0], np.float32).tobytes() + np.array([3], np.int32).tobytes()
    path = tmp_path / "scalar_faces.ply"
    path.write_bytes(header + body)
    with pytest.raises(MeshError, match=r"scalar_faces\.ply: property 'vertex_indices' of element 'face' is a scalar"):
        load_ply(path)


# ---------------------------------------------------------------------------------------
# Mitsuba's serialized format
# ---------------------------------------------------------------------------------------


def _serialized_loads():
    import json
    return json.loads((SHAPE_REFS / "serialized_mitsuba.json").read_text())


def test_serialized_matches_mitsuba():
    """Every mesh of the committed files (format versions 3 and 4, float32 and float64), with
    and without face_normals and to_world, loads as Mitsuba 3.9.1 loaded it
    (make_shape_references.py): positions, faces and uvs bitwise, normals to 1e-6."""
    doc = _serialized_loads()
    matrix = np.array(doc["to_world"]["matrix"])
    assert len(doc["loads"]) == 24
    for case in doc["loads"]:
        mesh = load_serialized(SHAPE_REFS / case["file"], case["shape_index"],
                               face_normals=case["face_normals"])
        if case["to_world"]:
            mesh = mesh.transformed(matrix)
        ref = case["arrays"]
        what = f"{case['file']} #{case['shape_index']} face_normals={case['face_normals']} to_world={case['to_world']}"
        assert np.array_equal(mesh.positions.ravel(), np.float32(ref["vertex_positions"])), what
        assert np.array_equal(mesh.faces.ravel(), ref["faces"]), what
        assert (mesh.normals is not None) == case["has_normals"], what
        if case["has_normals"]:
            np.testing.assert_allclose(mesh.normals.ravel(), ref["vertex_normals"], atol=1e-6, err_msg=what)
        assert (mesh.uvs is not None) == case["has_uvs"], what
        if case["has_uvs"]:
            assert np.array_equal(mesh.uvs.ravel(), np.float32(ref["vertex_texcoords"])), what


def test_serialized_round_trip_and_double_rounding(tmp_path):
    rng = np.random.default_rng(3)
    positions = rng.normal(size=(7, 3))
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 0, 3]])
    normals = rng.normal(size=(7, 3))
    uvs = rng.uniform(size=(7, 2))
    for version in (3, 4):
        for double in (False, True):
            path = tmp_path / f"m{version}{int(double)}.serialized"
            write_serialized(path, [dict(positions=positions[:3], faces=[[0, 1, 2]]),
                                    dict(positions=positions, faces=faces, normals=normals,
                                         uvs=uvs, colors=uvs[:, [0, 1, 1]], name="b")],
                             version=version, double=double)
            m = load_serialized(path, 1)
            # float64 values are rounded to nearest float32, as Mitsuba's (float) cast
            assert np.array_equal(m.positions, positions.astype(np.float32))
            assert np.array_equal(m.faces, faces)
            assert np.array_equal(m.uvs, uvs.astype(np.float32))
            np.testing.assert_allclose(m.normals, normals / np.linalg.norm(normals, axis=1, keepdims=True), atol=1e-6)
            first = load_serialized(path, 0)
            assert first.face_count == 1 and first.computed_normals


@pytest.mark.parametrize("damage, pattern", [
    (lambda b: b"\x1d" + b[1:], "not a Mitsuba serialized file"),
    (lambda b: b[:2] + b"\x05\x00" + b[4:], "version 5 is not supported"),
    (lambda b: b[:4] + b"\x00" * 12 + b[16:], "corrupt zlib stream"),
    (lambda b: b[:3], "only 3 bytes"),
    (lambda b: b[:20] + b[-4:], "truncated"),
])
def test_serialized_errors_name_the_file(tmp_path, damage, pattern):
    path = tmp_path / "m.serialized"
    write_serialized(path, [dict(positions=np.eye(3), faces=[[0, 1, 2]])])
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(MeshError, match=pattern) as info:
        load_serialized(path)
    assert "m.serialized" in str(info.value)


def test_serialized_shape_index_range_and_bad_indices(tmp_path):
    path = tmp_path / "m.serialized"
    write_serialized(path, [dict(positions=np.eye(3), faces=[[0, 1, 2]]),
                            dict(positions=np.eye(3), faces=[[0, 1, 3]])])
    with pytest.raises(MeshError, match="shape_index 2 is out of range .* holds 2 meshes"):
        load_serialized(path, 2)  # Mitsuba 3.9.1 fails too ("read 4 out of 8 bytes")
    with pytest.raises(MeshError, match=r"triangle 0 has vertex indices \[0, 1, 3\]"):
        load_serialized(path, 1)
    with pytest.raises(MeshError, match="not found"):
        load_serialized(tmp_path / "missing.serialized")


def test_ply_colors_become_mesh_attributes_like_mitsuba(tmp_path):
    """Mitsuba 3.9.1: vertex (red, green, blue) or (r, g, b) -> vertex_color, face colours ->
    face_color, alpha adds a channel, 8-bit values are kept as stored (255, not 1)."""
    vertex = np.empty(6, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                ("blue", "u1"), ("alpha", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = PLY_POSITIONS.T
    vertex["red"], vertex["green"], vertex["blue"], vertex["alpha"] = 255, 0, 128, 7
    face = np.empty(2, dtype=[("vertex_indices", "O"), ("r", "f4"), ("g", "f4"), ("b", "f4")])
    face["vertex_indices"] = [np.array([0, 1, 2, 3], np.int32), np.array([0, 3, 4], np.int32)]
    face["r"], face["g"], face["b"] = [0.1, 0.2], [0.3, 0.4], [0.5, 0.6]
    path = tmp_path / "c.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex"),
                     plyfile.PlyElement.describe(face, "face")]).write(str(path))
    mesh = load_ply(path)
    assert np.array_equal(mesh.attributes["vertex_color"], np.tile([255, 0, 128, 7], (6, 1)))
    # the quad's two triangles share its colour (polygons are fan-triangulated)
    np.testing.assert_allclose(mesh.attributes["face_color"],
                               [[0.1, 0.3, 0.5], [0.1, 0.3, 0.5], [0.2, 0.4, 0.6]], rtol=1e-6)
    moved = mesh.transformed(np.diag([2.0, 1, 1, 1]))
    assert moved.attributes["face_color"] is mesh.attributes["face_color"]
    assert "vertex_color" not in load_ply(write_ply(tmp_path / "plain.ply", TRIS)).attributes
