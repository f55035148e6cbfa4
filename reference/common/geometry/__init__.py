"""Geometry shared by the reconstruction methods (`mvs`, `gaussians3d`, `sugar`, ...).

- `region`: the box around a lane's ground cameras that every method reconstructs.
- `sfm`: sparse triangulation with known poses (pycolmap) and the ground-plane fallback.
- `mvs`: dense plane-sweep stereo, consistency filtering and fusion into a `PointCloud`;
  `sweep`: its cost volume (NCC, best-k over sources, SGM, sub-plane winner).
- `cloud`: the fused `PointCloud` and the street prior on it (`ground_height`, `snap_to_plane`).
- `splat`: a fused cloud as surface discs (Gaussians), its rendering with a z-buffer-like
  front-to-back compositing, and the horizon background.
"""
