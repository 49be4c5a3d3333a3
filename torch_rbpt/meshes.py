"""Triangle meshes with Mitsuba 3 semantics: OBJ and PLY loaders, built-in shapes.

Everything here is plain numpy; the arrays are handed to the C++ side as they are.

Conventions (established against Mitsuba 3.9.1, see the notes on each function):

* OBJ: vertices are deduplicated by their ``(v, vt, vn)`` index triple and numbered in
  order of first use by a face corner; unreferenced ``v`` lines are dropped; polygons are
  triangulated as a fan ``(0, i, i + 1)``; the texture ``v`` coordinate is flipped
  (``v -> 1 - v``, Mitsuba's ``flip_tex_coords`` defaults to true for OBJ); file normals
  are normalized.
* PLY: vertices are kept as stored (including unreferenced ones), texture coordinates are
  *not* flipped (``flip_tex_coords`` defaults to false for PLY), file normals are
  normalized.
* Missing vertex normals are recomputed with Mitsuba's angle-weighted scheme (Thuermer and
  Wuethrich 1998), see :func:`compute_vertex_normals`. Mitsuba recomputes them *after*
  applying ``to_world``; :meth:`Mesh.transformed` does the same for meshes whose
  ``computed_normals`` flag is set.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

__all__ = [
    "MeshError",
    "Mesh",
    "compute_vertex_normals",
    "load_obj",
    "load_ply",
    "load_serialized",
    "write_serialized",
    "load_mesh",
    "rectangle",
    "cube",
]


class MeshError(ValueError):
    """A mesh file could not be read, or mesh arrays are inconsistent."""


# ---------------------------------------------------------------------------------------
# Mesh container
# ---------------------------------------------------------------------------------------


@dataclass(eq=False)
class Mesh:
    """An indexed triangle mesh.

    Attributes:
        positions: float32 array, shape (N, 3), C-contiguous.
        faces: int32 array, shape (M, 3), C-contiguous; vertex indices in [0, N). The
            winding defines the geometric normal ``cross(p1 - p0, p2 - p0)``.
        normals: float32 array, shape (N, 3), unit length, or None (face normals only,
            Mitsuba's ``face_normals=true``).
        uvs: float32 array, shape (N, 2), or None (no texture coordinates).
        computed_normals: True when ``normals`` were derived from the geometry (the file
            had none). :meth:`transformed` then recomputes them from the transformed
            positions, as Mitsuba does, instead of transforming them.

    The constructor converts array-likes to the dtypes above and raises :class:`MeshError`
    on wrong shapes or out-of-range face indices.
    """

    positions: np.ndarray
    faces: np.ndarray
    normals: Optional[np.ndarray] = None
    uvs: Optional[np.ndarray] = None
    computed_normals: bool = False
    #: Mitsuba's mesh attributes ("vertex_color": (N, C), "face_color": (M, C), float32).
    attributes: dict = None

    def __post_init__(self) -> None:
        self.positions = _as_array(self.positions, np.float32, 3, "positions")
        self.faces = _as_array(self.faces, np.int32, 3, "faces")
        n = self.positions.shape[0]
        if self.normals is not None:
            self.normals = _as_array(self.normals, np.float32, 3, "normals", rows=n)
        if self.uvs is not None:
            self.uvs = _as_array(self.uvs, np.float32, 2, "uvs", rows=n)
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= n):
            raise MeshError(
                f"face indices must lie in [0, {n}), got [{self.faces.min()}, "
                f"{self.faces.max()}]"
            )
        if self.normals is None:
            self.computed_normals = False
        self.attributes = dict(self.attributes or {})

    # -- sizes ---------------------------------------------------------------------------

    @property
    def vertex_count(self) -> int:
        """Number of vertices N."""
        return int(self.positions.shape[0])

    @property
    def face_count(self) -> int:
        """Number of triangles M."""
        return int(self.faces.shape[0])

    # -- geometry ------------------------------------------------------------------------

    def face_normals(self) -> np.ndarray:
        """Unit geometric normals from the winding, float32 array of shape (M, 3).

        Degenerate triangles get a zero vector.
        """
        cross = _face_cross(self.positions.astype(np.float64), self.faces)
        length = np.linalg.norm(cross, axis=1, keepdims=True)
        return np.divide(cross, length, out=np.zeros_like(cross), where=length > 0).astype(
            np.float32
        )

    def face_areas(self) -> np.ndarray:
        """Triangle areas, float64 array of shape (M,)."""
        cross = _face_cross(self.positions.astype(np.float64), self.faces)
        return 0.5 * np.linalg.norm(cross, axis=1)

    def area(self) -> float:
        """Total surface area (sum of the triangle areas), as a Python float."""
        return float(self.face_areas().sum())

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds: (min, max), each float32 array of shape (3,)."""
        if self.vertex_count == 0:
            raise MeshError("bbox() of a mesh without vertices")
        return self.positions.min(axis=0), self.positions.max(axis=0)

    # -- derived meshes ------------------------------------------------------------------

    def transformed(self, matrix: np.ndarray) -> "Mesh":
        """This mesh under an affine object-to-world transform, like Mitsuba's ``to_world``.

        Args:
            matrix: array-like of shape (4, 4), row-major, acting on column vectors
                ``[x, y, z, 1]``; the last row must be ``[0, 0, 0, 1]``.

        Returns:
            A new mesh. Positions are mapped by the affine matrix; faces (the winding) and
            uvs are unchanged. Normals read from a file are mapped by the inverse transpose
            of the linear 3x3 part and renormalized; normals that were computed
            (``computed_normals``) are recomputed from the new positions, as Mitsuba
            computes them after applying ``to_world``.

        Mirroring (det < 0), as in Mitsuba: the winding is kept, so the geometric normal
        turns to the other side of the surface; file normals (and the built-in
        ``rectangle``/``cube`` normals) keep pointing the way the inverse transpose sends
        them, i.e. they then disagree with the geometric normal; computed normals follow
        the winding (they agree with the geometric normal).

        Raises:
            MeshError: if the matrix has the wrong shape, is not affine, is not finite or
                its linear part is singular.
        """
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4):
            raise MeshError(f"transformed(): expected a (4, 4) matrix, got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise MeshError("transformed(): matrix has non-finite entries")
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-6):
            raise MeshError(f"transformed(): last row must be [0, 0, 0, 1], got {m[3]}")
        linear = m[:3, :3]
        positions = _transform_points_like_mitsuba(self.positions, m)
        normals = None
        if self.normals is not None:
            if self.computed_normals:  # from the float32 positions, as Mitsuba
                normals = compute_vertex_normals(positions, self.faces)
            else:
                if abs(np.linalg.det(linear)) < 1e-300:
                    raise MeshError("transformed(): the matrix's 3x3 part is singular")
                inv_t = np.linalg.inv(linear).T
                normals = _normalize_rows(self.normals.astype(np.float64) @ inv_t.T)
        return Mesh(
            positions=positions,
            faces=self.faces.copy(),
            normals=normals,
            uvs=None if self.uvs is None else self.uvs.copy(),
            computed_normals=self.computed_normals,
            attributes=self.attributes,
        )

    def flipped(self) -> "Mesh":
        """This mesh with the other side facing out: Mitsuba's ``flip_normals``.

        Mitsuba's ``flip_normals`` keeps the buffers and negates both the geometric and
        the shading normal at every intersection. This returns the equivalent mesh: the
        winding is reversed (faces ``(a, b, c) -> (a, c, b)``) and vertex normals are
        negated; positions and uvs are unchanged, so interpolated uvs are the same.
        One difference remains for meshes *without* uvs: Mitsuba's barycentric surface
        parameterization ``(u, v) = (b1, b2)`` has u and v swapped here. For exact parity
        the renderer should apply flip_normals as a sign instead.
        """
        return Mesh(
            positions=self.positions.copy(),
            faces=np.ascontiguousarray(self.faces[:, [0, 2, 1]]),
            normals=None if self.normals is None else -self.normals,
            uvs=None if self.uvs is None else self.uvs.copy(),
            computed_normals=self.computed_normals,
            attributes=self.attributes,
        )

    def without_normals(self) -> "Mesh":
        """This mesh with ``normals=None`` (Mitsuba's ``face_normals=true``)."""
        return Mesh(self.positions.copy(), self.faces.copy(), None,
                    None if self.uvs is None else self.uvs.copy(), attributes=self.attributes)


