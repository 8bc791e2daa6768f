"""Differentiable 3D Gaussian rendering.

``rasterize`` is the entry point; on CPU it runs a pure-PyTorch tiled
compositor that follows gsplat's rules, on CUDA it can delegate to gsplat.
"""

from .compositor import CompositeStats, composite
from .projection import ProjectedGaussians, camera_centers, project_gaussians
from .rasterize import Backend, RenderOutput, rasterize
from .sh import eval_sh_colors, num_sh_bases, rgb_to_sh0, sh_bases

__all__ = [
    "Backend",
    "CompositeStats",
    "ProjectedGaussians",
    "RenderOutput",
    "camera_centers",
    "composite",
    "eval_sh_colors",
    "num_sh_bases",
    "project_gaussians",
    "rasterize",
    "rgb_to_sh0",
    "sh_bases",
]
