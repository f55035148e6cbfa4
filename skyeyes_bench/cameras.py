"""One camera convention for the whole project, and converters from the simulators'.

World: right-handed, metres, z up. Camera: OpenCV (x right, y down, z forward). `c2w` is a
4x4 float64 camera-to-world matrix; `K` is 3x3 with (fx, fy, cx, cy) in pixels. Pixel (row i,
column j) covers [j, j+1) x [i, i+1) in image coordinates, so its centre is (j + 0.5, i + 0.5).
Depth is planar (camera z), not distance along the ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import UserError

#: OpenCV camera axes written in a right-handed body frame (x forward, y left, z up):
#: columns are camera x (right = -y), camera y (down = -z), camera z (forward = +x).
_BODY_TO_CV = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def focal_from_fov(fov_deg: float, size: int) -> float:
    """f = size / (2 tan(fov / 2)), the pinhole focal length in pixels for a field of view."""
    if not 0.0 < fov_deg < 180.0:
        raise UserError(f"field of view {fov_deg} deg: expected 0 < fov < 180")
    return size / (2.0 * np.tan(np.deg2rad(fov_deg) / 2.0))


def intrinsics(fov_deg: float, width: int, height: int) -> np.ndarray:
    """K [3, 3] for a horizontal field of view, square pixels, principal point at the centre."""
    f = focal_from_fov(fov_deg, width)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rotation_from_ypr(yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """OpenCV camera-to-world rotation [3, 3] in the right-handed z-up world.

    yaw: heading, counter-clockwise from +x seen from above; pitch: positive looks up
    (-90 = nadir); roll: right-handed about the viewing direction. Composed from elementary
    rotations (no look-at cross products), so pitch +-90 deg is exact, not degenerate.
    """
    y, p, r = np.deg2rad([yaw_deg, pitch_deg, roll_deg])
    return _rz(y) @ _ry(-p) @ _rx(r) @ _BODY_TO_CV


def rigid_problem(c2w: np.ndarray, tol: float = 1e-4) -> str | None:
    """None if `c2w` [4, 4] is a rigid transform, else what is wrong with it."""
    m = np.asarray(c2w, dtype=np.float64)
    if m.shape != (4, 4):
        return f"shape {m.shape}, expected (4, 4)"
    if not np.all(np.isfinite(m)):
        return "contains NaN or inf"
    if not np.allclose(m[3], [0, 0, 0, 1], atol=tol):
        return f"last row {m[3].tolist()}, expected [0, 0, 0, 1]"
    r = m[:3, :3]
    err = np.abs(r.T @ r - np.eye(3)).max()
    if err > tol:
        return f"rotation is not orthonormal (max |R^T R - I| = {err:.2g})"
    det = np.linalg.det(r)
    if det < 0:
        return f"rotation has det {det:.3f} (a reflection; expected +1, right-handed)"
    return None


@dataclass(frozen=True)
class Camera:
    """A pinhole camera. K [3, 3], c2w [4, 4] (OpenCV axes, metres), size in pixels."""

    K: np.ndarray  # [3, 3]
    c2w: np.ndarray  # [4, 4]
    width: int
    height: int

    def __post_init__(self):
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "c2w", np.asarray(self.c2w, dtype=np.float64).reshape(4, 4))

    # ---------------------------------------------------------------- constructors
    @classmethod
    def from_ypr(cls, position, yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0, *,
                 fov_deg: float, width: int, height: int) -> "Camera":
        """Camera at `position` [3] (metres, our world) with yaw/pitch/roll in degrees."""
        c2w = np.eye(4)
        c2w[:3, :3] = rotation_from_ypr(yaw_deg, pitch_deg, roll_deg)
        c2w[:3, 3] = np.asarray(position, dtype=np.float64)
        return cls(intrinsics(fov_deg, width, height), c2w, width, height)

    # ---------------------------------------------------------------- properties
    @property
    def w2c(self) -> np.ndarray:  # [4, 4]
        r, t = self.c2w[:3, :3], self.c2w[:3, 3]
        out = np.eye(4)
        out[:3, :3] = r.T
        out[:3, 3] = -r.T @ t
        return out

    @property
    def center(self) -> np.ndarray:  # [3]
        return self.c2w[:3, 3].copy()

    @property
    def forward(self) -> np.ndarray:  # [3] unit viewing direction
        return self.c2w[:3, 2].copy()

    @property
    def fov_x_deg(self) -> float:
        return float(np.rad2deg(2 * np.arctan(self.width / (2 * self.K[0, 0]))))

    def with_size(self, width: int, height: int) -> "Camera":
        """The same camera at another resolution (intrinsics scaled)."""
        s = np.diag([width / self.width, height / self.height, 1.0])
        return Camera(s @ self.K, self.c2w, width, height)

    # ---------------------------------------------------------------- geometry
    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N, 3] -> pixel coordinates uv [N, 2] and planar depth z [N].

        Points behind the camera (z <= 0) get uv = NaN; check `z > 0` before using uv.
        """
        pts = np.asarray(points, dtype=np.float64)
        assert pts.ndim == 2 and pts.shape[1] == 3, pts.shape  # [N, 3]
        cam = (pts - self.c2w[:3, 3]) @ self.c2w[:3, :3]  # [N, 3] = R^T (p - t), row-wise
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = cam[:, :2] / np.where(z > 0, z, np.nan)[:, None]
        uv = xy @ self.K[:2, :2].T + self.K[:2, 2]
        return uv, z

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixel coordinates uv [N, 2] with planar depth [N] -> world points [N, 3]."""
        uv = np.asarray(uv, dtype=np.float64)
        depth = np.asarray(depth, dtype=np.float64)
        assert uv.ndim == 2 and uv.shape[1] == 2 and depth.shape == (uv.shape[0],), (uv.shape, depth.shape)
        d = self._camera_dirs(uv)  # [N, 3] with z = 1
        return (d * depth[:, None]) @ self.c2w[:3, :3].T + self.c2w[:3, 3]

    def pixel_centers(self) -> np.ndarray:
        """uv [H*W, 2] of every pixel centre, row-major (row i, column j -> i * W + j)."""
        j, i = np.meshgrid(np.arange(self.width), np.arange(self.height))
        return np.stack([j.ravel() + 0.5, i.ravel() + 0.5], axis=1).astype(np.float64)

    def rays(self, uv: np.ndarray | None = None, *, normalize: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Ray origins [N, 3] and directions [N, 3] in world space (all pixel centres by default).

        With normalize=False the directions have camera z = 1, so `t` along them is planar depth.
        """
        uv = self.pixel_centers() if uv is None else np.asarray(uv, dtype=np.float64)
        d = self._camera_dirs(uv) @ self.c2w[:3, :3].T
        if normalize:
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(self.c2w[:3, 3], d.shape).copy()
        return o, d

    def _camera_dirs(self, uv: np.ndarray) -> np.ndarray:  # [N, 2] -> [N, 3], z = 1
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        x = (uv[:, 0] - cx) / fx
        y = (uv[:, 1] - cy) / fy
        return np.stack([x, y, np.ones_like(x)], axis=1)

    # ---------------------------------------------------------------- serialisation
    def intrinsics_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": float(self.K[0, 0]),
                "fy": float(self.K[1, 1]), "cx": float(self.K[0, 2]), "cy": float(self.K[1, 2])}