def _transform_points_like_mitsuba(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Affine transform of float32 points (K, 3) by a (4, 4) matrix, float32 result.

    Reproduces Mitsuba's scalar ``transform_affine`` bit for bit: with the matrix in
    float32, ``r = t; r = fma(col0, x, r); r = fma(col1, y, r); r = fma(col2, z, r)``,
    each fused multiply-add rounded once to float32 (emulated in float64, where the
    float32 product is exact).
    """
    m = np.asarray(matrix, dtype=np.float32).astype(np.float64)
    p = np.asarray(points, dtype=np.float32).astype(np.float64)
    result = np.broadcast_to(m[:3, 3], p.shape)
    for k in range(3):
        result = (m[:3, k] * p[:, k:k + 1] + result).astype(np.float32).astype(np.float64)
    return result.astype(np.float32)


def _as_array(value, dtype, cols: int, name: str, rows: Optional[int] = None) -> np.ndarray:
    """Convert ``value`` to a C-contiguous ``dtype`` array of shape (rows, cols)."""
    try:
        arr = np.asarray(value)
    except Exception as exc:  # pragma: no cover - exotic inputs
        raise MeshError(f"{name}: cannot convert to an array ({exc})") from exc
    if arr.ndim != 2 or arr.shape[1] != cols or (rows is not None and arr.shape[0] != rows):
        want = f"({rows if rows is not None else 'K'}, {cols})"
        raise MeshError(f"{name}: expected shape {want}, got {arr.shape}")
    if np.issubdtype(dtype, np.integer) and arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise MeshError(f"{name}: expected integer indices, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=dtype)


def _face_cross(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unnormalized face normals ``cross(p1 - p0, p2 - p0)``, shape (M, 3)."""
    p0 = positions[faces[:, 0]]
    return np.cross(positions[faces[:, 1]] - p0, positions[faces[:, 2]] - p0)


def _normalize_rows(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (K, 3) scaled to unit length; zero rows stay zero."""
    length = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, length, out=np.zeros_like(v), where=length > 0)


def _unit_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors (rows of a and b, shape (K, 3)), stable near 0 and pi.

    Same formula as Mitsuba's ``unit_angle``.
    """
    dot = np.einsum("ij,ij->i", a, b)
    near = 2.0 * np.arcsin(np.minimum(np.linalg.norm(a - b, axis=1) * 0.5, 1.0))
    far = np.pi - 2.0 * np.arcsin(np.minimum(np.linalg.norm(a + b, axis=1) * 0.5, 1.0))
    return np.where(dot >= 0.0, near, far)


def compute_vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Mitsuba 3's ``Mesh::recompute_vertex_normals`` (angle-weighted vertex normals).

    Each triangle adds its unit geometric normal ``normalize(cross(p1 - p0, p2 - p0))``
    times its interior angle at the vertex (Thuermer and Wuethrich, JGT 1998) to each of
    its three vertices; degenerate (zero-area) triangles add nothing; sums are normalized.
    Vertices whose sum is zero (unreferenced, or only on degenerate triangles) get
    ``(1, 0, 0)``, Mitsuba's placeholder.

    Args:
        positions: float array, shape (N, 3).
        faces: integer array, shape (M, 3), indices in [0, N).

    Returns:
        float32 array, shape (N, 3), unit rows.
    """
    p = np.asarray(positions, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n_vertices = p.shape[0]
    v = [p[f[:, 0]], p[f[:, 1]], p[f[:, 2]]]
    face_n = np.cross(v[1] - v[0], v[2] - v[0])
    length = np.linalg.norm(face_n, axis=1)
    valid = length > 0
    face_n = face_n[valid] / length[valid, None]
    v = [x[valid] for x in v]
    f = f[valid]
    accum = np.zeros((n_vertices, 3), dtype=np.float64)
    for i in range(3):
        d0 = _normalize_rows(v[(i + 1) % 3] - v[i])
        d1 = _normalize_rows(v[(i + 2) % 3] - v[i])
        weighted = face_n * _unit_angle(d0, d1)[:, None]
        for axis in range(3):
            accum[:, axis] += np.bincount(f[:, i], weights=weighted[:, axis],
                                          minlength=n_vertices)
    length = np.linalg.norm(accum, axis=1)
    out = np.empty_like(accum)
    good = length > 0
    out[good] = accum[good] / length[good, None]
    out[~good] = (1.0, 0.0, 0.0)
    return out.astype(np.float32)


def _fan_triangles(counts: np.ndarray) -> np.ndarray:
    """Fan triangulation of consecutive polygons.

    Args:
        counts: int array (F,), corners per polygon, each >= 3; polygon k owns the corners
            ``starts[k] .. starts[k] + counts[k] - 1`` of one flat corner array.

    Returns:
        int64 array (sum(counts - 2), 3) of corner indices: triangles
        ``(s, s + j, s + j + 1)`` for ``j = 1 .. count - 2``, polygon by polygon.
    """
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    n_tri = counts - 2
    first_tri = np.concatenate(([0], np.cumsum(n_tri)[:-1]))
    owner = np.repeat(np.arange(len(counts)), n_tri)
    j = np.arange(int(n_tri.sum()), dtype=np.int64) - first_tri[owner] + 1
    s = starts[owner]
    return np.stack([s, s + j, s + j + 1], axis=1)


def _finish(path: Path, positions, faces, normals, uvs, face_normals: bool) -> Mesh:
    """Assemble the loaded arrays into a Mesh with Mitsuba's normal handling.

    ``normals`` holds file normals (N, 3) with NaN rows for vertices that have none, or is
    None when the file has no normals at all.
    """
    if faces.shape[0] == 0:
        raise MeshError(f"{path}: mesh has no faces")
    if face_normals:
        return Mesh(positions, faces, None, uvs)
    if normals is None:
        return Mesh(positions, faces, compute_vertex_normals(positions, faces), uvs,
                    computed_normals=True)
    normals = _normalize_rows(np.asarray(normals, dtype=np.float64))
    missing = ~np.all(np.isfinite(normals), axis=1) | (np.abs(normals).sum(axis=1) == 0)
    if missing.any():
        # Undefined in Mitsuba (uninitialized memory / NaN): use computed normals there.
        normals[missing] = compute_vertex_normals(positions, faces)[missing]
    return Mesh(positions, faces, normals, uvs)


def _read_bytes(path: Path, kind: str) -> bytes:
    """Whole file content, or MeshError naming the file."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise MeshError(f"{path}: {kind} file not found") from None
    except OSError as exc:
        raise MeshError(f"{path}: cannot read {kind} file ({exc.strerror})") from exc


# ---------------------------------------------------------------------------------------
# OBJ
# ---------------------------------------------------------------------------------------


def load_obj(path, face_normals: bool = False, flip_tex_coords: bool = True) -> Mesh:
    """Load a Wavefront OBJ file the way Mitsuba 3's ``obj`` plugin does.

    Supported: ``v x y z`` (extra values such as w or colors are ignored), ``vt u v``
    (extra values ignored), ``vn x y z``, and faces ``f c1 c2 c3 ...`` whose corners are
    ``v``, ``v/t``, ``v//n`` or ``v/t/n``; indices start at 1, negative indices count back
    from the last element defined before the face line (Mitsuba 3.9 rejects these; we
    accept them). All other statements (``o``, ``g``, ``s``, ``usemtl``, ``mtllib``, ``l``,
    comments, ...) are ignored.

    Mitsuba semantics:
      * a vertex is created for each distinct ``(v, vt, vn)`` triple, numbered by first use
        in the face corners; ``v`` lines no face refers to are dropped;
      * polygons are triangulated as a fan ``(c1, ci, ci+1)``;
      * texture coordinates are flipped vertically, ``uv = (u, 1 - v)``, unless
        ``flip_tex_coords=False`` (Mitsuba's OBJ property of that name, default true);
      * file normals are normalized; without any ``vn`` references normals are recomputed
        (:func:`compute_vertex_normals`, ``computed_normals=True``);
      * ``face_normals=True`` drops the normals (``normals=None``).
    Where Mitsuba's result is undefined (a corner without ``vt``/``vn`` in a file where
    other corners have them: Mitsuba leaves that memory uninitialized) we use uv ``(0, 0)``
    and the computed normal.

    Args:
        path: file path (str or Path).
        face_normals: drop vertex normals.
        flip_tex_coords: store ``1 - v`` (Mitsuba's OBJ default, true).

    Returns:
        A :class:`Mesh` in object space.

    Raises:
        MeshError: naming the file (and line) for a missing file, a malformed number, a
            bad or zero index, a face with fewer than 3 corners, or a mesh without faces.
    """
    path = Path(path)
    data = _read_bytes(path, "OBJ")
    records = _split_obj_records(data)
    positions = _parse_obj_floats(path, records["v"], 3, "v")
    texcoords = _parse_obj_floats(path, records["vt"], 2, "vt")
    normals = _parse_obj_floats(path, records["vn"], 3, "vn")
    if not np.all(np.isfinite(positions)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(positions), axis=1))[0])
        raise MeshError(f"{path}, line {records['v'][1][bad]}: non-finite vertex position")

    f_rows, f_lines = records["f"]
    if not f_rows:
        raise MeshError(f"{path}: mesh has no faces ('f' lines)")
    counts, raw = _parse_obj_faces(path, f_rows, f_lines)
    corner_lines = np.repeat(np.asarray(f_lines, dtype=np.int64), counts)
    resolved = [
        _resolve_obj_indices(path, raw[:, k], corner_lines, np.asarray(records[key][1]), what)
        for k, (key, what) in enumerate((("v", "vertex"), ("vt", "texture coordinate"),
                                         ("vn", "normal")))
    ]
    if flip_tex_coords:
        texcoords[:, 1] = np.float32(1.0) - texcoords[:, 1]  # float32 arithmetic, as Mitsuba
    return _assemble_obj(path, counts, resolved, positions, texcoords, normals, face_normals)


