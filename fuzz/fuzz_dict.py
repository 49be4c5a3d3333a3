"""Fuzz the dict loader: `load_dict` on dicts built from the input with a
FuzzedDataProvider. The first byte chooses between mutating the bundled Cornell box (as
read from torch_rbpt/scenes/cornell_box.xml) and building a scene from scratch; values
include nested plugins, refs, rgb dicts, wrong types, lists, arrays, tensors, Transforms,
NaN and huge numbers. Loaded scenes are rendered at 4x4, 1 spp. Relative file names
resolve in a folder holding tri.obj, tri.ply, tex.png, tex.exr.
Contract: see common.py (SceneError naming "<dict>")."""
import copy
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402
from common import atheris, tr  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torch_rbpt.loader import CATEGORY, PROPERTIES  # noqa: E402
from torch_rbpt.mitsuba_xml import read_xml  # noqa: E402
from seeds import BUNDLED  # noqa: E402

FOLDER = common.workdir()
TYPES = sorted(CATEGORY) + ["rgb", "ref", "scene", "plastic", ""]
KEYS = sorted(set().union(*PROPERTIES.values())) + [
    "type", "id", "value", "bsdf", "emitter", "film", "rfilter", "sampler", "texture", "brdf_0",
    "shading_samples", "emitter_samples", "bsdf_samples", "nested"]
STRINGS = ["true", "false", "none", "ggx", "beckmann", "x", "y", "diagonal", "smaller",
           "larger", "bilinear", "nearest", "repeat", "mirror", "clamp", "bk7", "air", "water",
           "50mm", "12", "mm", "tri.obj", "tri.ply", "tex.png", "tex.exr", "part.xml",
           "missing.obj", FOLDER, "red", "white", "light", "sensor", "$res"]
SPECIAL_FLOATS = [0.0, -0.0, 1.0, -1.0, 0.5, 1e-30, 1e30, 1e308, math.inf, -math.inf, math.nan]
IDS = ["red", "white", "box", "black", "green", "light", "sensor", "nothing", "m0", "m1"]


def bundled() -> dict:
    """The bundled Cornell box as a plain user dict (no private "__" entries), 8x8 pixels."""
    def strip(node):
        if isinstance(node, dict):
            return {k: strip(v) for k, v in node.items() if not k.startswith("__")}
        return node
    return strip(read_xml(BUNDLED, {"res": "8", "spp": "1"}))


BUNDLED_DICT = bundled()


class Gen:
    def __init__(self, data: bytes):
        self.fdp = atheris.FuzzedDataProvider(data)

    def pick(self, seq):
        return seq[self.fdp.ConsumeIntInRange(0, len(seq) - 1)]

    def number(self):
        kind = self.fdp.ConsumeIntInRange(0, 4)
        if kind == 0:
            return self.fdp.ConsumeIntInRange(-3, 20)
        if kind == 1:
            return self.fdp.ConsumeIntInRange(-2 ** 70, 2 ** 70)
        if kind == 2:
            return self.pick(SPECIAL_FLOATS)
        if kind == 3:
            return self.fdp.ConsumeFloat()
        return self.fdp.ConsumeFloatInRange(-4.0, 4.0)

    def value(self, depth: int):
        kind = self.fdp.ConsumeIntInRange(0, 13)
        if kind <= 2:
            return self.number()
        if kind == 3:
            return self.fdp.ConsumeBool()
        if kind == 4:
            return self.pick(STRINGS) if self.fdp.ConsumeBool() else self.fdp.ConsumeUnicodeNoSurrogates(6)
        if kind == 5:
            return [self.number() for _ in range(self.fdp.ConsumeIntInRange(0, 5))]
        if kind == 6 and depth > 0:
            return self.plugin(depth - 1)
        if kind == 7:
            return {"type": "rgb", "value": self.value(0) if self.fdp.ConsumeBool()
                    else [self.number() for _ in range(3)]}
        if kind == 8:
            return {"type": "ref", "id": self.pick(IDS)}
        if kind == 9:
            shape = [self.fdp.ConsumeIntInRange(0, 4) for _ in range(self.fdp.ConsumeIntInRange(0, 3))]
            array = np.array([self.number() for _ in range(int(np.prod(shape)))], dtype=np.float64)
            array = array.reshape(shape)
            return torch.from_numpy(array) if self.fdp.ConsumeBool() else array
        if kind == 10:
            m = np.eye(4)
            m[self.fdp.ConsumeIntInRange(0, 3), self.fdp.ConsumeIntInRange(0, 3)] = self.number()
            return tr.Transform(m)
        if kind == 11:
            return None
        if kind == 12:
            return {"value": self.value(0)} if self.fdp.ConsumeBool() else {"type": self.value(0)}
        return tuple(self.number() for _ in range(self.fdp.ConsumeIntInRange(0, 4)))

    def plugin(self, depth: int) -> dict:
        t = self.pick(TYPES)
        node = {"type": t}
        own = sorted(PROPERTIES.get(t, ())) or KEYS
        for _ in range(self.fdp.ConsumeIntInRange(0, 4)):
            key = self.pick(own) if self.fdp.ConsumeBool() else self.pick(KEYS)
            node[key] = self.value(depth)
        return node

    def scene_from_scratch(self) -> dict:
        scene = {"type": "scene"}
        for k in range(self.fdp.ConsumeIntInRange(0, 5)):
            scene[self.pick(IDS) if self.fdp.ConsumeBool() else f"o{k}"] = self.plugin(2)
        return scene

    def mutate(self, scene: dict) -> dict:
        for _ in range(self.fdp.ConsumeIntInRange(1, 4)):
            node = scene
            while True:  # walk down to a random dict
                children = [v for v in node.values() if isinstance(v, dict)]
                if not children or self.fdp.ConsumeIntInRange(0, 2) == 0:
                    break
                node = self.pick(children)
            op = self.fdp.ConsumeIntInRange(0, 3)
            keys = list(node)
            if op == 0 and keys:
                del node[self.pick(keys)]
            elif op == 1 and keys:
                node[self.pick(keys)] = self.value(2)
            elif op == 2:
                node["type"] = self.pick(TYPES)
            else:
                node[self.pick(KEYS)] = self.value(2)
        return scene


def test_one_input(data: bytes) -> None:
    gen = Gen(data)
    if gen.fdp.ConsumeIntInRange(0, 1) == 0:
        scene_dict = gen.mutate(copy.deepcopy(BUNDLED_DICT))
    else:
        scene_dict = gen.scene_from_scratch()
    try:
        scene = tr.load_dict(scene_dict, base_dir=FOLDER)
    except Exception as e:
        common.check_error(e, (tr.SceneError,), ("<dict>",))
        return
    common.render_tiny(scene)


if __name__ == "__main__":
    common.main(test_one_input)
