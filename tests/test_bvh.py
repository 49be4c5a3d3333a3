"""Ray intersection (csrc/bvh.cpp, shapes.h): the BVH agrees with brute force, closed meshes
are watertight at their shared edges and vertices, spheres are hit where they are, and a
small scene's rays tested in SIMD lanes hit what the traversal hits, bit for bit."""
import shutil
import subprocess

import numpy as np
import pytest
import torch

import torch_rbpt as tr
from torch_rbpt import build_flags, meshes
from conftest import OPT_FLAGS, ROOT, SHARED, assert_marked_loops_vectorise, uninstrumented_env


def _mesh_scene(mesh_dict):
    return tr.load_dict({"type": "scene", "m": mesh_dict})


def _brute_force_hits(tris, o, d):
    """Every ray against every triangle (tris: (T, 3, 3) vertices; float64 Moller-Trumbore):
    per ray the nearest hit's distance (inf: none), triangle, barycentrics u and v (the
    weights of its vertices 1 and 2), and the second nearest hit's distance."""
    p0 = tris[:, 0].astype(np.float64)
    e1, e2 = tris[:, 1] - p0, tris[:, 2] - p0
    n = len(o)
    t_best, second, u_best, v_best = np.full(n, np.inf), np.full(n, np.inf), np.zeros(n), np.zeros(n)
    best = np.zeros(n, dtype=np.int64)
    for i in range(n):
        pv = np.cross(d[i], e2)
        det = np.einsum("ij,ij->i", e1, pv)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
        tv = o[i] - p0
        u = np.einsum("ij,ij->i", tv, pv) * inv
        qv = np.cross(tv, e1)
        v = (qv @ d[i]) * inv
        t = np.einsum("ij,ij->i", e2, qv) * inv
        t = np.where(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0), t, np.inf)
        j = int(t.argmin())
        t_best[i], best[i], u_best[i], v_best[i] = t[j], j, u[j], v[j]
        if len(t) > 1:
            second[i] = np.partition(t, 1)[1]
    return t_best, best, u_best, v_best, second


def _brute_force(positions, faces, o, d):
    """Nearest hit distance per ray by testing every triangle (float64 Moller-Trumbore)."""
    return _brute_force_hits(positions[faces].astype(np.float64), o, d)[0]


def test01_bvh_matches_brute_force_on_the_bunny(shared):
    path = shared / "meshes" / "bunny.ply"
    scene = _mesh_scene({"type": "ply", "filename": str(path)})
    mesh = meshes.load_ply(path)
    lo, hi = mesh.bbox()
    rng = np.random.default_rng(0)
    n = 300
    target = lo + (hi - lo) * rng.random((n, 3))
    o = target + rng.normal(size=(n, 3)) * float(np.linalg.norm(hi - lo))
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, shape = tr._C.intersect_rays(scene._native, torch.from_numpy(o).float(), torch.from_numpy(d).float())
    expected = _brute_force(mesh.positions, mesh.faces, o, d)
    hit = np.isfinite(expected)
    assert hit.sum() > 50  # the test sees real hits
    np.testing.assert_array_equal(np.isfinite(t.numpy()), hit)
    np.testing.assert_allclose(t.numpy()[hit], expected[hit], rtol=1e-4, atol=1e-5)
    assert scene._native.bvh_node_count > 1000
    # A SAH tree is far cheaper than testing every triangle.
    assert scene._native.bvh_sah_cost < 0.01 * scene._native.triangle_count


def test02_closed_mesh_is_watertight_at_edges_and_vertices():
    # From inside a cube, rays aimed exactly at its vertices and edge midpoints must hit.
    scene = _mesh_scene({"type": "cube", "to_world": tr.Transform.rotate([1, 1, 0], 30)})
    cube = meshes.cube().transformed(tr.Transform.rotate([1, 1, 0], 30).matrix)
    p = cube.positions.astype(np.float64)
    edges = np.concatenate([(p[cube.faces[:, a]] + p[cube.faces[:, b]]) / 2 for a, b in [(0, 1), (1, 2), (2, 0)]])
    targets = np.concatenate([p, edges])
    origins = np.array([[0.1, -0.05, 0.02], [0.0, 0.0, 0.0], [-0.3, 0.2, 0.1]])
    o = np.repeat(origins, len(targets), axis=0)
    d = np.tile(targets, (len(origins), 1)) - o
    t, _ = tr._C.intersect_rays(scene._native, torch.from_numpy(o).float(), torch.from_numpy(d).float())
    assert torch.isfinite(t).all(), f"{int((~torch.isfinite(t)).sum())} rays leaked through the cube"