def _split_obj_records(data: bytes) -> dict:
    """Group the whitespace-split lines of an OBJ file by statement.

    Returns:
        dict mapping ``"v"``, ``"vt"``, ``"vn"``, ``"f"`` to ``(rows, line_numbers)``: rows
        are the token lists (bytes, statement keyword included), line numbers 1-based ints.
    """
    out = {b"v": ([], []), b"vt": ([], []), b"vn": ([], []), b"f": ([], [])}
    get = out.get
    for lineno, line in enumerate(data.split(b"\n"), 1):
        parts = line.split()
        if parts:
            slot = get(parts[0])
            if slot is not None:
                slot[0].append(parts)
                slot[1].append(lineno)
    return {k.decode(): v for k, v in out.items()}


def _parse_obj_floats(path: Path, record, width: int, keyword: str) -> np.ndarray:
    """The first ``width`` numbers of each ``keyword`` line as float32 (K, width)."""
    rows, lines = record
    if not rows:
        return np.zeros((0, width), dtype=np.float32)
    lengths = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
    short = np.flatnonzero(lengths < width + 1)
    if short.size:
        i = int(short[0])
        raise MeshError(f"{path}, line {lines[i]}: expected {width} numbers after '{keyword}', "
                        f"got {lengths[i] - 1}")
    flat = [tok for row in rows for tok in row[1:width + 1]]
    try:
        return np.array(flat).astype(np.float32).reshape(-1, width)
    except ValueError:
        pass
    for row, lineno in zip(rows, lines):
        for tok in row[1:width + 1]:
            try:
                float(tok)
            except ValueError:
                text = tok.decode(errors="replace")
                raise MeshError(f"{path}, line {lineno}: malformed number {text!r} in "
                                f"'{keyword}' line") from None
    raise MeshError(f"{path}: malformed '{keyword}' data")  # pragma: no cover


