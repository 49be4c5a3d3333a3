"""Build a Scene from Mitsuba 3's dict format (the XML reader produces the same format).

Supports the subset of Mitsuba 3 listed in the README, with Mitsuba's defaults and parameter
names. Anything else is a SceneError naming the plugin or parameter, where it was given, and
what is supported.
"""
from __future__ import annotations

import numbers
import os
import warnings
from pathlib import Path

import numpy as np
import torch

from . import meshes, spectra
from .images import read_image
from .mitsuba_xml import SceneError, read_xml
from .scene import Film, Integrator, NativeScene, Scene, Sensor
from .transform import Transform, as_matrix

CATEGORY = {
    "diffuse": "bsdf", "twosided": "bsdf", "conductor": "bsdf", "roughconductor": "bsdf",
    "dielectric": "bsdf", "roughplastic": "bsdf",
    "obj": "shape", "ply": "shape", "serialized": "shape", "rectangle": "shape", "cube": "shape", "sphere": "shape", "disk": "shape", "cylinder": "shape",
    "shapegroup": "shape", "instance": "shape",
    "area": "emitter", "point": "emitter", "constant": "emitter",
    "bitmap": "texture", "checkerboard": "texture", "mesh_attribute": "texture",
    "perspective": "sensor", "hdrfilm": "film", "box": "rfilter", "tent": "rfilter",
    "gaussian": "rfilter", "mitchell": "rfilter", "catmullrom": "rfilter", "lanczos": "rfilter",
    "orthographic": "sensor", "thinlens": "sensor",
    "independent": "sampler", "stratified": "sampler", "multijitter": "sampler",
    "orthogonal": "sampler", "ldsampler": "sampler",
    "path": "integrator", "prb": "integrator", "direct": "integrator",
}

# Properties each plugin accepts (besides nested plugins of the categories it takes).
PROPERTIES = {
    "diffuse": {"reflectance"},
    "twosided": set(),
    "conductor": {"specular_reflectance", "material"},
    "roughconductor": {"specular_reflectance", "material", "alpha", "distribution", "sample_visible"},
    "dielectric": {"int_ior", "ext_ior", "specular_reflectance", "specular_transmittance"},
    "roughplastic": {"diffuse_reflectance", "specular_reflectance", "alpha", "distribution",
                     "int_ior", "ext_ior", "nonlinear", "sample_visible"},
    "obj": {"filename", "face_normals", "flip_normals", "flip_tex_coords", "to_world"},
    "ply": {"filename", "face_normals", "flip_normals", "flip_tex_coords", "to_world"},
    "serialized": {"filename", "shape_index", "face_normals", "flip_normals", "to_world"},
    "rectangle": {"flip_normals", "to_world"},
    "cube": {"flip_normals", "to_world"},
    "sphere": {"center", "radius", "flip_normals", "to_world"},
    "disk": {"flip_normals", "to_world"},
    "cylinder": {"p0", "p1", "radius", "flip_normals", "to_world"},
    "shapegroup": set(),
    "instance": {"to_world"},
    "area": {"radiance"},
    "point": {"position", "intensity", "to_world"},
    "constant": {"radiance"},
    "bitmap": {"filename", "raw", "filter_type", "wrap_mode", "to_uv"},
    "checkerboard": {"color0", "color1", "to_uv"},
    "mesh_attribute": {"name", "scale"},
    "perspective": {"fov", "fov_axis", "focal_length", "near_clip", "far_clip", "focus_distance",
                    "to_world", "principal_point_offset_x", "principal_point_offset_y"},
    "hdrfilm": {"width", "height", "crop_offset_x", "crop_offset_y", "crop_width", "crop_height",
                "pixel_format", "component_format", "file_format", "sample_border"},
    "box": set(), "tent": {"radius"}, "gaussian": {"stddev"}, "mitchell": {"B", "C"},
    "catmullrom": set(), "lanczos": {"lobes"},
    "orthographic": {"to_world", "near_clip", "far_clip"},
    "thinlens": {"fov", "fov_axis", "focal_length", "near_clip", "far_clip", "focus_distance",
                 "aperture_radius", "to_world"},
    "independent": {"sample_count", "seed"},
    "stratified": {"sample_count", "seed", "jitter"},
    "multijitter": {"sample_count", "seed", "jitter"},
    "orthogonal": {"sample_count", "seed", "jitter", "strength"},
    "ldsampler": {"sample_count", "seed"},
    "path": {"max_depth", "rr_depth", "hide_emitters"},
    "prb": {"max_depth", "rr_depth", "hide_emitters"},
    "direct": {"emitter_samples", "bsdf_samples", "shading_samples", "hide_emitters"},
}

# hdrfilm's pixel formats (Mitsuba 3.9); render() returns linear RGB for all of them.
PIXEL_FORMATS = ("rgb", "rgba", "luminance", "luminance_alpha", "xyz", "xyza")

# Named indices of refraction (Mitsuba's ior.h).
IOR = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277,
    "carbon dioxide": 1.00045, "water": 1.3330, "acetone": 1.36, "ethanol": 1.361,
    "carbon tetrachloride": 1.461, "glycerol": 1.4729, "benzene": 1.501,
    "silicone oil": 1.52045, "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458,
    "pyrex": 1.470, "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046,
    "sodium chloride": 1.544, "amber": 1.55, "pet": 1.5750, "diamond": 2.419,
}


# Mesh attributes a mesh_attribute texture can read, in the order of the core's MeshAttribute.
MESH_ATTRIBUTES = ("vertex_color", "face_color")

GEOMETRY = ("geometry is fixed at load: torch_rbpt differentiates materials and emission, not "
            "shapes (visibility gradients are out of scope)")


def _where(node) -> str:
    return node.get("__where__", "<dict>") if isinstance(node, dict) else "<dict>"


def _is_plugin(value) -> bool:
    return isinstance(value, dict) and "type" in value and value["type"] not in ("rgb", "spectrum")


def _check_plugin_dicts(node: dict, key: str) -> None:
    """Check the shape of every dict in a scene tree before it is interpreted: a "type" is a
    string, an rgb has a "value", a ref has a string "id"."""
    t = node.get("type")
    if "type" in node and not isinstance(t, str):
        raise SceneError(f"{_where(node)}: '{key}': the plugin type must be a string, got "
                         f"{type(t).__name__} {t!r}")
    if t == "rgb" and "value" not in node:
        raise SceneError(f"{_where(node)}: '{key}': an rgb needs a 'value'")
    if t == "ref" and not isinstance(node.get("id"), str):
        raise SceneError(f"{_where(node)}: '{key}': a ref needs a string 'id', got {node.get('id')!r}")
    for name, value in node.items():
        if isinstance(value, dict) and not str(name).startswith("__"):
            _check_plugin_dicts(value, name)