def test03_sphere_hits_from_outside_and_inside():
    scene = _mesh_scene({"type": "sphere", "center": [1, 2, 3], "radius": 0.5})
    o = torch.tensor([[1.0, 2.0, 0.0], [1.0, 2.0, 3.0], [5.0, 5.0, 5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    t, shape = tr._C.intersect_rays(scene._native, o, d)
    torch.testing.assert_close(t[:2], torch.tensor([2.5, 0.5]))
    assert shape.tolist() == [0, 0, -1] and torch.isinf(t[2])


def test04_many_spheres_and_a_mesh_match_brute_force(shared):
    # Spheres and triangles share leaves (packs of four) in the 4-wide BVH: nearest hits and
    # shapes must match testing every primitive.
    rng = np.random.default_rng(2)
    centers = rng.uniform(-1, 1, size=(40, 3))
    radii = rng.uniform(0.02, 0.15, size=40)
    scene_dict = {"type": "scene"}
    for i, (c, r) in enumerate(zip(centers, radii)):
        scene_dict[f"s{i}"] = {"type": "sphere", "center": c.tolist(), "radius": float(r)}
    path = shared / "meshes" / "bunny.ply"
    scene_dict["bunny"] = {"type": "ply", "filename": str(path), "to_world": tr.Transform.scale(6)}
    scene = tr.load_dict(scene_dict)
    mesh = meshes.load_ply(path).transformed(tr.Transform.scale(6).matrix)
    n = 400
    # Rays from anywhere towards points near the spheres and the bunny's vertices.
    near = np.concatenate([centers[rng.integers(0, 40, n // 2)],
                           mesh.positions[rng.integers(0, len(mesh.positions), n - n // 2)]])
    o = rng.uniform(-2, 2, size=(n, 3))
    d = near + rng.normal(size=(n, 3)) * 0.05 - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, shape = tr._C.intersect_rays(scene._native, torch.from_numpy(o).float(), torch.from_numpy(d).float())
    oc = o[:, None, :] - centers[None]
    b = np.einsum("nkj,nj->nk", oc, d)
    disc = b ** 2 - (np.einsum("nkj,nkj->nk", oc, oc) - radii[None] ** 2)
    sq = np.sqrt(np.maximum(disc, 0))
    t_near = np.where(-b - sq > 0, -b - sq, -b + sq)
    t_sphere = np.where((disc >= 0) & (t_near > 0), t_near, np.inf).min(axis=1)
    t_mesh = _brute_force(mesh.positions, mesh.faces, o, d)
    expected = np.minimum(t_sphere, t_mesh)
    hit = np.isfinite(expected)
    assert hit.sum() > 200 and (t_mesh < t_sphere).sum() > 50 and (t_sphere < t_mesh).sum() > 50
    np.testing.assert_array_equal(np.isfinite(t.numpy()), hit)
    np.testing.assert_allclose(t.numpy()[hit], expected[hit], rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(shape.numpy()[hit] == 40, t_mesh[hit] < t_sphere[hit])


# The small scene below is a tree of one node (flat, or with the one-node shortcuts) with
# the 8-wide nodes of AVX builds; a baseline x86-64 build (PORTABLE=1) has 4-wide nodes, and
# the scene takes several.
one_node_small_scene = pytest.mark.skipif(tr._C.build_isa == "sse2",
                                          reason="the small scene fits one node with 8-wide nodes (AVX builds)")


def _small_scene(far_cube=False):
    """A cube (12 triangles), a quad of two triangles with a smaller one in its plane (a
    decal: ties between leaves), and two spheres, one touching the cube; with `far_cube`,
    another cube beside them (28 triangles in all, still one node)."""
    far = {"far": {"type": "cube", "to_world": tr.Transform.translate([2, 0.3, 0]).scale(0.9)}} if far_cube else {}
    return tr.load_dict({
        "type": "scene", **far,
        "box": {"type": "cube", "to_world": tr.Transform.translate([0.5, 0, 0]).scale(0.5)},
        "quad": {"type": "rectangle", "to_world": tr.Transform.translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(3)},
        "decal": {"type": "rectangle", "to_world": tr.Transform.translate([-1, -1, 1]).rotate([1, 0, 0], -90).scale(0.75)},
        "ball": {"type": "sphere", "center": [-1.0, 0, 0], "radius": 0.5},
        "touching": {"type": "sphere", "center": [0.5, 1.0, 0], "radius": 0.5},
    })


def _small_scene_rays(rng):
    """Rays for _small_scene(): 5000 towards the scene, many of them aimed at the cube's
    vertices and edges (exact ties, edge functions exactly zero) and at the decal (ties
    between leaves), along the axes, from the quad's surface, non-finite or zero, some with
    bounded intervals: (o, d, tmin, tmax) as float tensors."""
    n = 5000
    o = rng.normal(size=(n, 3)) * 3
    d = rng.uniform(-1.5, 1.5, size=(n, 3)) - o  # towards the scene
    # Rays aimed at the cube's vertices and edge midpoints, and at the quad's diagonal.
    corners = np.array([[x, y, z] for x in (0.0, 1.0) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    targets = np.concatenate([corners, (corners[:, None] + corners[None]).reshape(-1, 3) / 2,
                              np.stack([np.linspace(-3, 3, 40), np.full(40, -1.0), np.linspace(-3, 3, 40)], 1)])
    # And at random points of the cube's edges and face diagonals, and of the decal: edge
    # functions that round to zero in float, and ties.
    a, b = corners[rng.integers(0, 8, 1500)], corners[rng.integers(0, 8, 1500)]
    targets = np.concatenate([targets, a + (b - a) * rng.random((1500, 1)),
                              np.stack([rng.uniform(-1.7, -0.3, 500), np.full(500, -1.0), rng.uniform(0.3, 1.7, 500)], 1)])
    k = len(targets)
    d[:k] = targets - o[:k]
    # Rays along the axes from points of a grid of quarters (through the cube's edges and
    # its faces' diagonals, where the two triangles tie), rays from the quad's surface, and
    # degenerate rays.
    axis = rng.integers(0, 3, 200)
    o[k:k + 200] = np.round(rng.uniform(-1.2, 1.2, (200, 3)) * 4) / 4
    o[k + np.arange(200), axis] = 3.0 * rng.choice([-1, 1], 200)
    d[k:k + 200] = -np.eye(3)[axis] * np.sign(o[k + np.arange(200), axis])[:, None]
    o[k + 200:k + 300, 1] = -1.0
    o[k + 300] = [np.inf, 0, 0]
    o[k + 301] = [np.nan, 0, 0]
    d[k + 302] = [0, 0, 0]
    d[k + 303] = [np.inf, 1, 0]
    with np.errstate(invalid="ignore"):  # (the infinite direction becomes NaN: also a case)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    d[k + 302] = 0
    tmin = np.where(rng.random(n) < 0.1, rng.random(n), 0.0)
    tmax = np.where(rng.random(n) < 0.2, rng.random(n) * 4, np.inf)
    return [torch.from_numpy(a).float() for a in (o, d, tmin, tmax)]


@one_node_small_scene
@pytest.mark.parametrize("far_cube", [False, True])
def test05_flat_intersection_is_the_traversals_bitwise(far_cube):
    # A small scene's rays are tested against every primitive in SIMD lanes
    # (BVH::intersect_columns); each hit (t, primitive, barycentrics) must be the traversal's,
    # also for rays through the cube's vertices and edges (exact ties, edge functions exactly
    # zero), rays starting on surfaces, bounded intervals, and non-finite or zero rays. Beyond
    # 16 triangles the bound on t's rounding error is applied to each ray's nearest hit alone
    # (BVH::flat_rounding_check, exactly where a cheaper bound above it does not clear the
    # hit): the far cube's case, where the rays from the quad's surface need the exact test.
    scene = _small_scene(far_cube)
    assert scene._native.bvh_flat and scene._native.bvh_node_count == 1
    rng = np.random.default_rng(5)
    args = _small_scene_rays(rng)
    o, d, tmin, tmax = (a.double().numpy() for a in args)
    n = len(o)
    flat = tr._C.closest_hits(scene._native, *args, True)
    traversal = tr._C.closest_hits(scene._native, *args, False)
    assert int((traversal[1] >= 0).sum()) > 3000
    for a, b in zip(flat, traversal):
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
    # Calls of fewer rays than a chunk of lanes, or of a part of one (which the lanes fill up
    # with rays that hit nothing): the same hits, for the ties, the edges and the non-finite
    # rays among them.
    for start, m in ((n - 1, 1), (0, 5), (2400, 23), (2112, 303), (1000, 140)):
        part = [a[start:start + m] for a in args]
        for a, b in zip(tr._C.closest_hits(scene._native, *part, True), tr._C.closest_hits(scene._native, *part, False)):
            assert torch.equal(a.nan_to_num(), b.nan_to_num())
    # Where a hit lies within a rounding of its leaf's box, the test of the box and the hit's
    # distance can round apart, and the traversal may not visit the leaf: with the interval
    # ending a rounding past the hit, and for rays from just off the quad's plane towards the
    # decal in it (two leaves' hits a rounding apart). There, and only there, the lanes may
    # keep a hit the traversal does not find (documented at BVH::intersect_columns).
    def assert_same_but_for_roundings(rays, least_hits):
        flat = tr._C.closest_hits(scene._native, *rays, True)
        traversal = tr._C.closest_hits(scene._native, *rays, False)
        assert int((traversal[1] >= 0).sum()) > least_hits
        same = (flat[0].nan_to_num() == traversal[0].nan_to_num()) & (flat[1] == traversal[1])
        same &= (flat[2] == traversal[2]) & (flat[3] == traversal[3])
        t_flat, t_trav, t_max = flat[0].double(), traversal[0].double(), rays[3].double()
        near_tie = (t_flat - t_trav).abs() <= 1e-5 * t_trav + 1e-6  # (the scene is ~1 wide)
        at_the_end = torch.isinf(t_trav) & (t_flat >= t_max * (1 - 1e-5))
        assert bool((same | near_tie | at_the_end).all())
        assert int((~same).sum()) <= len(same) // 100
    t_hit = traversal[0].numpy().astype(np.float64)
    for scale, least_hits in ((1 - 1e-6, -1), (1.0, -1), (1 + 1e-6, 2000)):  # (the interval is open)
        near_hit = torch.from_numpy(np.where(np.isfinite(t_hit), t_hit * scale, tmax)).float()
        assert_same_but_for_roundings([args[0], args[1], args[2], near_hit], least_hits)
    m = 4000
    target = np.stack([rng.uniform(-1.7, -0.3, m), np.full(m, -1.0), rng.uniform(0.3, 1.7, m)], 1)
    o = target + rng.normal(size=(m, 3)) * 0.05
    o[:, 1] = -1.0 - rng.choice([-1, 1], m) * np.abs(rng.normal(size=m)) * 10.0 ** rng.uniform(-4, -1, m)
    d = target - o + rng.normal(size=(m, 3)) * 1e-3
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert_same_but_for_roundings([torch.from_numpy(a).float() for a in (o, d, np.zeros(m), np.full(m, np.inf))], m // 2)
    # Larger scenes keep the traversal (4 cubes: 48 triangles, beyond BVH::FlatTriangles).
    assert not tr.load_dict({"type": "scene", **{f"c{i}": {"type": "cube", "to_world": tr.Transform.translate([3 * i, 0, 0])}
                                                 for i in range(4)}})._native.bvh_flat


@pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")
@pytest.mark.parametrize("march", ["x86-64-v3", "native"])
def test06_flat_intersection_vectorises(tmp_path, march):
    # intersect_columns' loops over the rays (their constants and reciprocal directions, each
    # pass's chunks (the box tests of its halves, the triangle tests of both halves or of
    # one), the nearest hits' rounding check (its cheap bound for every ray, the
    # exact one for the doubtful, the primitives' gather), each sphere's near test, the hits'
    # copy, the flags of the rays a two-phase tree traces further or retraces, the rays'
    # 1 / |d|^2 for the spheres' near tests, ShapeBoxes::entered's finite check, and the
    # box tests of the root's children and of ShapeBoxes for the rays past the last whole
    # register) vectorise for AVX2 and for this machine: an edit that stops GCC keeps the
    # hits bitwise equal and only makes them slower, which no other test sees. (With AVX2
    # and AVX-512 the chunks' box and triangle tests, and those box tests' whole registers,
    # are written in their intrinsics: test14.)
    assert assert_marked_loops_vectorise("bvh.cpp", "#pragma GCC ivdep", march, tmp_path) == 18


@pytest.mark.parametrize("floor", [True, False])
def test08_shadow_rays_past_spheres_are_blocked_where_the_closest_hit_lies_inside(floor):
    # Shadow rays (BVH::occluded, which stops at the first hit) are blocked exactly where the
    # nearest hit lies inside their interval: rays towards points on the spheres stopping
    # short by the shadow epsilon (as towards a sphere light), rays from inside, from the
    # surfaces, and with random and unbounded intervals. The same in lanes (occluded_columns,
    # which the wavefront's shadow rays take in small scenes with sphere lights), and the
    # closest hits in lanes those of the traversal, bitwise: with a floor, and for spheres
    # alone, which are a flat tree too.
    centers = np.array([[0.0, 0.0, 0.0], [1.5, 0.2, 0.0], [-1.0, 1.0, 0.5], [0.3, -1.2, 1.0]])
    radii = np.array([0.5, 0.3, 0.05, 0.8])
    scene = tr.load_dict({"type": "scene", **{f"s{i}": {"type": "sphere", "center": c.tolist(), "radius": float(r)}
                                              for i, (c, r) in enumerate(zip(centers, radii))},
                          **({"floor": {"type": "rectangle", "to_world": tr.Transform.translate([0, -2.5, 0])
                                        .rotate([1, 0, 0], -90).scale(4)}} if floor else {})})
    if tr._C.build_isa != "sse2":  # (the flat tree needs one 8-wide node)
        assert scene._native.bvh_flat
    rng = np.random.default_rng(8)
    n = 6000
    o = rng.normal(size=(n, 3)) * 2.0
    which = rng.integers(0, 4, n)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    # A sixth of the targets near the sphere's silhouette as the origin sees it (the normal
    # within 1e-3 of perpendicular to the line of sight), where a shadow ray's interval
    # ends closest to the sphere's far side: lanes that leave out a sphere the ray's
    # interval cannot reach must leave out no other.
    k = n // 6
    view = centers[which[:k]] - o[:k]
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    side = normal[:k] - view * np.sum(normal[:k] * view, axis=1, keepdims=True)
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    normal[:k] = side - view * rng.uniform(-1e-3, 1e-2, (k, 1))
    normal[:k] /= np.linalg.norm(normal[:k], axis=1, keepdims=True)
    target = centers[which] + normal * radii[which, None]
    d = target - o
    dist = np.linalg.norm(d, axis=1)
    d /= dist[:, None]
    tmax = dist * (1 - 10 * 1500 * 2.0 ** -24)  # (spawn_ray_to's shadow epsilon)
    tmin = np.zeros(n)
    # Random directions and intervals, some unbounded; origins on and inside the spheres.
    m = n // 2
    d[m:] = rng.normal(size=(n - m, 3))
    d[m:] /= np.linalg.norm(d[m:], axis=1, keepdims=True)
    tmax[m:] = np.where(rng.random(n - m) < 0.2, np.inf, rng.random(n - m) * 4)
    tmin[m:] = np.where(rng.random(n - m) < 0.3, rng.random(n - m) * 0.5, 0.0)
    o[m:m + 1000] = target[m:m + 1000]  # on a surface
    o[m + 1000:m + 2000] = centers[which[m + 1000:m + 2000]] + normal[m + 1000:m + 2000] * radii[which[m + 1000:m + 2000], None] * 0.5
    rays = [torch.from_numpy(a).float() for a in (o, d, tmin, tmax)]
    blocked = tr._C.occluded_rays(scene._native, *rays, False)
    traversal = tr._C.closest_hits(scene._native, *rays, False)
    hit = traversal[1] >= 0
    assert 500 < int(blocked.sum()) < n - 500
    assert torch.equal(blocked, hit)
    for a, b in zip(tr._C.closest_hits(scene._native, *rays, True), traversal):
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
    assert torch.equal(tr._C.occluded_rays(scene._native, *rays, True), blocked)
    assert torch.equal(tr._C.occluded_rays(scene._native, *rays, False, masks=True), blocked)
    # The wavefront gives lanes without a shadow ray an empty interval (tmax -1): nothing
    # blocks those, in lanes or not, whatever their origin and direction.
    empty = [rays[0], rays[1], rays[2], torch.full_like(rays[3], -1.0)]
    for columns in (True, False):
        assert not bool(tr._C.occluded_rays(scene._native, *empty, columns).any())


def _ending_near_hits(args, t_hit):
    """(scale, rays): the rays `args` (o, d, tmin, tmax) as they are (scale None), and each
    ending a rounding before, at or after its nearest hit t_hit, where the box tests
    decide (scale 1 - 1e-6, 1, 1 + 1e-6; the rays without a hit as they are)."""
    t_hit = t_hit.double()
    for scale in (None, 1 - 1e-6, 1.0, 1 + 1e-6):
        ends = args[3] if scale is None else torch.where(torch.isfinite(t_hit), t_hit * scale, args[3].double()).float()
        yield scale, [args[0], args[1], args[2], ends]


@one_node_small_scene
@pytest.mark.parametrize("far_cube", [False, True])
def test09_one_node_shortcuts_are_the_traversals_bitwise(far_cube):
    # In a tree of one node, BVH::intersect and BVH::occluded test the children the ray enters
    # without the general traversal's stack (intersect_one_node, occluded_one_node): the
    # closest hits (t, primitive, barycentrics; ties go to the child the traversal visits
    # first) and the blocked rays must be the traversal's, bit for bit. Also in a scene of
    # one node with a disk and a cylinder, which is flat since session 52 (its disks and
    # cylinders tested for the rays that enter their boxes): there the lanes' closest hits
    # and blocked rays must be the traversal's too.
    scenes = [_small_scene(far_cube)]
    if not far_cube:
        scenes.append(tr.load_dict({
            "type": "scene",
            "box": {"type": "cube", "to_world": tr.Transform.translate([0.5, 0, 0]).scale(0.5)},
            "quad": {"type": "rectangle", "to_world": tr.Transform.translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(3)},
            "disk": {"type": "disk", "to_world": tr.Transform.translate([-1, 0.5, 0]).rotate([0, 1, 0], 30).scale(0.6)},
            "tube": {"type": "cylinder", "p0": [0.5, 1.0, -1.0], "p1": [0.5, 1.0, 1.0], "radius": 0.3},
            "ball": {"type": "sphere", "center": [-1.0, -0.5, 0.5], "radius": 0.4},
        }))
        assert scenes[1]._native.bvh_flat
    rng = np.random.default_rng(9)
    for scene in scenes:
        assert scene._native.bvh_node_count == 1
        args = _small_scene_rays(rng)
        shortcut = tr._C.closest_hits(scene._native, *args, False)
        traversal = tr._C.closest_hits(scene._native, *args, False, traversal=True)
        assert int((traversal[1] >= 0).sum()) > 2500
        for a, b in zip(shortcut, traversal):
            assert torch.equal(a.nan_to_num(), b.nan_to_num())
        if scene is not scenes[0]:
            others = (traversal[1] == 14) | (traversal[1] == 15)  # (after 14 triangles: the disk, the tube)
            assert int(others.sum()) > 200
            for a, b in zip(tr._C.closest_hits(scene._native, *args, True), traversal):
                assert torch.equal(a.nan_to_num(), b.nan_to_num())
        # Shadow rays: the same rays, and each ending just short of its nearest hit (a
        # rounding before or after it, where the box tests decide). Also through the
        # children each ray enters, found for a batch in lanes (BVH::root_masks, then
        # occluded_children: the wavefront's shadow rays in these scenes).
        for scale, rays in _ending_near_hits(args, traversal[0]):
            blocked = tr._C.occluded_rays(scene._native, *rays, False)
            assert torch.equal(blocked, tr._C.occluded_rays(scene._native, *rays, False, traversal=True))
            assert torch.equal(blocked, tr._C.occluded_rays(scene._native, *rays, False, masks=True))
            if scene is not scenes[0]:
                assert torch.equal(blocked, tr._C.occluded_rays(scene._native, *rays, True))
            assert int(blocked.sum()) > (1000 if scale is None or scale > 1 else -1)


def test10_two_phase_tree_is_the_traversals(shared):
    # A detailed mesh in a room: the root's leaves (the room's 12 triangles) are tested in
    # lanes, then the rest of the tree for the rays that enter its inner boxes
    # (BVH::two_phase). The lanes' hits and shadow rays must be intersect()'s and occluded()'s
    # bit for bit, and those the general traversal's but where a hit lies within a rounding
    # of a leaf's box (the root's leaves are tested without their boxes).
    bunny = shared / "meshes" / "bunny.ply"
    scene = tr.load_dict({
        "type": "scene",
        "room": {"type": "cube", "to_world": tr.Transform.scale(2), "flip_normals": True},
        "bunny": {"type": "ply", "filename": str(bunny), "to_world": tr.Transform.translate([0, -1.5, 0]).scale(9)},
    })
    assert scene._native.bvh_two_phase and not scene._native.bvh_flat
    rng = np.random.default_rng(10)
    n = 20000
    o = rng.uniform(-1.9, 1.9, size=(n, 3))
    d = rng.normal(size=(n, 3))
    # A third aimed at the bunny's vertices, some from the walls, some with bounded intervals,
    # and degenerate rays.
    mesh = meshes.load_ply(bunny).transformed(tr.Transform.translate([0, -1.5, 0]).scale(9).matrix)
    m = n // 3
    d[:m] = mesh.positions[rng.integers(0, len(mesh.positions), m)] - o[:m]
    axis = rng.integers(0, 3, 2000)
    o[m + np.arange(2000), axis] = 2.0 * rng.choice([-1, 1], 2000)
    # And 3000 at the bunny's extreme vertices, on the boxes of the tree's top nodes (hits on
    # box faces: the lanes' test of the root's inner boxes must let them through as the
    # traversal's does).
    p = mesh.positions.astype(np.float64)
    extremes = p[np.concatenate([np.argmin(p, axis=0), np.argmax(p, axis=0)])]
    d[m + 2000:m + 5000] = extremes[rng.integers(0, 6, 3000)] - o[m + 2000:m + 5000]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o[-3] = [np.inf, 0, 0]
    d[-2] = [0, 0, 0]
    o[-1] = [np.nan, 0, 0]
    tmin = np.where(rng.random(n) < 0.1, rng.random(n) * 0.5, 0.0)
    tmax = np.where(rng.random(n) < 0.2, rng.random(n) * 3, np.inf)
    args = [torch.from_numpy(a).float() for a in (o, d, tmin, tmax)]
    lanes = tr._C.closest_hits(scene._native, *args, True)
    per_ray = tr._C.closest_hits(scene._native, *args, False)
    traversal = tr._C.closest_hits(scene._native, *args, False, traversal=True)
    for a, b in zip(lanes, per_ray):
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
    on_room = (per_ray[1] >= 0) & (per_ray[1] < 12)
    assert int(on_room.sum()) > 5000 and int((per_ray[1] >= 12).sum()) > 5000
    same = (per_ray[0].nan_to_num() == traversal[0].nan_to_num()) & (per_ray[1] == traversal[1])
    same &= (per_ray[2] == traversal[2]) & (per_ray[3] == traversal[3])
    assert int((~same).sum()) <= n // 1000
    near = (per_ray[0].double() - traversal[0].double()).abs() <= 1e-5 * traversal[0].double().abs() + 1e-6
    assert bool((same | near).all())
    # Shadow rays: the same rays, and each ending a rounding before its nearest hit.
    for ends in (args[3], torch.where(torch.isfinite(per_ray[0]), per_ray[0].double() * (1 - 1e-6), args[3].double()).float()):
        rays = [args[0], args[1], args[2], ends]
        blocked = tr._C.occluded_rays(scene._native, *rays, True)
        assert torch.equal(blocked, tr._C.occluded_rays(scene._native, *rays, False))
        hit = tr._C.closest_hits(scene._native, *rays, False)[1] >= 0
        assert int((blocked != hit).sum()) == 0
        assert int((blocked != tr._C.occluded_rays(scene._native, *rays, False, traversal=True)).sum()) <= n // 1000
        # (Empty intervals, as the wavefront's lanes without a shadow ray have: never blocked.)
        assert not bool(tr._C.occluded_rays(scene._native, *rays[:3], torch.full_like(rays[3], -1.0), True).any())
    # The root's masks serve trees of one node only; asked of this tree, a clear error.
    with pytest.raises(ValueError, match="one node"):
        tr._C.occluded_rays(scene._native, *rays, False, masks=True)


@pytest.mark.parametrize("far_cube", [False, True])
def test11_flat_chunks_skip_only_boxes_their_rays_miss(far_cube):
    # The lanes skip a half of a pass of four triangles (a pair) for a chunk of 16 rays none
    # of which enters the pair's box (widened) before its nearest hit so far, and a single
    # triangle whose box is small beside the scene's likewise (BVH::flat_triangles; the
    # build pairs the triangles of smallest joint box). Bundles of 16 rays from one origin,
    # as a pixel's samples are, aimed at the cubes' vertices, edges and faces (hits on the
    # boxes' boundaries), at the decal, past the scene, and with intervals ending at or
    # near the hits: each hit must be the traversal's, bit for bit.
    scene = _small_scene(far_cube)
    rng = np.random.default_rng(11)
    bundles = 600
    corners = np.array([[x, y, z] for x in (0.0, 1.0) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    if far_cube:
        corners = np.concatenate([corners, (corners - [0.5, 0, 0]) * 1.8 + [2, 0.3, 0]])
    a, b = corners[rng.integers(0, len(corners), bundles)], corners[rng.integers(0, len(corners), bundles)]
    along = np.where(rng.random((bundles, 1)) < 0.3, rng.integers(0, 3, (bundles, 1)) / 2, rng.random((bundles, 1)))
    target = a + (b - a) * along  # vertices, edge midpoints, edges, face diagonals
    kind = rng.integers(0, 4, bundles)
    target[kind == 1] = rng.uniform(-1.7, 1.7, (int((kind == 1).sum()), 3))  # anywhere
    target[kind == 2] = np.stack([rng.uniform(-1.7, -0.3, int((kind == 2).sum())), np.full(int((kind == 2).sum()), -1.0),
                                  rng.uniform(0.3, 1.7, int((kind == 2).sum()))], 1)  # the decal
    target[kind == 3] *= 4.0  # past the scene
    origin = rng.normal(size=(bundles, 3)) * 3 + np.where(rng.random((bundles, 1)) < 0.2, 40.0, 0.0) * rng.normal(size=(bundles, 3))
    spread = 10.0 ** rng.uniform(-6, -1, (bundles, 1, 1))
    d = (target - origin)[:, None] + rng.normal(size=(bundles, 16, 3)) * spread * np.linalg.norm(target - origin, axis=1)[:, None, None]
    d[:, 0] = target - origin  # one ray of each bundle exactly at its target
    o = np.repeat(origin[:, None], 16, axis=1).reshape(-1, 3)
    d = (d / np.linalg.norm(d, axis=2, keepdims=True)).reshape(-1, 3)
    n = len(o)
    args = [torch.from_numpy(x).float() for x in (o, d, np.zeros(n), np.full(n, np.inf))]
    traversal = tr._C.closest_hits(scene._native, *args, False)
    assert 0.2 * n < int((traversal[1] >= 0).sum()) < 0.9 * n
    flat = tr._C.closest_hits(scene._native, *args, True)
    for x, y in zip(flat, traversal):
        assert torch.equal(x.nan_to_num(), y.nan_to_num())
    # Intervals ending just past each bundle's first hit: the rest of the bundle must find
    # the same hits as the traversal with that end.
    t_end = np.repeat(traversal[0].numpy().reshape(bundles, 16)[:, :1] * (1 + 1e-3), 16, axis=1).reshape(-1)
    args[3] = torch.from_numpy(np.where(np.isfinite(t_end), t_end, np.inf)).float()
    traversal = tr._C.closest_hits(scene._native, *args, False)
    flat = tr._C.closest_hits(scene._native, *args, True)
    for x, y in zip(flat, traversal):
        assert torch.equal(x.nan_to_num(), y.nan_to_num())


def _shadow_scenes(integrator=None):
    """Scenes for the shadow rays' tree (Scene::shadow_bvh), with the number of primitives it
    should keep: a closed room seen from inside (its 12 walls left out) around a box, a ball
    and a light; the same under a constant environment (shadow rays to infinity: nothing left
    out); a cube seen from outside under a point light in front of it (only the face towards
    the light can block a segment between two of the scene's points)."""
    sensor = lambda origin, target: {  # noqa: E731
        "type": "perspective", "fov": 70, "to_world": tr.Transform.look_at(origin, target, [0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 24, "height": 16, "rfilter": {"type": "box"}}}
    integrator = integrator or {"type": "path"}
    room = {
        "type": "scene", "sensor": sensor([0.2, 0.1, 1.8], [0, -0.3, 0]), "integrator": integrator,
        "room": {"type": "cube", "flip_normals": True, "to_world": tr.Transform.scale(2),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.6, 0.5]}}},
        "box": {"type": "cube", "to_world": tr.Transform.translate([0.4, -0.6, -0.3]).rotate([0, 1, 0], 25).scale(0.35)},
        "ball": {"type": "sphere", "center": [-0.7, -1.5, 0.2], "radius": 0.5},
        "light": {"type": "rectangle", "to_world": tr.Transform.translate([0, 1.9, 0]).rotate([1, 0, 0], 90).scale(0.5),
                  "emitter": {"type": "area", "radiance": 8.0}},
    }
    lit_cube = {
        "type": "scene", "sensor": sensor([3, 2.5, 4], [0, 0, 0]), "integrator": integrator,
        "cube": {"type": "cube", "to_world": tr.Transform.rotate([0, 1, 0], 10),
                 "bsdf": {"type": "diffuse", "reflectance": 0.6}},
        "light": {"type": "point", "position": [0.5, 0.3, 5.0], "intensity": 30.0},
    }
    outside = {k: v for k, v in room.items() if k not in ("ball", "light")}
    outside["light"] = {"type": "point", "position": [0.5, 0.3, 5.0], "intensity": 30.0}
    # (The room's primitives: 26 triangles and the ball.)
    # (With the point light's position, for segments to it.)
    return [("room", tr.load_dict(room), 15, None),
            ("room lit from outside", tr.load_dict(outside), 14, [0.5, 0.3, 5.0]),
            ("room under the sky", tr.load_dict({**room, "sky": {"type": "constant", "radiance": 0.5}}), 27, None),
            ("lit cube", tr.load_dict(lit_cube), 2, [0.5, 0.3, 5.0])]


def test12_shadow_tree_leaves_out_only_what_cannot_block_a_shadow_ray():
    # Shadow rays run between two points of the scene (a surface's, and a light's); a
    # triangle whose plane has the whole scene on one side (a room's wall) cannot block such
    # a segment, so their tree leaves those out. Segments between points on every surface
    # (each wall, the box, the ball, the light, the point light) must be blocked in that
    # tree exactly where they are in the whole scene's.
    rng = np.random.default_rng(12)
    for name, scene, kept, light in _shadow_scenes():
        native = scene._native
        assert native.shadow_primitive_count == kept, name
        # Points on the surfaces: the hits of rays from inside the room, or from around the cube.
        n = 4000
        if name.startswith("room"):
            o = rng.uniform(-1.8, 1.8, (n, 3))
        else:
            o = rng.normal(size=(n, 3))
            o = 4 * o / np.linalg.norm(o, axis=1, keepdims=True)
        d = rng.normal(size=(n, 3)) if name.startswith("room") else rng.uniform(-0.9, 0.9, (n, 3)) - o
        o, d = torch.tensor(o, dtype=torch.float32), torch.tensor(d, dtype=torch.float32)
        t, prim, _, _ = tr._C.closest_hits(native, o, d, torch.zeros(n), torch.full((n,), float("inf")), False)
        hit = prim >= 0
        assert int(hit.sum()) > n // 2, name
        p = (o + t.unsqueeze(1) * d)[hit]
        targets = p[torch.randperm(len(p), generator=torch.Generator().manual_seed(3))]
        if light is not None:
            targets = torch.cat([targets[: len(p) // 2], torch.tensor([light]).expand(len(p) - len(p) // 2, 3)])
        seg = targets - p
        m = len(p)
        # (Between the ends: a ten-thousandth of the segment off each, as a shadow ray's
        # offset origin and shortened end would be.)
        args = (p, seg, torch.full((m,), 1e-4), torch.full((m,), 1 - 1e-4))
        whole = tr._C.occluded_rays(native, *args, False)
        for columns in (False, True):
            shadow = tr._C.occluded_rays(native, *args, columns, shadow=True)
            assert torch.equal(shadow, whole), name
        assert 0.05 * m < int(whole.sum()) < 0.95 * m, name


@pytest.mark.parametrize("integrator", ["path", "direct"])
def test13_shadow_tree_renders_the_whole_trees_image(integrator, monkeypatch):
    # Renders with the shadow rays' tree and with the whole tree (build_shadow_tree(False))
    # are the same bit for bit, in SIMD lanes and through the scalar integrator (the shared
    # cornell-box too, where present: its walls are left out of its shadow tree).
    settings = {"type": "path", "max_depth": 5} if integrator == "path" else {"type": "direct"}
    scenes = [(name, scene) for name, scene, _, _ in _shadow_scenes(settings)]
    cornell = SHARED / "cornell-box" / "scene_v3.xml"
    if integrator == "path" and cornell.exists():
        scene = tr.load_file(cornell)
        scene.sensor.film.width = scene.sensor.film.height = 24
        assert scene._native.shadow_primitive_count < scene._native.triangle_count
        scenes.append(("cornell-box", scene))
    for name, scene in scenes:
        for wavefront in ("1", "0"):
            monkeypatch.setenv("TORCH_RBPT_WAVEFRONT", wavefront)
            scene._native.build_shadow_tree(True)
            culled = tr.render(scene, spp=16, seed=5)
            scene._native.build_shadow_tree(False)
            whole = tr.render(scene, spp=16, seed=5)
            scene._native.build_shadow_tree(True)
            # (Nothing reaches the room from a light outside it.)
            assert (float(whole.max()) == 0) == (name == "room lit from outside"), name
            assert torch.equal(culled, whole), (name, wavefront)


@pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")
def test14_flat_pass_is_the_traversals_in_every_build(tmp_path):
    # The flat pass's chunk tests are written in AVX-512 intrinsics for this machine (where
    # it has AVX-512) and in AVX2's for x86-64-v3, which no other test runs: tests/cpp/
    # flat_pass.cpp, compiled with the extension's optimisation flags for both, tests the
    # closest hits of rays at a box's vertices and edges (edge functions exactly zero, ties
    # between a face's triangles), at a decal in a quad's plane, from the quad's surface,
    # along the axes, non-finite, with bounded intervals, in a flat tree of 14 triangles and
    # of 30 (the rounding bound deferred; the box's faces and the quads tested as quads),
    # against the traversal's, bit for bit; the same rays as shadow rays through the root's
    # masks (BVH::root_masks, also in intrinsics) against occluded(), blocked where they have
    # a closest hit (the quads too: their widening the same in both queries);
    # ShapeBoxes::entered (also in intrinsics) flagging every ray whose hit is on its shapes;
    # and both builds must give the same hits, masks and flags (the same hash).
    outputs = {}
    for march in ("x86-64-v3", "native"):
        exe = tmp_path / f"flat_pass_{march}"
        build = subprocess.run(["g++", *OPT_FLAGS, *build_flags.target_flags(march), f"-I{ROOT / 'csrc'}",
                                str(ROOT / "tests" / "cpp" / "flat_pass.cpp"), str(ROOT / "csrc" / "bvh.cpp"),
                                str(ROOT / "csrc" / "shapes.cpp"), "-o", str(exe)], capture_output=True, text=True,
                               env=uninstrumented_env())
        assert build.returncode == 0, build.stderr[-3000:]
        run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=120)
        fields = run.stdout.split()
        assert run.returncode == 0 and fields[:1] == ["rays"], f"{march}: {run.stdout}{run.stderr}"
        result = dict(zip(fields[::2], fields[1::2]))
        assert int(result["rays"]) == 12288 and int(result["hits"]) > 6000 and int(result["differ"]) == 0, (march, result)
        assert int(result["blocked"]) == int(result["hits"]), (march, result)  # (blocked where there is a hit)
        assert 3000 < int(result["entered"]) < 12288, (march, result)
        outputs[march] = result
    assert outputs["x86-64-v3"] == outputs["native"]


def _obj_file(path, vertices, faces):
    """An OBJ file of `vertices` (rows x y z) and triangles `faces` (0-based), for a scene."""
    path.write_text("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(vertices, np.float64).tolist())
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    return str(path)


def _quad_scene(tmp_path):
    """A flat scene of parallelograms: a rotated cube (six faces of two triangles), two
    sheared parallelograms and a kite of two triangles (not a parallelogram); with its
    triangles' vertices (float64, as the renderer has them) in primitive order."""
    rotate = tr.Transform.rotate([1, 2, 0.5], 37)
    sheared = [[-2.0, -1.0, 0.3], [-1.2, -1.1, 0.5], [-0.9, 0.2, 0.9], [-1.7, 0.3, 0.7],
               [1.4, -1.6, -0.2], [2.6, -1.5, 0.4], [2.9, -0.4, 0.6], [1.7, -0.5, 0.0]]
    kite = [[0.0, 1.4, -0.5], [0.6, 1.6, -0.4], [0.2, 2.6, -0.2], [-0.5, 1.7, -0.6]]
    scene = tr.load_dict({
        "type": "scene",
        "cube": {"type": "cube", "to_world": rotate},
        "sheared": {"type": "obj", "filename": _obj_file(tmp_path / "sheared.obj", sheared,
                                                         [(0, 1, 2), (0, 2, 3), (4, 5, 6), (4, 6, 7)])},
        "kite": {"type": "obj", "filename": _obj_file(tmp_path / "kite.obj", kite, [(0, 1, 2), (0, 2, 3)])},
    })
    cube = meshes.cube().transformed(rotate.matrix)
    tris = [cube.positions[cube.faces].astype(np.float64)]
    for verts, faces in ((sheared, [(0, 1, 2), (0, 2, 3), (4, 5, 6), (4, 6, 7)]), (kite, [(0, 1, 2), (0, 2, 3)])):
        tris.append(np.asarray(verts, np.float32).astype(np.float64)[np.asarray(faces)])
    return scene, np.concatenate(tris)


@one_node_small_scene
def test15_parallelograms_are_tested_as_quads(tmp_path):
    # Pairs of a flat tree's triangles that make a parallelogram (a cube's faces, sheared
    # ones) are tested as one quad (BVH's FlatQuad: a plane and two coordinates, bounded for
    # rounding), a kite's as triangles. Their hits are the triangles' (float64, brute force):
    # the distance, the primitive and its barycentrics away from the edges; the lanes' and
    # the traversal's bit for bit; the same rays as shadow rays blocked exactly where they
    # have a hit, in lanes and one at a time; and a pair that is no parallelogram is no quad.
    scene, tris = _quad_scene(tmp_path)
    assert scene._native.bvh_flat and scene._native.triangle_count == len(tris) == 18
    assert scene._native.bvh_quad_count >= 6
    kites = tr.load_dict({"type": "scene", **{f"k{i}": {"type": "obj", "filename": _obj_file(
        tmp_path / f"k{i}.obj", [[i, 0, 0], [i + 1, 0.1, 0], [i + 0.4, 1, 0.2], [i - 0.3, 0.2, 0.1]], [(0, 1, 2), (0, 2, 3)])}
        for i in range(2)}})
    assert kites._native.bvh_flat and kites._native.bvh_quad_count == 0
    rng = np.random.default_rng(15)
    n = 4000
    target = tris[rng.integers(0, len(tris), n)]
    w = rng.dirichlet([1, 1, 1], n)
    target = np.einsum("nk,nkj->nj", w, target)
    o = target + rng.normal(size=(n, 3)) * 3
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = [torch.from_numpy(a).float() for a in (o, d, np.zeros(n), np.full(n, np.inf))]
    lanes = tr._C.closest_hits(scene._native, *rays, True)
    for a, b in zip(lanes, tr._C.closest_hits(scene._native, *rays, False)):
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
    for columns in (True, False):
        assert torch.equal(tr._C.occluded_rays(scene._native, *rays, columns), lanes[1] >= 0)
    t, prim, u, v = (x.numpy() for x in lanes)
    # Brute force over the triangles, in float64 from the rays as given.
    o64, d64 = rays[0].double().numpy(), rays[1].double().numpy()
    t_ref, best, bu_best, bv_best, second = _brute_force_hits(tris, o64, d64)
    hit = np.isfinite(t_ref)
    assert hit.sum() > 3000
    np.testing.assert_array_equal(prim >= 0, hit)
    # (Within a few roundings of the scene's scale along the triangle's normal: a grazing
    # ray's t moves far along the plane.)
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    cos = np.abs(np.einsum("nj,nj->n", d64, normal[best]))
    np.testing.assert_array_less(np.abs(t - t_ref)[hit] * cos[hit], 1e-6 * (1 + t_ref[hit]))
    # Away from every edge (and the other hits), the same triangle and barycentrics.
    margin = np.minimum(np.minimum(bu_best, bv_best), 1 - bu_best - bv_best)
    clear = hit & (margin > 1e-4) & (second > t_ref * (1 + 1e-4))
    assert clear.sum() > 2500
    np.testing.assert_array_equal(prim[clear], best[clear])
    for mine, theirs in ((u, bu_best), (v, bv_best)):  # (grazing rays' as t's)
        np.testing.assert_array_less(np.abs(mine - theirs)[clear] * cos[clear], 2e-6 * (1 + t_ref[clear]))


@one_node_small_scene
def test16_quads_keep_rays_that_leave_them_and_are_watertight(tmp_path):
    # A ray leaving a quad from a point of it (in float: within a rounding of its plane, on
    # either side) must not hit it again: its test keeps a hit only beyond the bound on t's
    # rounding error. And rays at the quads' shared edges and corners (the cube's) hit.
    scene, tris = _quad_scene(tmp_path)
    cube = tris[:12]
    rng = np.random.default_rng(16)
    n = 6000
    face = rng.integers(0, 12, n)
    w = rng.dirichlet([1, 1, 1], n)
    points = np.einsum("nk,nkj->nj", w, cube[face]).astype(np.float32).astype(np.float64)
    normal = np.cross(cube[face, 1] - cube[face, 0], cube[face, 2] - cube[face, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    outward = np.sign(np.einsum("nj,nj->n", normal, points - cube.reshape(-1, 3).mean(axis=0)))[:, None] * normal
    d = rng.normal(size=(n, 3))
    d -= outward * np.minimum(np.einsum("nj,nj->n", d, outward), 0)[:, None] * 2  # (reflected outwards)
    d[: n // 3] = outward[: n // 3] + rng.normal(size=(n // 3, 3)) * 2  # (some grazing)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    leaving = np.einsum("nj,nj->n", d, outward) > 0
    rays = [torch.from_numpy(a).float() for a in (points, d, np.zeros(n), np.full(n, np.inf))]
    for columns in (True, False):
        t, prim, _, _ = tr._C.closest_hits(scene._native, *rays, columns)
        on_cube = (prim >= 0) & (prim < 12)
        assert not bool(on_cube[torch.from_numpy(leaving)].any()), int(on_cube[torch.from_numpy(leaving)].sum())
        # Into the cube: another face, never the one it starts on (triangles 2f and 2f + 1).
        inward = torch.from_numpy(~leaving)
        assert bool((on_cube[inward] & (prim[inward] // 2 != torch.from_numpy(face)[inward] // 2)).all())
    # The cube's corners and edges (the quads' shared boundaries), from inside and outside.
    corners = cube.reshape(-1, 3)
    edges = np.concatenate([(cube[:, a] + cube[:, b]) / 2 for a, b in ((0, 1), (1, 2), (2, 0))])
    targets = np.concatenate([corners, edges, corners + (edges[rng.integers(0, len(edges), len(corners))] - corners) * 0.37])
    # From inside, each ray hits the cube; from outside, something no farther than its target.
    for origin in ([0.1, -0.05, 0.02], [4.0, 3.0, -5.0], [-3.0, 0.5, 4.0]):
        o = np.repeat([origin], len(targets), axis=0)
        d = targets - o
        dist = np.linalg.norm(d, axis=1)
        rays = [torch.from_numpy(a).float() for a in (o, d / dist[:, None], np.zeros(len(o)), np.full(len(o), np.inf))]
        for columns in (True, False):
            t, prim, _, _ = tr._C.closest_hits(scene._native, *rays, columns)
            if origin[0] == 0.1:
                assert bool(((prim >= 0) & (prim < 12)).all()), int(((prim < 0) | (prim >= 12)).sum())
            else:
                assert bool(((prim.numpy() >= 0) & (t.double().numpy() <= dist * (1 + 1e-5))).all())


def _room_of_balls(n_balls):
    """_small_scene()'s cube, quad and decal with `n_balls` small spheres in a grid around
    them: a tree of several nodes (the spheres spread out)."""
    d = {"type": "scene",
         "box": {"type": "cube", "to_world": tr.Transform.translate([0.5, 0, 0]).scale(0.5)},
         "quad": {"type": "rectangle", "to_world": tr.Transform.translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(3)},
         "decal": {"type": "rectangle", "to_world": tr.Transform.translate([-1, -1, 1]).rotate([1, 0, 0], -90).scale(0.75)}}
    for i in range(n_balls):
        x, z = -2.5 + 5.0 * (i % 6) / 5, -2.5 + 5.0 * (i // 6) / 5
        d[f"ball{i}"] = {"type": "sphere", "center": [x, -0.7 + 0.1 * (i % 3), z], "radius": 0.3}
    return tr.load_dict(d)


@pytest.mark.skipif(tr._C.build_isa == "sse2", reason="with the 4-wide nodes of a PORTABLE=1 build the room's root "
                    "has leaves of triangles only, and the tree is searched in two phases (test10)")
def test17_small_trees_of_several_nodes_are_flat():
    # A few primitives in a tree of several nodes (16 triangles and 20 spheres: a room of
    # balls) are tested in lanes too (BVH::flat beyond one node, up to FlatSpheres spheres),
    # without quads (their boxes are widened in the root's leaves only): the closest hits and
    # the blocked rays are the traversal's bit for bit. With more spheres than FlatSpheres the
    # tree is traversed.
    scene = _room_of_balls(20)
    assert scene._native.bvh_node_count > 1 and scene._native.bvh_flat
    rng = np.random.default_rng(17)
    args = _small_scene_rays(rng)
    flat = tr._C.closest_hits(scene._native, *args, True)
    traversal = tr._C.closest_hits(scene._native, *args, False)
    assert int((traversal[1] >= 16).sum()) > 300 and int(((traversal[1] >= 0) & (traversal[1] < 16)).sum()) > 1000
    for a, b in zip(flat, traversal):
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
    # Shadow rays, and each ending a rounding before, at or after its nearest hit: where it
    # ends a rounding past a hit within a rounding of its leaf's box, the lanes may find the
    # hit that the traversal's box test leaves out (as test05's, on the decal).
    for scale, rays in _ending_near_hits(args, traversal[0]):
        blocked = tr._C.occluded_rays(scene._native, *rays, True)
        by_traversal = tr._C.occluded_rays(scene._native, *rays, False, traversal=True)
        if scale is None or scale <= 1:
            assert torch.equal(blocked, by_traversal)
        else:
            apart = blocked != by_traversal
            assert int(apart.sum()) <= 5 and bool(blocked[apart].all())
        assert int(blocked.sum()) > (1000 if scale is None or scale > 1 else -1)
    assert not _room_of_balls(33)._native.bvh_flat  # (FlatSpheres: 32)
