"""Differentiable 3D Gaussian splatting on the CPU (gsplat's parameterisation), and training.

`rasterize` renders; `rasterize_dense` is its slow reference; `train` fits a scene.
"""

from .dense import rasterize_dense
from .project import covariance_3d, eval_sh, project, quat_to_rotmat
from .render import rasterize

__all__ = ["rasterize", "rasterize_dense", "project", "covariance_3d", "quat_to_rotmat", "eval_sh"]
