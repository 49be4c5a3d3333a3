"""Read Mitsuba 3 XML into the dict format that `load_dict` takes.

Every plugin becomes a dict with a "type" entry and its properties; the private entries
"__where__" ("file:line") and "__id__" carry the source location and the XML id so that
later errors can name them. <default>, $name substitution, <include>, <path> and <ref> are
resolved here.
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
from lxml import etree

from .spectra import SpectrumError, parse_pairs
from .transform import Transform

PLUGIN_TAGS = ("bsdf", "shape", "emitter", "texture", "sensor", "film", "rfilter", "sampler",
               "integrator")
VALUE_TAGS = ("float", "integer", "boolean", "string", "rgb", "spectrum", "point", "vector",
              "transform", "ref")


class SceneError(ValueError):
    """A scene description is invalid; the message names the file and line when known."""


def _snake_case(name: str) -> str:
    """Mitsuba's upgrade of pre-2.0 names: "maxDepth" -> "max_depth", "intIOR" -> "int_ior",
    "aBcD" -> "a_bc_d" (an underscore before each run of capitals that follows a lower-case
    letter, the run lower-cased)."""
    return re.sub(r"(?<=[a-z])([A-Z]+)", lambda m: "_" + m.group(1).lower(), name)


def _numbers(text: str, where: str, what: str) -> list[float]:
    try:
        return [float(t) for t in re.split(r"[,\s]+", text.strip()) if t]
    except ValueError:
        raise SceneError(f"{where}: {what}: cannot parse numbers from '{text}'") from None


class XMLReader:
    """Parses one scene file (and the files it includes) with `<default>` overrides."""

    def __init__(self, path, overrides: dict[str, str]):
        self.path = Path(path).resolve()
        self.overrides = {k: str(v) for k, v in overrides.items()}
        self.defaults: dict[str, str] = {}
        self.search_paths: list[Path] = [self.path.parent]
        self.used_overrides: set[str] = set()
        # The files being read, outermost first, each with the <include> that opened it.
        self.include_stack: list[tuple[Path, str]] = [(self.path, "")]

    # -- files -------------------------------------------------------------------------------

    def resolve(self, filename: str, where: str, relative_to: Path | None = None) -> Path:
        """Find a file as Mitsuba's file resolver does: absolute, or relative to the scene
        folder and the <path> folders (and the including file's folder)."""
        p = Path(filename)
        if p.is_absolute():
            candidates = [p]
        else:
            bases = list(self.search_paths) + ([relative_to] if relative_to else [])
            candidates = [b / p for b in bases]
        for c in candidates:
            if c.exists():
                return c
        raise SceneError(f"{where}: file '{filename}' not found (looked in: "
                         f"{', '.join(str(c.parent) for c in candidates)})")

    def read(self) -> dict:
        root = self._parse(self.path)
        if root.tag != "scene":
            raise SceneError(f"{self.path}:{root.sourceline}: the root element must be <scene>, "
                             f"got <{root.tag}>")
        self._upgrade(root, self.path, required=True)
        scene = {"type": "scene", "__where__": f"{self.path}:{root.sourceline}"}
        self._children(root, scene, self.path)
        scene["__search__"] = self.search_paths[1:]
        unused = set(self.overrides) - self.used_overrides
        if unused:
            # As Mitsuba: a parameter that no attribute uses is an error ("unused parameters").
            raise SceneError(f"{self.path}: parameter(s) {', '.join(sorted(unused))} given as "
                             f"keyword arguments are not used in the scene (no attribute refers "
                             f"to ${sorted(unused)[0]})")
        return scene

    @staticmethod
    def _upgrade(root, path: Path, required: bool) -> None:
        """Check the root's version="major.minor.patch" and bring older files up to date as
        Mitsuba 3.9 does: 2.x and 3.x files read alike; before 2.0.0, parameter names were
        camelCase (maxDepth) and become snake_case (max_depth), except <default> names."""
        version = root.get("version")
        where = f"{path}:{root.sourceline}"
        if version is None:
            if required:
                raise SceneError(f"{where}: <{root.tag}> needs a version attribute, e.g. "
                                 f"<scene version=\"3.0.0\">")
            return
        if not re.fullmatch(r"\d+\.\d+\.\d+", version.strip()):
            raise SceneError(f"{where}: invalid version number '{version}' (expected "
                             f"major.minor.patch, e.g. \"3.0.0\")")
        if tuple(int(x) for x in version.strip().split(".")) >= (2, 0, 0):
            return
        for el in root.iter():
            if isinstance(el.tag, str) and el.tag != "default" and el.get("name") is not None:
                el.set("name", _snake_case(el.get("name")))

    def _parse(self, path: Path):
        try:
            parser = etree.XMLParser(remove_comments=True)
            return etree.parse(str(path), parser).getroot()
        except OSError as e:
            raise SceneError(f"cannot read scene file '{path}': {e}") from None
        except etree.XMLSyntaxError as e:
            line = e.lineno if e.lineno is not None else "?"
            raise SceneError(f"{path}:{line}: malformed XML: {e.msg}") from None

    # -- elements ----------------------------------------------------------------------------

    def _attr(self, el, name: str, where: str, default=None) -> str:
        value = el.get(name)
        if value is None:
            if default is not None:
                return default
            raise SceneError(f"{where}: <{el.tag}> needs the attribute '{name}'")
        return self._substitute(value, where)

    @staticmethod
    def _float(text: str, where: str, what: str) -> float:
        try:
            return float(text)
        except ValueError:
            raise SceneError(f"{where}: {what}: cannot parse a number from '{text}'") from None

    def _substitute(self, value: str, where: str) -> str:
        """$name -> a keyword argument of that name, else its <default> (as Mitsuba, a
        keyword argument needs no <default>)."""
        def repl(m):
            name = m.group(1)
            if name in self.overrides:
                self.used_overrides.add(name)
                return self.overrides[name]
            if name in self.defaults:
                return self.defaults[name]
            raise SceneError(f"{where}: undefined parameter ${name} (no <default name=\"{name}\"> "
                             f"and no keyword argument {name}=...)")
        return re.sub(r"\$(\w+)", repl, value)

    def _children(self, el, node: dict, file: Path) -> None:
        counts: dict[str, int] = {}
        for child in el:
            if not isinstance(child.tag, str):
                continue
            where = f"{file}:{child.sourceline}"
            tag = child.tag
            if tag == "default":
                name = child.get("name")
                if name is None or child.get("value") is None:
                    raise SceneError(f"{where}: <default> needs 'name' and 'value'")
                self.defaults.setdefault(name, child.get("value"))
            elif tag == "path":
                folder = self._attr(child, "value", where)
                p = Path(folder)
                p = p if p.is_absolute() else file.parent / p
                if p.is_dir():
                    self.search_paths.append(p)
                else:
                    # Unlike Mitsuba (an error), a missing folder is skipped with a warning.
                    warnings.warn(f"{where}: <path> folder '{folder}' not found; ignored")
            elif tag == "include":
                if node.get("type") != "scene":
                    raise SceneError(f"{where}: <include> is only allowed directly in <scene>")
                target = self.resolve(self._attr(child, "filename", where), where, file.parent)
                self._check_include_cycle(target.resolve(), where)
                root = self._parse(target)
                if root.tag != "scene":
                    raise SceneError(f"{target}:{root.sourceline}: an included file must have a "
                                     f"<scene> root, got <{root.tag}>")
                self._upgrade(root, target, required=False)
                self.include_stack.append((target.resolve(), where))
                self._children(root, node, target)
                self.include_stack.pop()
            elif tag in PLUGIN_TAGS:
                value = self._plugin(child, file)
                if node.get("type") == "scene":
                    # Top-level objects are keyed by id; unnamed ones by type and count, which
                    # also prefixes their parameter keys (e.g. sphere_0.emitter.radiance.value).
                    key = value.get("__id__") or self._unnamed(node, value["type"])
                else:
                    key = child.get("name") or tag
                if key in node:
                    counts[key] = counts.get(key, 0) + 1
                    key = f"{key}_{counts[key]}"
                node[key] = value
            elif tag in VALUE_TAGS:
                name, value = self._value(child, where)
                if name in node:
                    raise SceneError(f"{where}: property '{name}' is given twice")
                node[name] = value
            elif tag in ("medium", "phase", "volume"):
                raise SceneError(f"{where}: <{tag}>: participating media are not supported "
                                 f"(surfaces in vacuum only)")
            else:
                raise SceneError(f"{where}: unsupported element <{tag}> (supported: "
                                 f"{', '.join(PLUGIN_TAGS + VALUE_TAGS)}, default, include, path)")

    def _check_include_cycle(self, target: Path, where: str) -> None:
        files = [f for f, _ in self.include_stack]
        if target in files:
            cycle = files[files.index(target):] + [target]
            raise SceneError(f"{where}: <include> cycle: {' -> '.join(str(f) for f in cycle)} "
                             f"(a file must not include itself, directly or indirectly)")

    @staticmethod
    def _unnamed(scene: dict, type_name: str) -> str:
        k = 0
        while f"{type_name}_{k}" in scene:
            k += 1
        return f"{type_name}_{k}"

    def _plugin(self, el, file: Path) -> dict:
        where = f"{file}:{el.sourceline}"
        node = {"type": self._attr(el, "type", where), "__where__": where, "__tag__": el.tag}
        if el.get("id") is not None:
            node["__id__"] = self._substitute(el.get("id"), where)
        self._children(el, node, file)
        return node

    def _value(self, el, where: str):
        tag = el.tag
        if tag == "ref":
            ref_id = self._attr(el, "id", where)
            name = el.get("name") or f"ref:{ref_id}"
            return name, {"type": "ref", "id": ref_id, "__where__": where}
        name = self._attr(el, "name", where)
        if tag == "transform":
            return name, self._transform(el, where)
        if tag in ("point", "vector"):
            if el.get("value") is not None:
                v = _numbers(self._attr(el, "value", where), where, name)
            else:
                v = [self._float(self._attr(el, c, where, "0"), where, f"{name}.{c}") for c in "xyz"]
            if len(v) != 3:
                raise SceneError(f"{where}: <{tag} name=\"{name}\"> needs 3 values, got {len(v)}")
            return name, v
        if tag == "spectrum":
            return name, self._spectrum(el, name, where)
        text = self._attr(el, "value", where)
        try:
            if tag == "float":
                return name, float(text)
            if tag == "integer":
                return name, int(text)
        except ValueError:
            raise SceneError(f"{where}: <{tag} name=\"{name}\">: cannot parse '{text}'") from None
        if tag == "boolean":
            if text.lower() not in ("true", "false"):
                raise SceneError(f"{where}: <boolean name=\"{name}\"> must be true or false, got '{text}'")
            return name, text.lower() == "true"
        if tag == "string":
            return name, text
        if tag == "rgb":
            v = _numbers(text, where, name)
            if len(v) not in (1, 3):
                raise SceneError(f"{where}: <rgb name=\"{name}\"> needs 1 or 3 values, got {len(v)}")
            return name, {"type": "rgb", "value": v * 3 if len(v) == 1 else v, "__where__": where}
        raise SceneError(f"{where}: unsupported value <{tag}>")

    def _spectrum(self, el, name: str, where: str) -> dict:
        """<spectrum value="0.5"/>, value="400:0.1, 700:0.5" or filename="x.spd": a dict of
        type "spectrum" (converted to RGB by the loader, which knows whether it is emitted)."""
        node = {"type": "spectrum", "__where__": where}
        if el.get("type") is not None:
            raise SceneError(f"{where}: <spectrum type=\"{el.get('type')}\">: spectrum plugins are not "
                             f"supported (RGB rendering: give a constant or wavelength:value pairs)")
        if (el.get("value") is None) == (el.get("filename") is None):
            raise SceneError(f"{where}: <spectrum name=\"{name}\"> needs either 'value' or 'filename'")
        if el.get("filename") is not None:
            node["filename"] = str(self.resolve(self._attr(el, "filename", where), where))
            return node
        text = self._attr(el, "value", where)
        try:
            if ":" in text:
                w, v = parse_pairs(text)
                node["value"] = [[a, b] for a, b in zip(w.tolist(), v.tolist())]
            else:
                node["value"] = float(text)
        except SpectrumError as e:
            raise SceneError(f"{where}: <spectrum name=\"{name}\">: {e}") from None
        except ValueError:
            raise SceneError(f"{where}: <spectrum name=\"{name}\">: cannot parse '{text}' (expected "
                             f"a number or wavelength:value pairs)") from None
        return node

    def _transform(self, el, where: str) -> Transform:
        t = Transform()
        for op in el:
            if not isinstance(op.tag, str):
                continue
            w = f"{where.rsplit(':', 1)[0]}:{op.sourceline}"
            try:
                t = self._transform_op(op, w) @ t
            except SceneError:
                raise
            except ValueError as e:  # float() of an attribute, a zero rotation axis, ...
                raise SceneError(f"{w}: <{op.tag}>: {e}") from None
        return t

    def _transform_op(self, op, w: str) -> Transform:
        """One <translate>, <scale>, <rotate>, <matrix> or <lookat> as a Transform."""
        tag = op.tag

        def xyz(default: str) -> list:
            """The operation's vector: its `value` attribute, or x, y, z (each `default`)."""
            if op.get("value") is not None:
                return _numbers(self._attr(op, "value", w), w, tag)
            return [float(self._attr(op, c, w, default)) for c in "xyz"]

        if tag == "translate":
            m = Transform.translate(xyz("0"))
        elif tag == "scale":
            v = xyz("1")
            m = Transform.scale(v * 3 if len(v) == 1 else v)
        elif tag == "rotate":
            m = Transform.rotate(xyz("0"), float(self._attr(op, "angle", w)))
        elif tag == "matrix":
            v = _numbers(self._attr(op, "value", w), w, "matrix")
            if len(v) == 9:
                mat = np.eye(4)
                mat[:3, :3] = np.reshape(v, (3, 3))
            elif len(v) == 16:
                mat = np.reshape(v, (4, 4))
            else:
                raise SceneError(f"{w}: <matrix> needs 9 or 16 values, got {len(v)}")
            m = Transform(mat)
        elif tag == "lookat":
            m = Transform.look_at(_numbers(self._attr(op, "origin", w), w, "origin"),
                                  _numbers(self._attr(op, "target", w), w, "target"),
                                  _numbers(self._attr(op, "up", w, "0, 1, 0"), w, "up"))
        else:
            raise SceneError(f"{w}: unsupported transform <{tag}> (supported: translate, "
                             f"scale, rotate, matrix, lookat)")
        return m


def read_xml(path, overrides: dict | None = None) -> dict:
    """Parse a Mitsuba 3 XML scene file into a scene dict (see module docstring)."""
    return XMLReader(path, overrides or {}).read()
