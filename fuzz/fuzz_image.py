"""Fuzz the image reader: `read_image` on the input's bytes after the first, written to a
file whose extension the first byte picks (.png, .exr, .jpg). Images that load are used
as a bitmap texture in a tiny scene rendered at 4x4, 1 spp.
Contract: see common.py (ImageError naming the file)."""
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402
import torch  # noqa: E402
from common import images, tr  # noqa: E402
from seeds import IMAGE_SUFFIXES  # noqa: E402

FOLDER = common.workdir()


def test_one_input(data: bytes) -> None:
    if not data:
        return
    path = os.path.join(FOLDER, "image" + IMAGE_SUFFIXES[data[0] % len(IMAGE_SUFFIXES)])
    with open(path, "wb") as f:
        f.write(data[1:])
    raw = bool(data[0] & 0x80)
    try:
        image = images.read_image(path, raw=raw)
    except Exception as e:
        common.check_error(e, (images.ImageError,), (path,))
        return
    assert image.dtype == torch.float32 and image.ndim == 3, image.shape
    assert min(image.shape) > 0, image.shape
    try:
        scene = tr.load_dict(scene_with_bitmap(path, raw))
    except Exception as e:  # the loader may refuse what read_image accepts, clearly
        common.check_error(e, (tr.SceneError,), (path,))
        return
    common.render_tiny(scene)


def scene_with_bitmap(path: str, raw: bool) -> dict:
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 60,
                   "to_world": tr.Transform.look_at([0, 0, 3], [0, 0, 0], [0, 1, 0])},
        "wall": {"type": "rectangle",
                 "bsdf": {"type": "diffuse",
                          "reflectance": {"type": "bitmap", "filename": path, "raw": raw}}},
        "light": {"type": "constant"}}


if __name__ == "__main__":
    common.main(test_one_input)
