"""Fuzz the Mitsuba XML loader: `load_file` on the input written as scene.xml in a folder
holding tri.obj, tri.ply, tex.png, tex.exr and part.xml. Loaded scenes are rendered at
4x4, 1 spp. Contract: see common.py (SceneError naming the scene file)."""
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402
from common import tr  # noqa: E402

FOLDER = common.workdir()
SCENE = os.path.join(FOLDER, "scene.xml")


def test_one_input(data: bytes) -> None:
    with open(SCENE, "wb") as f:
        f.write(data)
    try:
        scene = tr.load_file(SCENE)
    except Exception as e:
        # Errors name the scene file, or the included / referenced file they come from.
        common.check_error(e, (tr.SceneError,), (FOLDER,))
        return
    common.render_tiny(scene)


if __name__ == "__main__":
    common.main(test_one_input)
