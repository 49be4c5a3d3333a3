"""4x4 affine transforms with Mitsuba 3's conventions (degrees, right-handed rotations,
`look_at` with the camera looking along local +z and local +x pointing left)."""
from __future__ import annotations

import numpy as np


class _Composing:
    """A constructor that, called on an instance, composes with it as Mitsuba 3's chained
    transforms do: `t.scale(2)` is `t @ Transform.scale(2)` (not a fresh scale, which would
    silently drop `t`)."""

    def __init__(self, make):
        self.make = make
        self.__doc__ = make.__doc__

    def __get__(self, obj, cls):
        if obj is None:
            return lambda *args, **kwargs: self.make(cls, *args, **kwargs)
        return lambda *args, **kwargs: obj @ self.make(type(obj), *args, **kwargs)


class Transform:
    """An affine transform held as a (4, 4) float64 matrix; compose with `@` (right first),
    or chain as in Mitsuba 3 (each call applies to the points before the transform so far).

    >>> to_world = Transform.translate([0, 1, 0]) @ Transform.scale(0.5)
    >>> to_world = Transform.translate([0, 1, 0]).scale(0.5)  # the same
    """

    def __init__(self, matrix=None):
        m = np.eye(4) if matrix is None else np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"Transform needs a (4, 4) matrix, got shape {m.shape}")
        self.matrix = m

    @_Composing
    def translate(cls, v) -> "Transform":
        m = np.eye(4)
        m[:3, 3] = _vec3(v, "translate")
        return cls(m)

    @_Composing
    def scale(cls, v) -> "Transform":
        s = np.full(3, float(v)) if np.ndim(v) == 0 else _vec3(v, "scale")
        return cls(np.diag([*s, 1.0]))

    @_Composing
    def rotate(cls, axis, angle: float) -> "Transform":
        """Rotation by `angle` degrees counter-clockwise about `axis` (Rodrigues)."""
        a = _vec3(axis, "rotate axis")
        n = np.linalg.norm(a)
        if n == 0:
            raise ValueError("rotate: the axis must not be zero")
        x, y, z = a / n
        s, c = np.sin(np.radians(angle)), np.cos(np.radians(angle))
        t = 1 - c
        m = np.eye(4)
        m[:3, :3] = [[x * x * t + c, x * y * t - z * s, x * z * t + y * s],
                     [x * y * t + z * s, y * y * t + c, y * z * t - x * s],
                     [x * z * t - y * s, y * z * t + x * s, z * z * t + c]]
        return cls(m)

    @classmethod
    def look_at(cls, origin, target, up) -> "Transform":
        """Camera-to-world: local +z towards `target`, +y along `up`, +x to the left."""
        o, t, u = _vec3(origin, "origin"), _vec3(target, "target"), _vec3(up, "up")
        d = t - o
        if np.linalg.norm(d) == 0:
            raise ValueError("look_at: origin and target coincide")
        d /= np.linalg.norm(d)
        left = np.cross(u, d)
        if np.linalg.norm(left) == 0:
            raise ValueError("look_at: 'up' is parallel to the viewing direction")
        left /= np.linalg.norm(left)
        new_up = np.cross(d, left)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
        return cls(m)

    def __matmul__(self, other: "Transform") -> "Transform":
        if not isinstance(other, Transform):
            return NotImplemented
        return Transform(self.matrix @ other.matrix)

    def inverse(self) -> "Transform":
        return Transform(np.linalg.inv(self.matrix))

    def apply_point(self, p) -> np.ndarray:
        return self.matrix[:3, :3] @ _vec3(p, "point") + self.matrix[:3, 3]

    def apply_vector(self, v) -> np.ndarray:
        return self.matrix[:3, :3] @ _vec3(v, "vector")

    def __repr__(self) -> str:
        return f"Transform({np.array2string(self.matrix, precision=4)})"


def _vec3(v, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"{what} needs 3 components, got {a.size}")
    return a.copy()


def as_matrix(value, what: str = "to_world") -> np.ndarray:
    """A (4, 4) float64 matrix from a Transform, a Mitsuba transform, nested lists, numpy
    arrays or tensors."""
    if isinstance(value, Transform):
        return value.matrix
    if hasattr(value, "matrix") and not isinstance(value, np.ndarray):  # mi.ScalarTransform4f
        value = value.matrix
    if hasattr(value, "detach"):  # torch.Tensor
        value = value.detach().cpu().numpy()
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{what} must be a 4x4 matrix or a Transform, got {value!r}") from None
    if m.shape != (4, 4):
        raise ValueError(f"{what} must be a 4x4 matrix or a Transform, got shape {m.shape}")
    return m
