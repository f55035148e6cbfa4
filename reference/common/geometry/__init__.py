"""Geometry shared by the reconstruction methods (`mvs`, `gaussians3d`, `sugar`, ...).

- `region`: the box around a lane's ground cameras that every method reconstructs.
- `sfm`: sparse triangulation with known poses (pycolmap) and the ground-plane fallback.
- `mvs`: dense plane-sweep stereo, consistency filtering and fusion into a `PointCloud`.
- `splat`: a fused cloud as surface discs (Gaussians), its rendering with a z-buffer-like
  front-to-back compositing, and the horizon background.
"""
