"""Rigid camera poses and the rotation conventions every file uses (brief, section 3).

A Pose stores T_CW (X_c = R X_w + t), OpenCV's convention, so it can be handed to
any OpenCV function unchanged.  Files speak of the camera centre and the camera
orientation R_WC, plus REP-103 roll/pitch/yaw of the camera *body* frame
(x forward along the optical axis, y left, z up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Columns of R_CB are the body axes (x fwd, y left, z up) written in the camera frame
# (x right, y down, z forward).
R_CB = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def rodrigues(rvec) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis * angle), vectorised-friendly, no OpenCV."""
    r = np.asarray(rvec, dtype=float).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        k = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
        return np.eye(3) + k
    k = r / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * (kx @ kx)


def rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (inverse of `rodrigues`), stable near 0 and pi."""
    q = quat_from_matrix(R)
    w, v = q[0], q[1:]
    s = np.linalg.norm(v)
    if s < 1e-15:
        return 2.0 * v  # small-angle limit
    angle = 2.0 * np.arctan2(s, w)
    if angle > np.pi:
        angle -= 2 * np.pi
    return v / s * angle


def rotvecs(R: np.ndarray) -> np.ndarray:
    """`rotvec` over a stack of rotation matrices (..., 3, 3) -> (..., 3), stable near 0 and
    pi: the smoother takes the logs of a whole window at once."""
    R = np.asarray(R, float)
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    a = np.arccos(c)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], axis=-1)  # fmt: skip
    sa = np.sin(a)
    f = np.where(a < 1e-6, 0.5, a / (2 * np.where(sa > 1e-12, sa, 1.0)))
    out = w * f[..., None]
    near = np.pi - a < 1e-4
    for i in np.ndindex(a.shape) if near.any() else ():  # the axis from R + I
        if not near[i]:
            continue
        B = (R[i] + np.eye(3)) / 2
        axis = B[np.argmax(np.diag(B))]
        axis = axis / np.linalg.norm(axis)
        out[i] = a[i] * axis * (1 if axis @ w[i] >= 0 else -1)
    return out


def rodrigues_many(w: np.ndarray) -> np.ndarray:
    """`rodrigues` over a stack of rotation vectors (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, float)
    a = np.linalg.norm(w, axis=-1)[..., None, None]
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    small = a < 1e-9
    safe = np.where(small, 1.0, a)
    s1 = np.where(small, 1.0, np.sin(safe) / safe)
    s2 = np.where(small, 0.5, (1 - np.cos(safe)) / safe**2)
    return np.eye(3) + s1 * K + s2 * (K @ K)


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w >= 0 of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    diag = np.array([tr, R[0, 0], R[1, 1], R[2, 2]])
    i = int(np.argmax(diag))
    if i == 0:
        s = np.sqrt(1.0 + tr) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif i == 1:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif i == 2:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def matrix_from_quat(q) -> np.ndarray:
    """Rotation matrix of a quaternion (w, x, y, z); the quaternion is normalised first."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll): REP-103 fixed-axis X-Y-Z (= intrinsic Z-Y-X), radians."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def rpy_from_matrix(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    pitch = float(np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0])))
    roll = float(np.arctan2(R[2, 1], R[2, 2]))
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return roll, pitch, yaw


def look_at(center, target, up=(0.0, 0.0, 1.0)) -> Pose:
    """Pose of a level camera at `center` whose optical axis points at `target`."""
    c = np.asarray(center, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:  # looking straight up/down: any x will do
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_wc = np.column_stack([x, y, z])
    return Pose.from_center(R_wc, c)


@dataclass(frozen=True)
class Pose:
    """Camera pose T_CW: a world point X_w maps to camera coordinates R @ X_w + t."""

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "R", np.asarray(self.R, dtype=float).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=float).reshape(3))

    # --- constructors -------------------------------------------------------------------
    @classmethod
    def identity(cls) -> Pose:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_rvec_tvec(cls, rvec, tvec) -> Pose:
        return cls(rodrigues(rvec), np.asarray(tvec, float).reshape(3))

    @classmethod
    def from_center(cls, R_wc, center) -> Pose:
        """From camera orientation R_WC and camera centre C in W."""
        R = np.asarray(R_wc, float).T
        return cls(R, -R @ np.asarray(center, float).reshape(3))

    @classmethod
    def from_center_quat(cls, center, q_wxyz) -> Pose:
        return cls.from_center(matrix_from_quat(q_wxyz), center)

    @classmethod
    def from_center_rpy(cls, center, roll_deg, pitch_deg, yaw_deg) -> Pose:
        R_wb = matrix_from_rpy(*np.radians([roll_deg, pitch_deg, yaw_deg]))
        return cls.from_center(R_wb @ R_CB.T, center)

    @classmethod
    def from_matrix(cls, T) -> Pose:
        T = np.asarray(T, float)
        return cls(T[:3, :3], T[:3, 3])

    # --- conversions --------------------------------------------------------------------
    @property
    def rvec(self) -> np.ndarray:
        return rotvec(self.R)

    @property
    def tvec(self) -> np.ndarray:
        return self.t.copy()

    @property
    def R_wc(self) -> np.ndarray:
        return self.R.T

    @property
    def center(self) -> np.ndarray:
        """Camera centre in W."""
        return -self.R.T @ self.t

    @property
    def quat_wxyz(self) -> np.ndarray:
        """Unit quaternion of R_WC (camera orientation in W), w >= 0."""
        return quat_from_matrix(self.R.T)

    @property
    def rpy_deg(self) -> np.ndarray:
        """REP-103 roll, pitch, yaw (degrees) of the camera body frame in W."""
        return np.degrees(rpy_from_matrix(self.R.T @ R_CB))

    @property
    def azimuth_deg(self) -> float:
        """Bearing of the camera centre around the landmark, in (-180, 180]."""
        c = self.center
        a = float(np.degrees(np.arctan2(c[1], c[0])))
        return 180.0 if a <= -180.0 else a

    @property
    def matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T

    # --- algebra ------------------------------------------------------------------------
    def __matmul__(self, other: Pose) -> Pose:
        """Composition: (self @ other) maps through `other` first, then `self`."""
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def inverse(self) -> Pose:
        return Pose(self.R.T, -self.R.T @ self.t)

    def transform(self, X) -> np.ndarray:
        """Apply to points (N,3): world -> camera coordinates."""
        return np.asarray(X, float) @ self.R.T + self.t

    def angle_to(self, other: Pose) -> float:
        """Rotation angle (degrees) between two orientations."""
        c = (np.trace(self.R @ other.R.T) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))

    def distance_to(self, other: Pose) -> float:
        """Distance (m) between the two camera centres."""
        return float(np.linalg.norm(self.center - other.center))

    def __repr__(self) -> str:
        c = np.round(self.center, 4).tolist()
        return f"Pose(center={c}, rpy_deg={np.round(self.rpy_deg, 3).tolist()})"