def K_from_dict(d: dict) -> np.ndarray:
    return np.array([[d["fx"], 0.0, d["cx"]], [0.0, d["fy"], d["cy"]], [0.0, 0.0, 1.0]], dtype=np.float64)


# --------------------------------------------------------------------------- CARLA

#: Flip of the world y axis: CARLA/UE4's left-handed world -> our right-handed one.
FLIP_Y = np.diag([1.0, -1.0, 1.0])


def carla_matrix(location, rotation) -> np.ndarray:
    """CARLA's `Transform.get_matrix()` [4, 4] for location (x, y, z) in metres and rotation
    (pitch, yaw, roll) in degrees. Columns of the rotation: forward, right, up (left-handed).

    NOTE: formula of carla::geom::Transform::GetMatrix (LibCarla/source/carla/geom/Transform.h).
    """
    pitch, yaw, roll = np.deg2rad(np.asarray(rotation, dtype=np.float64))
    cy, sy, cr, sr, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    m = np.eye(4)
    m[:3, :3] = [
        [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
        [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
        [sp, -cp * sr, cp * cr],
    ]
    m[:3, 3] = np.asarray(location, dtype=np.float64)
    return m


def carla_points_to_world(points: np.ndarray) -> np.ndarray:
    """CARLA world points [N, 3] -> our right-handed world (y negated)."""
    return np.asarray(points, dtype=np.float64) @ FLIP_Y


def from_carla(location, rotation, fov_deg: float, width: int, height: int) -> Camera:
    """A CARLA camera (location m, rotation (pitch, yaw, roll) deg, horizontal fov) -> Camera.

    OpenCV c2w in CARLA's world is M @ P with P's columns [right, -up, forward]; that has
    det -1 because CARLA's world is left-handed, so the world's y is flipped (on poses and on
    points, see `carla_points_to_world`), giving det +1.
    """
    m = carla_matrix(location, rotation)
    r_cv = np.stack([m[:3, 1], -m[:3, 2], m[:3, 0]], axis=1)  # columns: right, -up, forward
    c2w = np.eye(4)
    c2w[:3, :3] = FLIP_Y @ r_cv
    c2w[:3, 3] = FLIP_Y @ m[:3, 3]
    return Camera(intrinsics(fov_deg, width, height), c2w, width, height)


# --------------------------------------------------------------------------- MatrixCity

#: NeRF / OpenGL camera (x right, y up, z back) <-> OpenCV: negate camera y and z.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def from_matrixcity(transform_matrix, *, pose_format: str = "paper", convention: str = "opengl",
                    fov_deg: float | None = None, K=None, width: int, height: int) -> Camera:
    """A MatrixCity / CitySample pose -> Camera.

    Args:
        transform_matrix: [4, 4] c2w as stored in the JSON ("transform_matrix" / "rot_mat").
        pose_format: "raw" (MatrixCity capture `transforms.json`: the rotation is stored scaled by
            0.01, position in metres) or "paper" (the paper-split `transforms_*.json`: positions in
            units of 100 m, rotation orthonormal).
        convention: "opengl" (NeRF: x right, y up, z back; MatrixCity's default) or "opencv".
        fov_deg / K: horizontal field of view, or explicit intrinsics [3, 3].
    """
    m = np.array(transform_matrix, dtype=np.float64).reshape(4, 4)
    if pose_format == "raw":
        m[:3, :3] *= 100.0  # NOTE: MatrixCity stores rot_mat x 0.01 (UE centimetre scale).
    elif pose_format == "paper":
        m[:3, 3] *= 100.0  # NOTE: paper-split poses are in units of 100 m.
    else:
        raise UserError(f"MatrixCity pose format {pose_format!r}: expected 'raw' or 'paper'")
    if convention == "opengl":
        m = m @ GL_TO_CV
    elif convention != "opencv":
        raise UserError(f"camera convention {convention!r}: expected 'opengl' or 'opencv'")
    problem = rigid_problem(m, tol=1e-3)
    if problem:
        raise UserError(f"MatrixCity pose ({pose_format}): {problem}")
    # Re-orthonormalise the rotation (the files hold ~6 significant digits).
    u, _, vt = np.linalg.svd(m[:3, :3])
    m[:3, :3] = u @ vt
    if K is None:
        if fov_deg is None:
            raise UserError("from_matrixcity: give fov_deg or K")
        K = intrinsics(fov_deg, width, height)
    return Camera(np.asarray(K, dtype=np.float64), m, width, height)