_CORNER_PATTERNS = {
    # (slashes per corner, double slashes per corner) -> (separator, fields present)
    (0, 0): (None, (0,)),
    (1, 0): (b"/", (0, 1)),
    (2, 1): (b"//", (0, 2)),
    (2, 0): (b"/", (0, 1, 2)),
}


def _parse_obj_faces(path: Path, f_rows, f_lines):
    """Parse face corners.

    Returns:
        counts: int64 (F,), corners per face (each >= 3).
        raw: int64 (C, 3), the signed OBJ indices (v, vt, vn) of every corner in file
            order; 0 marks an absent vt/vn (a literal 0 index is rejected here).
    """
    counts = np.fromiter(map(len, f_rows), dtype=np.int64, count=len(f_rows)) - 1
    small = np.flatnonzero(counts < 3)
    if small.size:
        i = int(small[0])
        raise MeshError(f"{path}, line {f_lines[i]}: face has {counts[i]} vertices, expected at "
                        f"least 3")
    tokens = [tok for row in f_rows for tok in row[1:]]
    raw = _parse_corners_fast(tokens)
    if raw is None:
        raw = _parse_corners_slow(path, f_rows, f_lines)
    zero = np.flatnonzero(raw[:, 0] == 0)
    if zero.size:
        line = int(np.repeat(np.asarray(f_lines), counts)[zero[0]])
        raise MeshError(f"{path}, line {line}: vertex index 0 is invalid (OBJ indices start at 1)")
    return counts, raw


def _parse_corners_fast(tokens) -> Optional[np.ndarray]:
    """Vectorized corner parsing when every corner has the same form; else None."""
    arr = np.array(tokens)
    slashes = np.strings.count(arr, b"/")
    doubles = np.strings.count(arr, b"//")
    key = (int(slashes[0]), int(doubles[0]))
    if key not in _CORNER_PATTERNS or np.any(slashes != key[0]) or np.any(doubles != key[1]):
        return None
    sep, fields = _CORNER_PATTERNS[key]
    joined = b" ".join(tokens)
    if sep is not None:
        joined = joined.replace(sep, b" ")
    values = _parse_ints(joined)
    if values is None or values.size != len(tokens) * len(fields):
        return None
    values = values.reshape(len(tokens), len(fields))
    if np.any(values[:, 1:] == 0):
        return None  # explicit 0 for vt/vn: let the slow path report it
    raw = np.zeros((len(tokens), 3), dtype=np.int64)
    raw[:, list(fields)] = values
    return raw