# Plugins of capabilities we do not have at all, named in the error (Mitsuba 3 plugin names).
NOT_SUPPORTED = {
    **dict.fromkeys(["homogeneous", "heterogeneous", "isotropic", "hg", "rayleigh", "sggx",
                     "volpath", "volpathmis", "prbvolpath", "gridvolume", "constvolume"],
                    "participating media are not supported"),
    **dict.fromkeys(["polarizer", "retarder", "measured_polarized", "stokes", "pplastic"],
                    "polarisation is not supported (RGB rendering only)"),
    **dict.fromkeys(["bsplinecurve", "linearcurve"], "curves are not supported"),
    "sdfgrid": "SDF grids are not supported",
    "hair": "hair BSDFs are not supported",
    **dict.fromkeys(["irregular", "blackbody", "d65", "uniform", "regular"],
                    "spectral rendering is not supported: give colours as rgb or a "
                    "wavelength:value <spectrum> list, which is converted to RGB"),
}


def _unsupported(node: dict, key: str) -> str:
    """The message for a plugin of unknown type, listing the supported plugins of its kind
    (from its XML tag, or its dict key when that names a kind) or all of them."""
    if node.get("type") in NOT_SUPPORTED:
        return f"plugin '{node['type']}': {NOT_SUPPORTED[node['type']]}"
    kind = node.get("__tag__") or key
    if kind not in CATEGORY.values():
        return f"unsupported plugin '{node['type']}' (supported: {', '.join(sorted(CATEGORY))})"
    supported = sorted(k for k, v in CATEGORY.items() if v == kind)
    return f"unsupported {kind} plugin '{node['type']}' (supported: {', '.join(supported)})"


