"""Shared by the fuzz targets: the error contract, the tiny render, atheris set-up.

The contract (what the loaders promise today): any input either loads, or raises the
loader's own error type -- `SceneError` for scenes (load_file, load_dict), `MeshError` for
load_obj / load_ply, `ImageError` for read_image; all three are ValueErrors -- with a
message that names the culprit (the file, or "<dict>" and the plugin, for dict scenes).
Anything else (IndexError, KeyError, TypeError, a bare ValueError from numpy, RecursionError,
a crash, a hang) is a finding: the target re-raises it and libFuzzer stops and saves the
input.
"""
import os
import sys
import tempfile

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before torch and the extension load

import atheris  # noqa: E402

# Import the heavy dependencies uninstrumented (instrumenting torch would take minutes),
# then instrument only our package.
import lxml.etree  # noqa: E402,F401
import numpy  # noqa: E402,F401
import plyfile  # noqa: E402,F401
import torch  # noqa: E402

with atheris.instrument_imports(include=["torch_rbpt"]):
    import torch_rbpt as tr
    from torch_rbpt import meshes, images  # noqa: F401

torch.set_num_threads(1)

# Cheap render settings: legitimate but expensive values are capped by the harness (a
# scene with max_depth=10**6 in a closed white box is slow, not wrong); values that do not
# fit the renderer's 32-bit ints are left alone, so that the render boundary sees them.
MAX_DEPTH, MAX_SAMPLES, INT32 = 8, 4, 2 ** 31 - 1


class UnclearError(AssertionError):
    """An expected exception type whose message does not name the culprit."""


def check_error(exc: BaseException, allowed: tuple, names: tuple) -> None:
    """Re-raise `exc` unless it is one of `allowed` and its message contains one of `names`."""
    if not isinstance(exc, allowed):
        raise exc
    message = str(exc)
    if not any(n in message for n in names):
        raise UnclearError(f"{type(exc).__name__} does not name any of {names}: {message}") from exc


def render_tiny(scene) -> None:
    """Render `scene` at 4x4, 1 spp; any exception here is a finding."""
    film = scene.sensor.film
    film.width = film.height = 4
    film.crop = None
    integ = scene.integrator
    if -1 <= integ.max_depth <= INT32:
        integ.max_depth = MAX_DEPTH if integ.max_depth == -1 else min(integ.max_depth, MAX_DEPTH)
    if 0 <= integ.rr_depth <= INT32:
        integ.rr_depth = min(integ.rr_depth, MAX_DEPTH)
    for name in ("emitter_samples", "bsdf_samples"):
        value = getattr(integ, name)
        if 0 <= value <= INT32:
            setattr(integ, name, min(value, MAX_SAMPLES))
    image = tr.render(scene, spp=1)
    assert image.shape == (4, 4, 3), image.shape


def workdir() -> str:
    """A per-process folder holding the tiny assets that fuzzed scenes may refer to."""
    folder = tempfile.mkdtemp(prefix="rbpt_fuzz_")
    import seeds
    seeds.write_assets(folder)
    return folder


def main(test_one_input) -> None:
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()



def scene_with_mesh(kind: str, path: str, face_normals: bool) -> dict:
    """A dict scene: the mesh file in front of the camera, lit by a point light."""
    return {"type": "scene",
            "sensor": {"type": "perspective", "fov": 60,
                       "to_world": tr.Transform.look_at([0.3, 0.4, 3], [0.3, 0.4, 0], [0, 1, 0])},
            "mesh": {"type": kind, "filename": path, "face_normals": face_normals},
            "light": {"type": "point", "position": [0, 0, 2]}}


def check_mesh(data: bytes, path: str, load, kind: str) -> None:
    """The mesh target body: load, check the Mesh invariants, load as a scene and render."""
    flags = data[0] if data else 0
    face_normals, flip = bool(flags & 1), bool(flags & 2)
    with open(path, "wb") as f:
        f.write(data[1:])
    try:
        mesh = load(path, face_normals=face_normals, flip_tex_coords=flip)
    except Exception as e:
        check_error(e, (meshes.MeshError,), (path,))
        return
    n = mesh.vertex_count
    assert mesh.faces.shape[1] == 3 and mesh.faces.size and 0 <= mesh.faces.min() <= mesh.faces.max() < n
    assert (mesh.normals is None) == face_normals
    # Through the scene loader (the mesh is already known to load) and the renderer.
    scene = tr.load_dict(scene_with_mesh(kind, path, face_normals))
    render_tiny(scene)
