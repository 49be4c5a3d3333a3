"""Fuzz the PLY loader: `load_ply` on the input written as mesh.ply (the first byte picks
face_normals / flip_tex_coords), then the mesh in a tiny scene rendered at 4x4, 1 spp.
Contract: see common.py (MeshError naming the file)."""
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402
from common import meshes  # noqa: E402

FOLDER = common.workdir()
MESH = os.path.join(FOLDER, "mesh.ply")


def test_one_input(data: bytes) -> None:
    common.check_mesh(data, MESH, meshes.load_ply, "ply")


if __name__ == "__main__":
    common.main(test_one_input)