class _Builder:
    def __init__(self, scene: dict, base_dir: Path, dtype: torch.dtype):
        _check_plugin_dicts(scene, "scene")
        self.search = [base_dir] + list(scene.get("__search__", []))
        self.dtype = dtype
        self.native = NativeScene()
        self.params: dict[str, torch.Tensor] = {}
        self.fixed: dict[str, tuple] = {}  # key -> (tensor, why it cannot be differentiated)
        self.objects = {}  # id -> plugin dict (top-level ones, then nested ones with an id)
        self.built_bsdfs: dict[int, int] = {}  # id(node) -> native BSDF index
        self.built_textures: dict[int, int] = {}
        self.built_emitters: dict[int, int] = {}  # id(area emitter node) -> radiance parameter
        self.attached: dict[int, str] = {}  # id(area emitter node) -> key of its shape
        self.built_shapes: set[int] = set()  # id(node) of shapes built (shapegroup members)
        self.default_bsdfs: dict[int, dict] = {}  # id(shape node) -> its default BSDF
        self.bsdf_attributes: set = set()  # mesh attributes read by the BSDF being built
        self.attributes_of_bsdf: dict[int, set] = {}  # native BSDF index -> attributes it reads
        self.attribute_params: dict = {}  # (id(shape node), name) -> param index
        for key, value in scene.items():
            if _is_plugin(value) and value["type"] != "ref":
                self.objects[value.get("__id__", key)] = value
        # As in Mitsuba, a nested object with an id can be referenced from elsewhere too.
        self._collect_nested_ids(scene)

    def _collect_nested_ids(self, node: dict) -> None:
        for name, value in node.items():
            if str(name).startswith("__") or not _is_plugin(value) or value["type"] == "ref":
                continue
            if node.get("type") != "scene" and "__id__" in value:
                self.objects.setdefault(value["__id__"], value)
            self._collect_nested_ids(value)

    # -- helpers ------------------------------------------------------------------------------

    def fail(self, node, message: str):
        raise SceneError(f"{_where(node)}: {message}")

    def resolve_ref(self, value):
        """The plugin a {"type": "ref", "id": ...} names (other values pass through)."""
        if not (isinstance(value, dict) and value.get("type") == "ref"):
            return value
        target = self.objects.get(value.get("id"))
        if target is None:
            self.fail(value, f"reference to unknown id '{value.get('id')}'")
        return target

    def deref(self, value, category: str, where_node):
        value = self.resolve_ref(value)
        if not _is_plugin(value) or CATEGORY.get(value["type"]) != category:
            got = value.get("type") if isinstance(value, dict) else type(value).__name__
            self.fail(where_node, f"expected a {category} plugin, got '{got}'")
        return value

    def check(self, node, category: str, nested: tuple = ()):
        """Validate a plugin's type and property names."""
        self.current = node  # the plugin being built, for errors raised while adding its parameters
        t = node["type"]
        if CATEGORY.get(t) != category:
            supported = sorted(k for k, v in CATEGORY.items() if v == category)
            self.fail(node, f"unsupported {category} plugin '{t}' (supported: {', '.join(supported)})")
        tag = node.get("__tag__")
        if tag is not None and tag != category:
            self.fail(node, f"<{tag} type=\"{t}\">: '{t}' is a {category}, not a {tag}")
        allowed = PROPERTIES[t]
        for key, value in node.items():
            if key.startswith("__") or key in ("type", "id"):
                continue
            if _is_plugin(value):
                target = self.resolve_ref(value)
                cat = CATEGORY.get(target["type"])
                if cat is None:
                    self.fail(target if target.get("__where__") else node,
                              f"{t}: '{key}': {_unsupported(target, key)}")
                if key in allowed or cat in nested:
                    continue
                self.fail(value if value.get("__where__") else node,
                          f"{t}: unexpected nested plugin '{key}' ({value['type']})")
            elif key not in allowed:
                self.fail(node, f"{t}: unsupported parameter '{key}' (supported: "
                                f"{', '.join(sorted(allowed)) or 'none'})")

    def nested(self, node, category: str) -> list:
        out = []
        for key, value in node.items():
            if key.startswith("__") or not _is_plugin(value):
                continue
            target = self.resolve_ref(value)
            if CATEGORY.get(target["type"]) == category:
                out.append((key, target, target is not value))
        return out

    def add_param(self, key: str, value) -> int:
        t = torch.as_tensor(np.asarray(value, dtype=np.float64)).to(self.dtype).contiguous()
        node = getattr(self, "current", None)
        if key in self.params:
            self.fail(node, f"two parameters share the key '{key}': give the objects distinct ids")
        if not bool(torch.isfinite(t).all()):
            self.fail(node, f"'{key}' has a non-finite value ({t.flatten().tolist()[:3]}{'...' if t.numel() > 3 else ''}): "
                            f"parameters must be finite")
        self.params[key] = t
        return self.native.add("param", key, t.numel())

    def add_native(self, node, what: str, *args) -> int:
        """`self.native.add_<what>(*args)`; the core's ValueErrors are re-raised naming the plugin."""
        try:
            return self.native.add(what, *args)
        except ValueError as e:
            self.fail(node, f"{node['type']}: {e}")

    def add_fixed(self, key: str, value, why: str) -> None:
        """A Mitsuba parameter we expose read-only: editing or differentiating it is an error."""
        self.fixed[key] = (torch.as_tensor(np.asarray(value, dtype=np.float64)).to(self.dtype), why)

    def number(self, node, name: str, default=None, kind=float):
        value = node.get(name, default)
        if value is None:
            self.fail(node, f"{node['type']}: missing parameter '{name}'")
        try:
            if kind is bool:
                if isinstance(value, str):
                    if value.lower() not in ("true", "false"):
                        raise ValueError
                    return value.lower() == "true"
                if not isinstance(value, numbers.Real):  # not a list, array or tensor
                    raise TypeError
                return bool(value)
            if kind is int and isinstance(value, float) and not value.is_integer():
                raise ValueError
            result = kind(value)
        except (TypeError, ValueError, OverflowError):
            self.fail(node, f"{node['type']}: parameter '{name}' must be a {kind.__name__}, got {value!r}")
        if kind is int and not -2 ** 31 <= result < 2 ** 31:  # the renderer's ints are 32-bit
            self.fail(node, f"{node['type']}: parameter '{name}' must fit in 32 bits, got {value!r}")
        return result

    def floats(self, node, name: str, value) -> np.ndarray:
        """`value` (a number, list, array or tensor) as a flat float64 array."""
        try:
            return np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value,
                              dtype=np.float64).reshape(-1)
        except (TypeError, ValueError, OverflowError):
            self.fail(node, f"{node['type']}: parameter '{name}' must be numbers, got {value!r}")

    def string(self, node, name: str, default: str, choices=None) -> str:
        value = node.get(name, default)
        if not isinstance(value, str):
            self.fail(node, f"{node['type']}: parameter '{name}' must be a string, got {value!r}")
        if choices is not None and value not in choices:
            self.fail(node, f"{node['type']}: parameter '{name}' must be one of {', '.join(choices)}, got '{value}'")
        return value

    def matrix(self, node, name: str = "to_world") -> np.ndarray:
        value = node.get(name)
        if value is None:
            return np.eye(4)
        try:
            m = as_matrix(value, name)
        except ValueError as e:
            self.fail(node, f"{node['type']}: {e}")
        if not np.all(np.isfinite(m)) or not np.array_equal(m[3], [0, 0, 0, 1]):
            self.fail(node, f"{node['type']}: {name} must be an affine transform with finite entries "
                            f"(last row 0, 0, 0, 1), got {m.tolist()}")
        return m

    def vector(self, node, name: str, default=None) -> np.ndarray:
        value = node.get(name, default)
        v = self.floats(node, name, value)
        if v.shape != (3,):
            self.fail(node, f"{node['type']}: parameter '{name}' needs 3 values, got {v.size}")
        return v

    def ior(self, node, name: str, default: str) -> float:
        value = node.get(name, default)
        if isinstance(value, str):
            if value.lower() not in IOR:
                self.fail(node, f"{node['type']}: unknown {name} '{value}' (known: {', '.join(IOR)})")
            return IOR[value.lower()]
        ior = self.number(node, name)
        if not ior > 0:
            self.fail(node, f"{node['type']}: {name} must be positive, got {ior}")
        return ior

    def resolve(self, node, filename) -> Path:
        if not isinstance(filename, (str, os.PathLike)):
            self.fail(node, f"{node['type']}: parameter 'filename' must be a string, got {filename!r}")
        p = Path(os.path.expanduser(str(filename)))
        candidates = [p] if p.is_absolute() else [base / p for base in self.search]
        for c in candidates:
            try:
                if c.exists():
                    return c
            except OSError as e:  # e.g. a name too long for the file system
                self.fail(node, f"{node['type']}: cannot access file '{filename}' ({e.strerror})")
        self.fail(node, f"{node['type']}: file '{filename}' not found (looked in "
                        f"{', '.join(str(c.parent) for c in candidates)})")

    # -- textures ------------------------------------------------------------------------------

    def texture(self, owner, name: str, key: str, default):
        """A material or emission input: returns (param, texture) for the C++ side, one of
        them -1. Constants (numbers, rgb, spectrum) become the parameter `<key>.value`;
        textures (bitmap, checkerboard) register their own parameters under `key`."""
        value = owner.get(name, default)
        if isinstance(value, dict) and value.get("type") == "ref":
            value = self.deref(value, "texture", owner)
        if isinstance(value, dict) and value.get("type") in ("bitmap", "checkerboard"):
            return -1, self.build_texture(value, key)
        if isinstance(value, dict) and value.get("type") == "mesh_attribute":
            return self.mesh_attribute(owner, value)
        return self.constant(owner, name, key, value), -1

    def constant(self, owner, name: str, key: str, value) -> int:
        """A constant input (a number, 1 or 3 numbers, rgb or spectrum) as the parameter
        `<key>.value`, of 1 or 3 entries as Mitsuba's traverse has it."""
        if isinstance(value, dict) and value.get("type") == "rgb":
            v = self.floats(value, name, value["value"])
            if v.size == 1:
                v = np.repeat(v, 3)
            if v.size != 3:
                self.fail(value, f"rgb '{name}' needs 1 or 3 values")
            return self.add_param(f"{key}.value", v)
        if isinstance(value, dict) and value.get("type") == "spectrum":
            return self.add_param(f"{key}.value", self.spectrum(value, name, CATEGORY.get(owner["type"]) == "emitter"))
        if isinstance(value, dict):
            self.fail(value, f"'{name}': unsupported texture '{value.get('type')}' (supported: rgb, "
                             f"spectrum, bitmap, checkerboard, or a number)")
        if isinstance(value, (torch.Tensor, np.ndarray, list, tuple)):
            v = self.floats(owner, name, value)
            if v.size not in (1, 3):
                self.fail(owner, f"{owner['type']}: '{name}' needs 1 or 3 values, got {v.size}")
            return self.add_param(f"{key}.value", v)
        try:
            v = float(value)
        except (TypeError, ValueError, OverflowError):
            self.fail(owner, f"{owner['type']}: '{name}' must be a number, rgb, spectrum or texture, got {value!r}")
        return self.add_param(f"{key}.value", [v])

    def mesh_attribute(self, owner, node) -> tuple:
        """Mitsuba's mesh_attribute texture, as a BSDF input: (param, bitmap, attribute)."""
        self.check(node, "texture")
        if owner["type"] != "diffuse":
            self.fail(node, f"mesh_attribute: supported as a diffuse reflectance, not in a {owner['type']}")
        name = self.string(node, "name", "", ("vertex_color", "face_color"))
        if self.number(node, "scale", 1.0) != 1.0:
            self.fail(node, "mesh_attribute: only scale = 1 is supported")
        self.bsdf_attributes.add(name)
        return -1, -1, MESH_ATTRIBUTES.index(name)

    def spectrum(self, node, name: str, emitted: bool) -> np.ndarray:
        """A `spectrum` dict ("value": a number or [[wavelength, value], ...], or "filename")
        as Mitsuba's RGB variants convert it (see spectra.py): 1 value or RGB."""
        try:
            if "filename" in node:
                if "value" in node:
                    raise spectra.SpectrumError("give either 'value' or 'filename', not both")
                return spectra.pairs_to_rgb(*spectra.read_spd(self.resolve(node, node["filename"])), emitted)
            if "value" not in node:
                raise spectra.SpectrumError("needs a 'value' or a 'filename'")
            value = node["value"]
            if isinstance(value, numbers.Real) and not isinstance(value, bool):
                return spectra.constant_to_value(float(value), emitted)
            pairs = np.asarray(value, dtype=np.float64)
            if pairs.ndim != 2 or pairs.shape[1] != 2:
                raise spectra.SpectrumError(f"'value' must be a number or (wavelength, value) pairs, got {value!r}")
            return spectra.pairs_to_rgb(pairs[:, 0], pairs[:, 1], emitted)
        except (spectra.SpectrumError, OSError, TypeError, ValueError) as e:
            self.fail(node, f"spectrum '{name}': {e}")

    def to_uv(self, node, key: str) -> list:
        """Mitsuba's texture `to_uv`: the 2D affine part (rows and columns x, y, translation)
        of a 4x4 transform, applied to (u, v, 1); exposed read-only as `<key>.to_uv` (3x3)."""
        m = self.matrix(node, "to_uv")
        m3 = m[np.ix_([0, 1, 3], [0, 1, 3])]
        self.add_fixed(f"{key}.to_uv", m3, "a texture's to_uv transform is fixed at load")
        return [] if np.array_equal(m3, np.eye(3)) else m3[:2].tolist()

    def build_texture(self, node, key: str) -> int:
        """A texture plugin (bitmap or checkerboard), once per node; its native index."""
        if id(node) in self.built_textures:
            return self.built_textures[id(node)]
        if node["type"] == "bitmap":
            index = self.bitmap(node, key)
        else:
            self.check(node, "texture")
            c0 = self.texture(node, "color0", f"{key}.color0", 0.4)
            c1 = self.texture(node, "color1", f"{key}.color1", 0.2)
            if c0[1] >= 0 or c1[1] >= 0:
                self.fail(node, "checkerboard: color0 and color1 must be constants (a number, rgb "
                                "or spectrum), not textures")
            index = self.add_native(node, "checkerboard", c0[0], c1[0], self.to_uv(node, key))
        self.built_textures[id(node)] = index
        return index

    def bitmap(self, node, key: str) -> int:
        self.check(node, "texture")
        if "filename" not in node:
            self.fail(node, "bitmap: missing parameter 'filename'")
        path = self.resolve(node, self.string(node, "filename", ""))
        raw = self.number(node, "raw", False, bool)
        try:
            image = read_image(path, raw=raw)
        except (ValueError, OSError) as e:  # re-raised with the scene location
            self.fail(node, f"bitmap: {e}")
        if image.shape[2] == 4:
            image = image[:, :, :3]
        elif image.shape[2] == 2:
            image = image[:, :, :1]
        h, w, c = image.shape
        bad = (~torch.isfinite(image)).nonzero()
        if len(bad):
            y, x, ch = (int(v) for v in bad[0])
            self.fail(node, f"bitmap '{path}': {len(bad)} non-finite texel value(s), the first "
                            f"({float(image[y, x, ch])}) at row {y}, column {x}, channel {ch}; "
                            f"texels must be finite")
        param = self.add_param(f"{key}.data", image.numpy())
        self.params[f"{key}.data"] = self.params[f"{key}.data"].reshape(h, w, c)
        filt = self.string(node, "filter_type", "bilinear", ("bilinear", "nearest"))
        wrap = self.string(node, "wrap_mode", "repeat", ("repeat", "mirror", "clamp"))
        return self.add_native(node, "bitmap", param, w, h, c, wrap, filt == "nearest", self.to_uv(node, key))

    # -- BSDFs ---------------------------------------------------------------------------------

    def bsdf(self, node, key: str, twosided: bool = False) -> int:
        if id(node) in self.built_bsdfs:
            return self.built_bsdfs[id(node)]
        outer, self.bsdf_attributes = self.bsdf_attributes, set()
        index = self.build_bsdf(node, key, twosided)
        self.attributes_of_bsdf[index] = self.attributes_of_bsdf.get(index, set()) | self.bsdf_attributes
        self.bsdf_attributes = outer | self.bsdf_attributes
        return index

    def build_bsdf(self, node, key: str, twosided: bool) -> int:
        t = node["type"]
        self.check(node, "bsdf", nested=("bsdf", "texture") if t == "twosided" else ("texture",))
        if t == "twosided":
            inner = self.nested(node, "bsdf")
            if len(inner) != 1:
                self.fail(node, f"twosided needs exactly one nested BSDF, got {len(inner)} "
                                f"(different front and back BSDFs are not supported)")
            _, child, _ = inner[0]
            if child["type"] == "twosided":
                self.fail(child, "twosided cannot nest another twosided")
            index = self.bsdf(child, f"{key}.brdf_0", twosided=True)
            self.built_bsdfs[id(node)] = index
            return index
        material = self.string(node, "material", "none")
        if t in ("conductor", "roughconductor") and material != "none":
            self.fail(node, f"{t}: material '{material}' is not supported (only 'none', an ideal "
                            f"mirror tinted by specular_reflectance)")
        if not self.number(node, "sample_visible", True, bool):
            self.fail(node, f"{t}: only sample_visible=true is supported")
        refl = spec = trans = None
        alpha, dist, eta, nonlinear = -1, "beckmann", 1.0, False
        if t == "diffuse":
            refl = self.texture(node, "reflectance", f"{key}.reflectance", 0.5)
        elif t == "conductor":
            spec = self.texture(node, "specular_reflectance", f"{key}.specular_reflectance", 1.0)
        elif t == "roughconductor":
            spec = self.texture(node, "specular_reflectance", f"{key}.specular_reflectance", 1.0)
            alpha = self.add_param(f"{key}.alpha.value", [self.number(node, "alpha", 0.1)])
            dist = self.string(node, "distribution", "beckmann", ("beckmann", "ggx"))
        elif t == "dielectric":
            spec = self.texture(node, "specular_reflectance", f"{key}.specular_reflectance", 1.0)
            trans = self.texture(node, "specular_transmittance", f"{key}.specular_transmittance", 1.0)
            eta = self.ior(node, "int_ior", "bk7") / self.ior(node, "ext_ior", "air")
        elif t == "roughplastic":
            refl = self.texture(node, "diffuse_reflectance", f"{key}.diffuse_reflectance", 0.5)
            spec = self.texture(node, "specular_reflectance", f"{key}.specular_reflectance", 1.0)
            # Mitsuba keys roughplastic's roughness as `<id>.alpha` (a plain float).
            alpha = self.add_param(f"{key}.alpha", [self.number(node, "alpha", 0.1)])
            dist = self.string(node, "distribution", "beckmann", ("beckmann", "ggx"))
            eta = self.ior(node, "int_ior", "polypropylene") / self.ior(node, "ext_ior", "air")
            nonlinear = self.number(node, "nonlinear", False, bool)
        if alpha >= 0 and not float(list(self.params.values())[alpha][0]) > 0:
            self.fail(node, f"{t}: alpha must be positive")
        if t in ("dielectric", "roughplastic"):
            self.add_fixed(f"{key}.eta", [eta], f"the relative index of refraction (int_ior / ext_ior) "
                                                f"of a {t} is not differentiable and is fixed at load")
        index = self.add_native(node, "bsdf", t, twosided, refl, spec, trans, alpha, dist, float(eta), nonlinear)
        self.built_bsdfs[id(node)] = index
        return index

    # -- shapes and emitters -------------------------------------------------------------------

    def shapegroup(self, node, key: str) -> None:
        """Validate a shapegroup (Mitsuba: no emitters, no nested groups). Its shapes are built
        by each instance that references it."""
        self.check(node, "shape", nested=("shape",))
        for _, child, _ in self.nested(node, "shape"):
            if child["type"] in ("shapegroup", "instance"):
                self.fail(child, f"shapegroup: a {child['type']} cannot be nested in a shapegroup "
                                 f"(Mitsuba: 'Nested ShapeGroup is not permitted')")
            if self.nested(child, "emitter"):
                self.fail(child, "shapegroup: shapes in a shapegroup cannot have emitters "
                                 "(Mitsuba: 'Instancing of emitters is not supported')")

    def instance(self, node, key: str) -> None:
        """Mitsuba's `instance` of a shapegroup, flattened: each shape of the group is added
        again under instance.to_world @ its own to_world. The group's shapes keep the keys
        `<group id>.<shape key>...` (BSDFs shared by all instances), the instance has
        `<key>.to_world` (read-only, like all geometry)."""
        self.check(node, "shape", nested=("shape",))
        groups = self.nested(node, "shape")
        if len(groups) != 1 or groups[0][1]["type"] != "shapegroup":
            self.fail(node, "instance: needs exactly one shapegroup (Mitsuba: 'Only a shapegroup "
                            "can be specified in an instance')")
        group = groups[0][1]
        self.shapegroup(group, group.get("__id__", "shapegroup"))
        gkey = group.get("__id__", f"{key}.shapegroup")
        matrix = self.matrix(node)
        self.add_fixed(f"{key}.to_world", matrix, GEOMETRY)
        for ckey, child, _ in self.nested(group, "shape"):
            self.shape(child, f"{gkey}.{child.get('__id__', ckey)}", instance=matrix)

    def shape(self, node, key: str, instance=None) -> None:
        """Add a shape; `instance` (4x4) is the to_world of an instance of the shapegroup that
        holds it, applied after the shape's own to_world. Keys are registered once, with the
        shape's values in its group's space, as Mitsuba's."""
        t = node["type"]
        if t == "shapegroup":
            return self.shapegroup(node, key)
        if t == "instance":
            return self.instance(node, key)
        self.check(node, "shape", nested=("bsdf", "emitter"))
        first = instance is None or id(node) not in self.built_shapes
        self.built_shapes.add(id(node))
        bsdfs = self.nested(node, "bsdf")
        if len(bsdfs) > 1:
            self.fail(node, f"{t}: a shape takes one BSDF, got {len(bsdfs)}")
        if bsdfs:
            name, child, referenced = bsdfs[0]
            bsdf = self.bsdf(child, f"{key}.bsdf")
        else:  # Mitsuba's default: a diffuse BSDF, of reflectance 0.5, or 0 (black) on an emitter
            default = {"type": "diffuse", "__where__": _where(node)}
            if self.nested(node, "emitter"):
                default["reflectance"] = 0.0
            default = self.default_bsdfs.setdefault(id(node), default)
            bsdf = self.bsdf(default, f"{key}.bsdf")
        flip = self.number(node, "flip_normals", False, bool)
        to_world = self.matrix(node)
        self.build_shape(node, key, t, bsdf, flip, to_world, instance, first)

    def build_shape(self, node, key, t, bsdf, flip, to_world, instance, first) -> None:
        inst = np.eye(4) if instance is None else instance
        mesh = None

        def fixed(name, value):  # a group's shape registers its keys at its first instance
            if first:
                self.add_fixed(f"{key}.{name}", value, GEOMETRY)

        if t == "sphere":
            center = self.vector(node, "center", [0, 0, 0])
            radius = self.number(node, "radius", 1.0)
            m = to_world @ Transform.translate(center).matrix @ Transform.scale(radius).matrix
            fixed("to_world", m)
            m = inst @ m
            axes = m[:3, :3]
            scales = np.linalg.norm(axes, axis=0)
            if not np.allclose(scales, scales[0], rtol=1e-4) or scales[0] <= 0:
                self.fail(node, f"sphere: to_world must scale uniformly (got axis scales {scales})"
                                + ("; an instance's to_world included (Mitsuba renders an ellipsoid)"
                                   if instance is not None else ""))
            frame = (axes / scales).T.tolist()
            shape = self.add_native(node, "sphere", m[:3, 3].tolist(), float(scales[0]), frame, bsdf, flip)
        elif t == "disk":
            fixed("to_world", to_world @ np.diag([1, 1, -1 if flip else 1, 1]))
            to_world = inst @ to_world
            axes = to_world[:3, :3].T.astype(np.float32)
            radius = float(np.linalg.norm(axes[:2], axis=1).max())  # bounds p's rounding error
            shape = self.add_native(node, "disk_or_cylinder", "disk", to_world[:3, 3].tolist(),
                                    axes.tolist(), radius, 1.0, bsdf, flip)
        elif t == "cylinder":
            fixed("to_world", self.cylinder_frame(node, to_world)[4])
            center, axes, radius, length, _ = self.cylinder_frame(node, inst @ to_world)
            shape = self.add_native(node, "disk_or_cylinder", "cylinder", center, axes, radius,
                                    length, bsdf, flip)
        else:
            if t in ("obj", "ply", "serialized"):
                if "filename" not in node:
                    self.fail(node, f"{t}: missing parameter 'filename'")
                path = self.resolve(node, node["filename"])
                face_normals = self.number(node, "face_normals", False, bool)
                try:
                    if t == "serialized":
                        index = self.number(node, "shape_index", 0, int)
                        if index < 0:
                            self.fail(node, f"serialized: shape_index must be >= 0, got {index}")
                        mesh = meshes.load_serialized(path, index, face_normals=face_normals)
                    else:
                        flip_tex = self.number(node, "flip_tex_coords", t == "obj", bool)
                        mesh = (meshes.load_obj if t == "obj" else meshes.load_ply)(
                            path, face_normals=face_normals, flip_tex_coords=flip_tex)
                except meshes.MeshError as e:
                    self.fail(node, f"{t}: {e}")
            else:
                mesh = meshes.rectangle() if t == "rectangle" else meshes.cube()
            try:
                mesh = mesh.transformed(to_world)
            except meshes.MeshError as e:  # e.g. a singular to_world
                self.fail(node, f"{t}: to_world: {e}")
            if t == "rectangle":
                fixed("to_world", to_world)
            else:
                fixed("vertex_positions", mesh.positions.reshape(-1))
            if instance is not None:
                # An instance transforms the group's mesh, normals by the inverse transpose
                # (computed normals are not recomputed, as Mitsuba's instance)
                mesh.computed_normals = False
                try:
                    mesh = mesh.transformed(instance)
                except meshes.MeshError as e:
                    self.fail(node, f"{t}: instance to_world: {e}")
            # A rectangle's and a cube's vertex normals are their faces' normals (Mitsuba's
            # rectangle is analytic, its shading normal its plane's): without them the renderer
            # shades with the geometric normal, the same up to rounding, and a scene whose
            # meshes all lack vertex normals takes the wavefront's interaction stage without
            # their gathers (the texture gradient's rectangles 6% faster).
            flat = t in ("rectangle", "cube")
            shape = self.add_native(node, "mesh",
                torch.from_numpy(mesh.positions), torch.from_numpy(mesh.faces.astype(np.int64)),
                None if mesh.normals is None or flat else torch.from_numpy(mesh.normals),
                None if mesh.uvs is None else torch.from_numpy(mesh.uvs), bsdf, flip)
        self.mesh_attributes(node, key, t, bsdf, shape, mesh)
        emitters = self.nested(node, "emitter")
        if len(emitters) > 1:
            self.fail(node, f"{t}: a shape takes one emitter, got {len(emitters)}")
        for _, em, _ in emitters:
            if em["type"] != "area":
                self.check(em, "emitter")
                self.fail(em, f"only 'area' emitters can be attached to a shape, got '{em['type']}'")
            if id(em) in self.attached:
                self.fail(node, f"{t}: its area emitter is already attached to '{self.attached[id(em)]}' "
                                f"(as in Mitsuba, an emitter can be attached to a single shape)")
            self.attached[id(em)] = key
            self.add_native(em, "emitter", "area", self.area_radiance(em, f"{key}.emitter"), shape, [])

    def area_radiance(self, node, key: str) -> int:
        """An area emitter's radiance parameter, once per node. Its key follows Mitsuba's
        traversal: the emitter's id if declared at top level before the shape that references
        it, else `<shape>.emitter`."""
        if id(node) not in self.built_emitters:
            self.check(node, "emitter")
            param, texture = self.texture(node, "radiance", f"{key}.radiance",
                                          None if "radiance" in node else 1.0)
            if texture >= 0:
                self.fail(node, "area: textured radiance is not supported")
            self.built_emitters[id(node)] = param
        return self.built_emitters[id(node)]

    def mesh_attributes(self, node, key, t, bsdf, shape, mesh) -> None:
        """Register a mesh's vertex_color / face_color (keys `<shape>.vertex_color`, flat as
        Mitsuba's, differentiable) and check that it has those its BSDF reads."""
        have = {} if mesh is None else mesh.attributes
        for which, name in enumerate(MESH_ATTRIBUTES):
            values = have.get(name)
            if values is None:
                continue
            pkey = (id(node), name)
            if pkey not in self.attribute_params:  # once per shape, shared by instances
                self.attribute_params[pkey] = self.add_param(f"{key}.{name}", values.reshape(-1))
            if values.shape[1] in (1, 3):
                self.native.set_mesh_attribute(shape, which, self.attribute_params[pkey], values.shape[1])
        for name in sorted(self.attributes_of_bsdf.get(bsdf, ())):
            if name not in have:
                self.fail(node, f"{t}: its BSDF reads the mesh attribute '{name}', which this shape "
                                f"does not have (PLY colours r, g, b or red, green, blue give "
                                f"vertex_color or face_color)")
            if have[name].shape[1] not in (1, 3):
                self.fail(node, f"{t}: mesh attribute '{name}' has {have[name].shape[1]} channels; "
                                f"a BSDF input needs 1 or 3 (Mitsuba: 'requested but had size 4')")

    def cylinder_frame(self, node, to_world: np.ndarray):
        """Mitsuba's cylinder: to_world @ translate(p0) @ to_frame(Frame(unit(p1 - p0))) @
        scale(radius, radius, |p1 - p0|), split by polar decomposition into a rotation (the
        axes) and the radius and length. Returns (p0 in world, axes as rows, radius, length,
        the whole matrix: Mitsuba's `to_world` key).
        Shear, a non-uniform scale of the cross-section and mirroring are refused: Mitsuba
        3.9.1 warns and then renders a shape whose silhouette does not match its own surface
        (or nothing)."""
        p0 = self.vector(node, "p0", [0, 0, 0])
        p1 = self.vector(node, "p1", [0, 0, 1])
        radius = self.number(node, "radius", 1.0)
        axis = p1 - p0
        length = float(np.linalg.norm(axis))
        if not (radius > 0 and length > 0):
            self.fail(node, f"cylinder: radius and |p1 - p0| must be positive, got {radius} and {length}")
        n = axis / length
        sign = float(np.copysign(1.0, n[2]))  # Mitsuba's coordinate_system (Duff et al. 2017)
        a = -1.0 / (sign + n[2])
        b = n[0] * n[1] * a
        s_axis = np.array([1 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]])
        t_axis = np.array([b, sign + n[1] * n[1] * a, -n[1]])
        m = to_world[:3, :3] @ np.column_stack([s_axis, t_axis, n]) @ np.diag([radius, radius, length])
        u, sigma, vt = np.linalg.svd(m)
        q = u @ vt
        sym = vt.T @ np.diag(sigma) @ vt
        r, l = sym[0, 0], sym[2, 2]
        if np.linalg.det(m) <= 0:
            self.fail(node, "cylinder: to_world must not mirror (Mitsuba 3.9.1 renders nothing)")
        off = np.abs(sym - np.diag(np.diag(sym))).max()
        if off > 1e-5 * max(r, l) or abs(sym[0, 0] - sym[1, 1]) > 1e-5 * r:
            self.fail(node, "cylinder: to_world must scale the cross-section uniformly and not shear "
                            f"(scales {np.diag(sym).round(6).tolist()}); Mitsuba 3.9.1 warns and "
                            f"renders a shape inconsistent with its own surface")
        center = (to_world @ np.append(p0, 1.0))[:3]
        matrix = np.eye(4)
        matrix[:3, :3], matrix[:3, 3] = m, center
        return center.tolist(), q.T.tolist(), float(r), float(l), matrix

    def emitter(self, node, key: str) -> None:
        self.check(node, "emitter")
        t = node["type"]
        if t == "area":
            # Declared at top level: attached to the shape that references it (before or
            # after this point); unreferenced, it emits nothing (as in Mitsuba).
            self.area_radiance(node, key)
            return
        if t == "point":
            if "position" in node and "to_world" in node:
                self.fail(node, "point: give either 'position' or 'to_world', not both")
            position = self.vector(node, "position", [0, 0, 0])
            if "to_world" in node:
                position = self.matrix(node) @ np.append(position, 1.0)
            param, texture = self.texture(node, "intensity", f"{key}.intensity", 1.0)
            if texture >= 0:
                self.fail(node, "point: a textured intensity is not supported (use rgb, spectrum or a number)")
            self.add_native(node, "emitter", "point", param, -1, [float(x) for x in position[:3]])
        else:
            param, bitmap = self.texture(node, "radiance", f"{key}.radiance", 1.0)
            if bitmap >= 0:
                self.fail(node, "constant: textured radiance is not supported (use rgb, spectrum or a number)")
            self.add_native(node, "emitter", "constant", param, -1, [])

    # -- sensor and integrator ---------------------------------------------------------------

    def sensor(self, node) -> Sensor:
        self.check(node, "sensor", nested=("film", "sampler"))
        t = node["type"]
        s = Sensor(type=t)
        s.to_world = self.matrix(node)
        if np.linalg.matrix_rank(s.to_world[:3, :3]) < 3:  # the renderer's rays would be NaN
            self.fail(node, f"{t}: to_world must be invertible, got {s.to_world.tolist()}")
        s.near_clip = self.number(node, "near_clip", 1e-2)
        s.far_clip = self.number(node, "far_clip", 1e4)
        if t != "orthographic":
            self.field_of_view(node, s)
        if t == "thinlens":
            if "aperture_radius" not in node:
                self.fail(node, "thinlens: missing parameter 'aperture_radius' (Mitsuba has no default)")
            # Mitsuba replaces a zero radius by its float epsilon (with a warning).
            s.aperture_radius = self.number(node, "aperture_radius") or 2.0 ** -24
            s.focus_distance = self.number(node, "focus_distance", s.far_clip)
            r = s.to_world[:3, :3]  # Mitsuba's has_scale(): rows orthonormal within 1e-3
            if not np.allclose(r @ r.T, np.eye(3), rtol=0, atol=1e-3):
                self.fail(node, "thinlens: scale factors in to_world are not allowed (as in Mitsuba), "
                                f"got axis lengths {np.linalg.norm(r, axis=0).tolist()}")
        films = self.nested(node, "film")
        s.film = self.film(films[0][1]) if films else Film()
        samplers = self.nested(node, "sampler")
        if samplers:
            self.sampler(samplers[0][1], s)
        return s

    def field_of_view(self, node, s: Sensor) -> None:
        """`fov` + `fov_axis` or `focal_length` (perspective, thinlens), as Mitsuba's parse_fov."""
        t = node["type"]
        for name in ("principal_point_offset_x", "principal_point_offset_y"):
            if self.number(node, name, 0.0) != 0.0:
                self.fail(node, f"{t}: '{name}' must be 0 (off-centre projections are not supported)")
        if "fov" in node and "focal_length" in node:
            self.fail(node, f"{t}: give either 'fov' or 'focal_length', not both")
        if "fov" in node:
            s.fov = self.number(node, "fov")
            s.fov_axis = self.string(node, "fov_axis", "x", ("x", "y", "diagonal", "smaller", "larger"))
        else:
            f = node.get("focal_length", "50mm")
            text = str(f)[:-2] if str(f).endswith("mm") else str(f)
            try:
                focal = float(text)
            except ValueError:
                self.fail(node, f"{t}: cannot parse focal_length '{f}'")
            # Mitsuba: a 35 mm film (36 x 24 mm) diagonal field of view.
            s.fov = float(np.degrees(2 * np.arctan(np.hypot(36.0, 24.0) / (2 * focal))))
            s.fov_axis = "diagonal"

    def sampler(self, node, s: Sensor) -> None:
        """A sampler plugin's settings into sensor `s` (its sample count is rounded at render
        time as Mitsuba rounds it)."""
        self.check(node, "sampler")
        t = node["type"]
        s.sampler = t
        s.spp = self.number(node, "sample_count", 4, int)
        s.seed = self.number(node, "seed", 0, int)
        s.jitter = self.number(node, "jitter", True, bool)
        if s.spp <= 0:
            self.fail(node, f"{t}: sample_count must be positive")
        if t != "independent" and s.spp > 2 ** 24:
            self.fail(node, f"{t}: sample_count must be at most 2^24, got {s.spp}")
        if t == "orthogonal" and self.number(node, "strength", 2, int) != 2:
            self.fail(node, "orthogonal: only strength 2 is supported (Mitsuba 3.9.1's other "
                            "strengths do not give stratified patterns)")

    def film(self, node) -> Film:
        self.check(node, "film", nested=("rfilter",))
        f = Film(width=self.number(node, "width", 768, int), height=self.number(node, "height", 576, int))
        # Accepted as Mitsuba does (case-insensitive); render() returns linear RGB whatever it is.
        f.pixel_format = self.string(node, "pixel_format", "rgb").lower()
        if f.pixel_format not in PIXEL_FORMATS:
            self.fail(node, f"hdrfilm: pixel_format must be one of {', '.join(PIXEL_FORMATS)}, got "
                            f"'{node['pixel_format']}'")
        if f.width <= 0 or f.height <= 0:
            self.fail(node, f"hdrfilm: width and height must be positive, got {f.width}x{f.height}")
        if any(k in node for k in ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height")):
            x, y = self.number(node, "crop_offset_x", 0, int), self.number(node, "crop_offset_y", 0, int)
            w = self.number(node, "crop_width", f.width - x, int)
            h = self.number(node, "crop_height", f.height - y, int)
            if x < 0 or y < 0 or w <= 0 or h <= 0 or x + w > f.width or y + h > f.height:
                self.fail(node, f"hdrfilm: crop window ({x}, {y}, {w}, {h}) lies outside the {f.width}x{f.height} film")
            f.crop = (x, y, w, h)
        filters = self.nested(node, "rfilter")
        if filters:
            rf = filters[0][1]
            self.check(rf, "rfilter")
            f.filter = rf["type"]
            if f.filter == "box":
                f.filter_radius = 0.5
            elif f.filter == "tent":
                f.filter_radius = self.number(rf, "radius", 1.0)
            elif f.filter == "gaussian":
                f.filter_stddev = self.number(rf, "stddev", 0.5)
                f.filter_radius = 4 * f.filter_stddev
            elif f.filter == "mitchell":  # Mitsuba: radius 2, B = C = 1/3 by default
                f.filter_radius = 2.0
                f.filter_b, f.filter_c = self.number(rf, "B", 1 / 3), self.number(rf, "C", 1 / 3)
            elif f.filter == "catmullrom":  # Mitchell-Netravali with B = 0, C = 1/2
                f.filter_radius, f.filter_b, f.filter_c = 2.0, 0.0, 0.5
            else:  # lanczos: sinc(x) sinc(x / lobes), radius = lobes (default 3)
                f.filter_lobes = self.number(rf, "lobes", 3, int)
                if f.filter_lobes <= 0:
                    self.fail(rf, f"lanczos: lobes must be positive, got {f.filter_lobes}")
                f.filter_radius = float(f.filter_lobes)
            if not f.filter_radius > 0:
                self.fail(rf, f"{f.filter}: the filter radius must be positive")
        return f

    def integrator(self, node) -> Integrator:
        self.check(node, "integrator")
        i = Integrator(type=node["type"], hide_emitters=self.number(node, "hide_emitters", False, bool))
        if i.type == "direct":
            shading = self.number(node, "shading_samples", 1, int)
            i.emitter_samples = self.number(node, "emitter_samples", shading, int)
            i.bsdf_samples = self.number(node, "bsdf_samples", shading, int)
            if i.emitter_samples < 0 or i.bsdf_samples < 0 or i.emitter_samples + i.bsdf_samples == 0:
                self.fail(node, "direct: emitter_samples and bsdf_samples must be >= 0 and not both 0")
        else:
            i.max_depth = self.number(node, "max_depth", -1, int)
            i.rr_depth = self.number(node, "rr_depth", 5, int)
            if i.max_depth < -1 or i.rr_depth <= 0:
                self.fail(node, f"{i.type}: max_depth must be >= -1 and rr_depth > 0")
        return i

    # -- scene ---------------------------------------------------------------------------------

    def build(self, scene: dict, source: str) -> Scene:
        if scene.get("type") != "scene":
            raise SceneError(f"{_where(scene)}: the root must have type 'scene', got {scene.get('type')!r}")
        sensors, integrator = [], Integrator()
        for key, value in scene.items():
            if key.startswith("__") or key == "type":
                continue
            if not _is_plugin(value):
                raise SceneError(f"{_where(scene)}: scene entry '{key}' must be a plugin dict, got {type(value).__name__}")
            t = value["type"]
            cat = CATEGORY.get(t)
            if t == "ref":
                continue
            if cat is None:
                raise SceneError(f"{_where(value)}: {_unsupported(value, key)}")
            key = value.get("__id__", key)
            if cat == "shape":
                self.shape(value, key)
            elif cat == "emitter":
                self.emitter(value, key)
            elif cat == "sensor":
                sensors.append(self.sensor(value))
            elif cat == "integrator":
                integrator = self.integrator(value)
            elif cat == "bsdf":
                self.bsdf(value, key)  # registers its parameters even if unused
            elif cat == "texture":
                self.build_texture(value, key)
            elif cat == "sampler" and "__id__" not in value:
                # Mitsuba 3 loads a top-level sampler that nothing can reference and ignores
                # it: sensors keep their own (by default independent, 4 samples).
                self.check(value, "sampler")
                warnings.warn(f"{_where(value)}: a top-level sampler is ignored, as Mitsuba 3 "
                              f"ignores it; nest it in the sensor to use it", UserWarning, stacklevel=3)
            # A top-level film, rfilter or sampler is used where a sensor (or film) references it.
        return Scene(self.native, self.params, sensors, integrator, source, self.fixed)


def load_dict(scene: dict, dtype: torch.dtype = torch.float32, base_dir=None) -> Scene:
    """Load a scene from Mitsuba 3's dict format.

    `to_world` values may be 4x4 matrices (nested lists, numpy arrays, tensors) or
    `torch_rbpt.Transform`s. Relative file names resolve against `base_dir` (default: the
    current directory). Parameters are created with `dtype` (float32 or float64).
    """
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    if not isinstance(scene, dict):
        raise TypeError(f"load_dict expects a dict, got {type(scene).__name__}")
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    return _Builder(scene, base, dtype).build(scene, "<dict>")


def load_file(path, dtype: torch.dtype = torch.float32, **defaults) -> Scene:
    """Load a Mitsuba 3 XML scene; keyword arguments override its <default> values
    (e.g. `load_file("cbox.xml", res=64, spp=16)`)."""
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    path = Path(path)
    tree = read_xml(path, defaults)
    return _Builder(tree, path.resolve().parent, dtype).build(tree, str(path))