def _parse_ints(text: bytes) -> Optional[np.ndarray]:
    """Whitespace-separated decimal integers -> int64 (K,), or None if any is malformed."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warns (instead of failing) on bad data
        try:
            return np.fromstring(text, dtype=np.int64, sep=" ")
        except (ValueError, DeprecationWarning):
            return None


def _parse_corners_slow(path: Path, f_rows, f_lines) -> np.ndarray:
    """Corner-by-corner parsing with precise errors; same result as the fast path."""
    out = []
    for row, lineno in zip(f_rows, f_lines):
        for tok in row[1:]:
            out.append(_parse_corner(path, tok, lineno))
    return np.array(out, dtype=np.int64).reshape(-1, 3)


def _parse_corner(path: Path, tok: bytes, lineno: int) -> tuple:
    """One ``v[/t][/n]`` corner -> (v, t, n) with 0 for absent fields."""
    fields = tok.split(b"/")
    text = tok.decode(errors="replace")
    if len(fields) > 3 or fields[0] == b"" or (len(fields) == 3 and fields[2] == b""):
        raise MeshError(f"{path}, line {lineno}: malformed face corner {text!r}, expected "
                        f"v, v/t, v//n or v/t/n")
    values = [0, 0, 0]
    for k, field in enumerate(fields):
        if field == b"" and k == 1:
            continue
        try:
            values[k] = int(field)
        except ValueError:
            bad = field.decode(errors="replace")
            raise MeshError(f"{path}, line {lineno}: malformed index {bad!r} in face corner "
                            f"{text!r}") from None
        if not -2 ** 62 < values[k] < 2 ** 62:
            raise MeshError(f"{path}, line {lineno}: index {values[k]} in face corner {text!r} is "
                            f"out of range")
        if values[k] == 0:
            raise MeshError(f"{path}, line {lineno}: index 0 in face corner {text!r} is invalid "
                            f"(OBJ indices start at 1)")
    if len(fields) == 2 and fields[1] == b"":
        raise MeshError(f"{path}, line {lineno}: malformed face corner {text!r}, expected "
                        f"v, v/t, v//n or v/t/n")
    return tuple(values)


def _resolve_obj_indices(path: Path, raw: np.ndarray, corner_lines: np.ndarray,
                         element_lines: np.ndarray, what: str) -> np.ndarray:
    """Turn signed 1-based OBJ indices into 0-based ones; -1 where absent (raw == 0).

    Positive indices may refer to any element of the file; negative ones count back from
    the elements defined before the corner's line.
    """
    total = len(element_lines)
    out = raw - 1
    neg = raw < 0
    if neg.any():
        before = np.searchsorted(element_lines, corner_lines[neg])
        out[neg] = before + raw[neg]
    absent = raw == 0
    out[absent] = -1
    bad = (~absent) & ((out < 0) | (out >= total))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        if raw[i] < 0:
            before = int(np.searchsorted(element_lines, corner_lines[i]))
            detail = f"{before} defined before this line"
        else:
            detail = f"the file has {total}"
        raise MeshError(f"{path}, line {corner_lines[i]}: {what} index {raw[i]} is out of range "
                        f"({detail})")
    return out


def _assemble_obj(path: Path, counts, resolved, positions, texcoords, normals,
                  face_normals: bool) -> Mesh:
    """Deduplicate (v, vt, vn) triples in first-use order and build the mesh."""
    v_idx, t_idx, n_idx = resolved
    n_t, n_n = texcoords.shape[0] + 1, normals.shape[0] + 1
    if positions.shape[0] * n_t * n_n < 2**62:
        keys = (v_idx * n_t + (t_idx + 1)) * n_n + (n_idx + 1)
        _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    else:  # pragma: no cover - astronomically large files
        _, first, inverse = np.unique(np.stack([v_idx, t_idx, n_idx], 1), axis=0,
                                      return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    vertex_of_corner = rank[inverse]
    rep = first[order]  # representative corner of each new vertex, in vertex order

    faces = vertex_of_corner[_fan_triangles(counts)]
    out_pos = positions[v_idx[rep]]
    uvs = None
    if np.any(t_idx >= 0):
        t = t_idx[rep]
        uvs = np.zeros((rep.size, 2), dtype=np.float32)
        uvs[t >= 0] = texcoords[t[t >= 0]]
    out_n = None
    if not face_normals and np.any(n_idx >= 0):
        n = n_idx[rep]
        out_n = np.full((rep.size, 3), np.nan)
        out_n[n >= 0] = normals[n[n >= 0]]
    return _finish(path, out_pos, faces, out_n, uvs, face_normals)


# ---------------------------------------------------------------------------------------
# PLY
# ---------------------------------------------------------------------------------------

# Texture coordinate property pairs, in the order Mitsuba 3.9 looks for them.
# ("texture_s", "texture_t") is deliberately absent: Mitsuba 3.9.1 ignores it.
PLY_UV_NAMES = (("u", "v"), ("texture_u", "texture_v"), ("s", "t"))
# Colour property names of vertices and faces (Mitsuba's vertex_color / face_color).
PLY_COLOR_NAMES = (("r", "g", "b"), ("red", "green", "blue"))
# Face index list names, in the order Mitsuba looks for them.
PLY_FACE_LIST_NAMES = ("vertex_index", "vertex_indices")


def load_ply(path, face_normals: bool = False, flip_tex_coords: bool = False) -> Mesh:
    """Load a Stanford PLY file (ascii, binary little or big endian) like Mitsuba 3.

    Reads the ``vertex`` element (``x, y, z``; optional ``nx, ny, nz``; optional texture
    coordinates ``u, v`` or ``texture_u, texture_v`` or ``s, t``, the first pair found) and
    the ``face`` element (list ``vertex_index`` or ``vertex_indices``). Other elements and
    properties are ignored.

    Mitsuba semantics: vertices are kept in file order (unreferenced ones too, with the
    normal ``(1, 0, 0)`` when normals are computed); texture coordinates are *not* flipped
    unless ``flip_tex_coords=True`` (Mitsuba's PLY property, default false, unlike OBJ);
    file normals are normalized; without normals they are recomputed
    (:func:`compute_vertex_normals`, ``computed_normals=True``); ``face_normals=True`` drops
    them. Polygons are triangulated as a fan (Mitsuba 3.9 rejects non-triangles; we accept
    them).

    Args:
        path: file path (str or Path).
        face_normals: drop vertex normals.
        flip_tex_coords: store ``1 - v`` (Mitsuba's PLY default: false).

    Returns:
        A :class:`Mesh` in object space.

    Raises:
        MeshError: naming the file (and the line for header errors and ascii data) for a
            missing file, a malformed header or body, missing properties, faces with fewer
            than 3 vertices, out-of-range indices or a mesh without faces.
    """
    path = Path(path)
    if not path.exists():
        raise MeshError(f"{path}: PLY file not found")
    ply = _read_plyfile(path)
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise MeshError(f"{path}: no 'vertex' element (elements: {names})")
    if "face" not in names:
        raise MeshError(f"{path}: no 'face' element (elements: {names})")
    vertex = ply["vertex"]
    positions = _ply_columns(path, vertex, ("x", "y", "z"), required=True)
    normals = None if face_normals else _ply_columns(path, vertex, ("nx", "ny", "nz"))
    uvs = None
    for pair in PLY_UV_NAMES:
        uvs = _ply_columns(path, vertex, pair)
        if uvs is not None:
            break
    if uvs is not None and flip_tex_coords:
        uvs[:, 1] = np.float32(1.0) - uvs[:, 1]
    faces, face_of_triangle = _ply_faces(path, ply, positions.shape[0])
    if not np.all(np.isfinite(positions)):
        raise MeshError(f"{path}: vertex positions contain non-finite values")
    mesh = _finish(path, positions, faces, normals, uvs, face_normals)
    # Colours as Mitsuba's mesh attributes: (r, g, b) or (red, green, blue), plus alpha, as
    # stored (8-bit values are not normalized; Mitsuba warns and keeps them).
    for element, attribute in (("vertex", "vertex_color"), ("face", "face_color")):
        for names in PLY_COLOR_NAMES:
            cols = _ply_columns(path, ply[element], names)
            if cols is not None:
                alpha = _ply_columns(path, ply[element], ("alpha",))
                if alpha is not None:
                    cols = np.hstack([cols, alpha])
                mesh.attributes[attribute] = cols if element == "vertex" else cols[face_of_triangle]
                break
    return mesh


def _read_plyfile(path: Path):
    """Parse with plyfile; triangle lists of binary files are memory-mapped (fast path)."""
    try:
        import plyfile
    except ImportError as exc:  # pragma: no cover - dependency missing
        raise MeshError(f"{path}: reading PLY needs the 'plyfile' package") from exc
    fast = {"face": {name: 3 for name in PLY_FACE_LIST_NAMES}}
    try:
        try:
            return plyfile.PlyData.read(str(path), known_list_len=fast)
        except plyfile.PlyElementParseError as exc:
            if "unexpected list length" not in str(exc):
                raise
            return plyfile.PlyData.read(str(path))  # polygons: general (slow) reader
    except plyfile.PlyHeaderParseError as exc:
        raise MeshError(f"{path}, line {exc.line}: invalid PLY header: {exc.message}") from None
    except plyfile.PlyElementParseError as exc:
        raise MeshError(f"{path}{_ply_data_location(path, exc)}: {exc.message}") from None
    except (ValueError, TypeError, OSError, OverflowError) as exc:
        raise MeshError(f"{path}: cannot parse PLY file ({exc})") from None


def _ply_data_location(path: Path, exc) -> str:
    """Where a plyfile body error happened, to append to the path:
    ``", line L (element 'face' row R ...)"`` for ascii files (line 1-based, one element
    row per line as plyfile reads them), ``", element 'face' row R ..."`` for binary ones
    (rows 0-based)."""
    where = f", element '{exc.element.name}' row {exc.row}"
    if exc.prop is not None:
        where += f" property '{exc.prop.name}'"
    try:
        import plyfile
        with open(path, "rb") as stream:
            header = plyfile.PlyData._parse_header(stream)
            head = stream.tell()
            stream.seek(0)
            header_lines = stream.read(head).count(b"\n")
    except Exception:  # pragma: no cover - the header was already parsed once
        return where
    if not header.text or exc.row is None:
        return where
    before = 0
    for el in header.elements:
        if el.name == exc.element.name:
            break
        before += el.count
    return f", line {header_lines + before + exc.row + 1} ({where[2:]})"


def _ply_columns(path: Path, element, names: Sequence[str], required: bool = False):
    """Stack scalar properties of a PLY element into float32 (K, len(names)), or None."""
    present = {p.name for p in element.properties}
    if not all(name in present for name in names):
        if required:
            raise MeshError(f"{path}: element '{element.name}' lacks properties "
                            f"{', '.join(n for n in names if n not in present)} "
                            f"(expected {', '.join(names)})")
        return None
    columns = []
    for name in names:
        col = element[name]
        if col.dtype == object:
            raise MeshError(f"{path}: property '{name}' of element '{element.name}' is a "
                            f"list, expected a scalar")
        columns.append(np.asarray(col, dtype=np.float32))
    return np.stack(columns, axis=1)


def _ply_faces(path: Path, ply, n_vertices: int):
    """Face index lists of a PLY file -> int32 triangles (M, 3), fan-triangulated, and the
    index of the face each triangle comes from."""
    face = ply["face"]
    present = {p.name for p in face.properties}
    name = next((n for n in PLY_FACE_LIST_NAMES if n in present), None)
    if name is None:
        raise MeshError(f"{path}: element 'face' has no 'vertex_index' or 'vertex_indices' "
                        f"list (properties: {sorted(present)})")
    lists = face[name]
    face_of_triangle = np.arange(len(lists))
    if lists.dtype != object and lists.ndim == 2:  # memory-mapped triangles
        tris = np.asarray(lists, dtype=np.int64)
    elif lists.dtype != object:
        raise MeshError(f"{path}: property '{name}' of element 'face' is a scalar, expected a "
                        f"list of vertex indices")
    else:
        counts = np.fromiter(map(len, lists), dtype=np.int64, count=len(lists))
        small = np.flatnonzero(counts < 3)
        if small.size:
            i = int(small[0])
            raise MeshError(f"{path}: face {i} has {counts[i]} vertices, expected at least 3")
        flat = (np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])
                if len(lists) else np.zeros(0, dtype=np.int64))
        tris = flat[_fan_triangles(counts)] if len(lists) else np.zeros((0, 3), np.int64)
        face_of_triangle = np.repeat(face_of_triangle, counts - 2)
    if tris.size and (tris.min() < 0 or tris.max() >= n_vertices):
        bad = int(np.flatnonzero(np.any((tris < 0) | (tris >= n_vertices), axis=1))[0])
        raise MeshError(f"{path}: triangle {bad} has vertex indices {tris[bad].tolist()}, "
                        f"expected indices in [0, {n_vertices})")
    return tris.astype(np.int32), face_of_triangle


# ---------------------------------------------------------------------------------------
# Mitsuba's serialized format
# ---------------------------------------------------------------------------------------

SERIALIZED_MAGIC = 0x041C
# Flags of a serialized mesh (Mitsuba's TriMeshFlags).
_SER_NORMALS, _SER_TEXCOORDS, _SER_COLORS, _SER_DOUBLE = 0x0001, 0x0002, 0x0008, 0x2000


def load_serialized(path, shape_index: int = 0, face_normals: bool = False) -> Mesh:
    """Load mesh `shape_index` of a Mitsuba ``.serialized`` file (format versions 3 and 4).

    The format (little endian): per mesh, an uncompressed header ``uint16 0x041C, uint16
    version``, then a zlib stream holding ``uint32 flags``, (version 4) a null-terminated
    name, ``uint64`` vertex and triangle counts, positions, normals (flag 0x1), texture
    coordinates (0x2), vertex colours (0x8), all float32 or float64 (0x2000), and ``uint32``
    triangle indices. The file ends with the byte offset of each mesh (``uint64``, version 3:
    ``uint32``) and the ``uint32`` mesh count.

    Mitsuba 3.9.1 semantics (tests/references/MITSUBA_FACTS.md): double values are rounded
    to float32; file normals are normalized, missing ones computed (angle-weighted) after
    ``to_world``; texture coordinates are not flipped; vertex colours and the file's
    face-normals flag (0x10) are ignored (only the ``face_normals`` parameter counts).

    Raises:
        MeshError: naming the file for a missing file, a wrong header or version, a shape
            index out of range, a truncated or corrupt stream, or invalid indices.
    """
    import struct
    import zlib

    path = Path(path)
    data = _read_bytes(path, "serialized")
    if len(data) < 8:
        raise MeshError(f"{path}: not a Mitsuba serialized file (only {len(data)} bytes)")
    magic, version = struct.unpack_from("<HH", data, 0)
    if magic != SERIALIZED_MAGIC:
        raise MeshError(f"{path}: not a Mitsuba serialized file (header 0x{magic:04x}, "
                        f"expected 0x041c)")
    if version not in (3, 4):
        raise MeshError(f"{path}: serialized format version {version} is not supported "
                        f"(versions 3 and 4 are)")
    count = struct.unpack_from("<I", data, len(data) - 4)[0]
    if not 0 <= shape_index < max(count, 1):
        raise MeshError(f"{path}: shape_index {shape_index} is out of range (the file holds "
                        f"{count} mesh{'es' if count != 1 else ''})")
    offset = 0
    if shape_index > 0:
        size = 8 if version == 4 else 4
        at = len(data) - 4 - size * (count - shape_index)
        offset = struct.unpack_from("<Q" if version == 4 else "<I", data, at)[0]
        if offset + 4 > len(data) or struct.unpack_from("<HH", data, offset) != (magic, version):
            raise MeshError(f"{path}: the offset of mesh {shape_index} ({offset}) does not "
                            f"point to a mesh header")
    try:
        body = zlib.decompressobj().decompress(data[offset + 4:])
    except zlib.error as exc:
        raise MeshError(f"{path}: mesh {shape_index}: corrupt zlib stream ({exc})") from None

    pos = 0

    def take(n: int, what: str) -> bytes:
        nonlocal pos
        if pos + n > len(body):
            raise MeshError(f"{path}: mesh {shape_index} is truncated (reading {what})")
        pos += n
        return body[pos - n:pos]

    flags = struct.unpack("<I", take(4, "flags"))[0]
    if version == 4:
        end = body.find(b"\0", pos)
        if end < 0:
            raise MeshError(f"{path}: mesh {shape_index} is truncated (reading its name)")
        pos = end + 1
    n_vertices, n_faces = struct.unpack("<QQ", take(16, "counts"))
    if n_vertices > len(body) or n_faces > len(body):  # each needs at least a byte
        raise MeshError(f"{path}: mesh {shape_index} declares {n_vertices} vertices and "
                        f"{n_faces} triangles, more than the stream holds")
    dtype = np.dtype("<f8" if flags & _SER_DOUBLE else "<f4")

    def floats(dim: int, what: str) -> np.ndarray:
        raw = take(n_vertices * dim * dtype.itemsize, what)
        return np.frombuffer(raw, dtype=dtype).reshape(n_vertices, dim).astype(np.float32)

    positions = floats(3, "positions")
    normals = floats(3, "normals") if flags & _SER_NORMALS else None
    uvs = floats(2, "texture coordinates") if flags & _SER_TEXCOORDS else None
    if flags & _SER_COLORS:
        floats(3, "vertex colors")  # skipped, as Mitsuba does
    faces = np.frombuffer(take(n_faces * 12, "triangles"), dtype="<u4").reshape(n_faces, 3)
    faces = faces.astype(np.int64)
    if faces.size and faces.max() >= n_vertices:
        bad = int(np.flatnonzero(np.any(faces >= n_vertices, axis=1))[0])
        raise MeshError(f"{path}: mesh {shape_index}: triangle {bad} has vertex indices "
                        f"{faces[bad].tolist()}, expected indices in [0, {n_vertices})")
    if not np.all(np.isfinite(positions)):
        raise MeshError(f"{path}: mesh {shape_index}: vertex positions contain non-finite values")
    return _finish(path, positions, faces.astype(np.int32),
                   None if face_normals else normals, uvs, face_normals)


def write_serialized(path, meshes: Sequence[dict], version: int = 4, double: bool = False) -> None:
    """Write meshes in Mitsuba's ``.serialized`` format (see :func:`load_serialized`).

    Each mesh is a dict with ``positions`` (N, 3), ``faces`` (M, 3) and optionally
    ``normals`` (N, 3), ``uvs`` (N, 2), ``colors`` (N, 3), ``face_normals`` (the 0x10 flag)
    and ``name`` (version 4 only). Values are written as float32, or float64 with `double`.
    """
    import struct
    import zlib

    out, offsets = bytearray(), []
    ftype = "<f8" if double else "<f4"
    for m in meshes:
        offsets.append(len(out))
        out += struct.pack("<HH", SERIALIZED_MAGIC, version)
        flags = _SER_DOUBLE if double else 0x1000
        for key, bit in (("normals", _SER_NORMALS), ("uvs", _SER_TEXCOORDS), ("colors", _SER_COLORS)):
            if m.get(key) is not None:
                flags |= bit
        if m.get("face_normals"):
            flags |= 0x0010
        positions, faces = np.asarray(m["positions"]), np.asarray(m["faces"])
        body = struct.pack("<I", flags)
        if version == 4:
            body += m.get("name", "").encode() + b"\0"
        body += struct.pack("<QQ", len(positions), len(faces))
        for key in ("positions", "normals", "uvs", "colors"):
            if m.get(key) is not None:
                body += np.asarray(m[key], dtype=ftype).tobytes()
        body += np.asarray(faces, dtype="<u4").tobytes()
        out += zlib.compress(body)
    out += b"".join(struct.pack("<Q" if version == 4 else "<I", o) for o in offsets)
    out += struct.pack("<I", len(meshes))
    Path(path).write_bytes(bytes(out))


def load_mesh(path, face_normals: bool = False,
              flip_tex_coords: Optional[bool] = None) -> Mesh:
    """Load an ``.obj`` or ``.ply`` file by extension (see :func:`load_obj`, :func:`load_ply`).

    ``flip_tex_coords=None`` uses the format's Mitsuba default (OBJ true, PLY false).
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".obj":
        return load_obj(path, face_normals, True if flip_tex_coords is None else flip_tex_coords)
    if suffix == ".ply":
        return load_ply(path, face_normals, bool(flip_tex_coords))
    raise MeshError(f"{path}: unsupported mesh format {suffix!r}, expected .obj or .ply")


# ---------------------------------------------------------------------------------------
# Built-in shapes
# ---------------------------------------------------------------------------------------


def rectangle() -> Mesh:
    """Mitsuba 3's ``rectangle`` as two triangles.

    The square [-1, 1]^2 in the plane z = 0, facing +z (winding and normals), uv =
    ``((x + 1) / 2, (y + 1) / 2)``: the uv Mitsuba 3.9's analytic rectangle reports at a
    hit (checked with ``si.uv``); the affine map is reproduced exactly by the two
    triangles. Vertices (-1,-1), (1,-1), (1,1), (-1,1); faces (0,1,2), (0,2,3); area 4.

    Returns:
        Mesh with 4 vertices, 2 faces, normals (0, 0, 1), uvs.
    """
    positions = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    normals = np.tile(np.array([0, 0, 1], dtype=np.float32), (4, 1))
    uvs = (positions[:, :2] + 1.0) * 0.5
    return Mesh(positions, faces, normals, uvs)


# Mitsuba 3.9.1 ``cube``, vertex by vertex (mi.traverse(cube)): 4 per side, sides in the
# order -y, +y, +x, +z, -x, -z; each side's uvs are (0,1), (1,1), (1,0), (0,0).
_CUBE_SIDES = (
    ((0, -1, 0), ((1, -1, -1), (1, -1, 1), (-1, -1, 1), (-1, -1, -1))),
    ((0, 1, 0), ((1, 1, -1), (-1, 1, -1), (-1, 1, 1), (1, 1, 1))),
    ((1, 0, 0), ((1, -1, -1), (1, 1, -1), (1, 1, 1), (1, -1, 1))),
    ((0, 0, 1), ((1, -1, 1), (1, 1, 1), (-1, 1, 1), (-1, -1, 1))),
    ((-1, 0, 0), ((-1, -1, 1), (-1, 1, 1), (-1, 1, -1), (-1, -1, -1))),
    ((0, 0, -1), ((1, 1, -1), (1, -1, -1), (-1, -1, -1), (-1, 1, -1))),
)


def cube() -> Mesh:
    """Mitsuba 3's ``cube``: [-1, 1]^3 with outward normals, Mitsuba's exact layout.

    24 vertices (4 per side, sides ordered -y, +y, +x, +z, -x, -z), 12 triangles
    ``(4k, 4k+1, 4k+2), (4k+3, 4k, 4k+2)`` wound counter-clockwise seen from outside,
    per-side uvs (0,1), (1,1), (1,0), (0,0); identical to ``mi.traverse`` of a Mitsuba
    3.9.1 cube. The normals are stored normals (``computed_normals=False``).

    Returns:
        Mesh with 24 vertices, 12 faces, normals and uvs.
    """
    positions = np.array([p for _, ps in _CUBE_SIDES for p in ps], dtype=np.float32)
    normals = np.repeat(np.array([n for n, _ in _CUBE_SIDES], dtype=np.float32), 4, axis=0)
    uvs = np.tile(np.array([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=np.float32), (6, 1))
    base = 4 * np.arange(6)[:, None, None]
    faces = (np.array([[0, 1, 2], [3, 0, 2]])[None] + base).reshape(-1, 3)
    return Mesh(positions, faces, normals, uvs)
