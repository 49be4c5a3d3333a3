"""torch_rbpt: a physically based differentiable path tracer for PyTorch.

Load Mitsuba 3 scenes with `load_file` / `load_dict`, read and edit their parameters in
`scene.params`, and render them with `render`.
"""
import torch  # noqa: F401  (loads libtorch before the extension)

from . import _C, ops  # noqa: F401  (ops registers the torch.ops.torch_rbpt operators)
from .images import read_image, write_image
from .loader import load_dict, load_file
from .mitsuba_xml import SceneError
from .render import render, render_forward
from .scene import Scene, SceneParams
from .transform import Transform

__all__ = ["load_file", "load_dict", "render", "render_forward", "read_image", "write_image", "Scene",
           "SceneParams", "SceneError", "Transform"]
__version__ = "0.1.0"
