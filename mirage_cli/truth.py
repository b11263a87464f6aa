"""Ground truth for `mirage report`: a pose CSV, a TUM file or a ROS bag pose topic, moved
from the tracked body to the camera and associated with the pose frames.

Motion capture tracks a marker body, not the camera: the truth file holds T_W_body and a
fixed, calibrated T_body_camera gives T_W_camera = T_W_body * T_body_camera (brief,
section 3: W the landmark's frame, C OpenCV's camera frame). Truth with frame ids (a pose
CSV) is joined by frame; truth with only times (TUM, a bag) is associated like evo does:
the nearest truth stamp within `t_max_diff_s`, after `t_offset_s` is added to the truth
stamps. Frames without truth are left out of the truth errors, and counted.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from . import validate
from .bags import is_bag_path, read_poses
from .errors import InputError
from .records import Status
from .trajectory import derived_angles, guess_format, match_times, read_trajectory

IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class BodyToCamera:
    """T_body_camera: the camera centre in the body frame (m) and the unit quaternion
    (w, x, y, z) of R_body_camera (maps OpenCV camera-frame vectors to body vectors)."""

    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    q: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))

    @property
    def is_identity(self) -> bool:
        return not self.t.any() and abs(abs(self.q[0]) - 1.0) < 1e-15

    @classmethod
    def parse(cls, text: str | None) -> BodyToCamera:
        """`x y z qw qx qy qz` (spaces or commas), or a file holding that one line ('#'
        comments allowed); None is the identity."""
        if text is None:
            return cls()
        src = str(text)
        p = Path(src).expanduser()
        where = "--truth-transform"
        if p.is_file():
            lines = [ln.split("#")[0].strip() for ln in p.read_text(errors="replace").splitlines()]
            lines = [ln for ln in lines if ln]
            src, where = (lines[0] if len(lines) == 1 else ""), f"--truth-transform file {p}"
        try:
            v = np.array([float(w) for w in src.replace(",", " ").split()])
        except ValueError:
            v = np.array([])
            looks_like_file = not any(c.isspace() or c == "," for c in src) and (
                "/" in src or "\\" in src or Path(src).suffix != ""
            )
            if where == "--truth-transform" and looks_like_file and not p.exists():
                raise InputError(
                    f"--truth-transform file {src} not found (or give the transform itself: "
                    "'x y z qw qx qy qz')"
                ) from None
        if v.size != 7 or not np.isfinite(v).all():
            raise InputError(
                f"{where}: expected 7 numbers 'x y z qw qx qy qz' (T_body_camera, metres), "
                f"got {str(text)[:60]!r}"
            )
        n = float(np.linalg.norm(v[3:]))
        if not abs(n - 1.0) <= validate.QUAT_TOL:
            raise InputError(
                f"{where}: the quaternion qw qx qy qz has norm {n:.4g}; expected a unit "
                f"quaternion (norm 1 +- {validate.QUAT_TOL:g})"
            )
        return cls(v[:3], v[3:] / n)


@dataclass(frozen=True)
class TruthSettings:
    topic: str | None = None  # bag pose topic; None: the bag's only one
    body_to_camera: BodyToCamera = field(default_factory=BodyToCamera)
    t_offset_s: float = 0.0  # added to the truth stamps before matching
    t_max_diff_s: float = 0.01  # evo's default association tolerance


def _rot(q: np.ndarray) -> np.ndarray:
    """(N,3,3) rotation matrices of unit quaternions (N,4) w, x, y, z."""
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a * b of quaternion rows (w, x, y, z)."""
    aw, ax, ay, az = np.moveaxis(np.atleast_2d(a), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.atleast_2d(b), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def body_to_camera(df: pd.DataFrame, T: BodyToCamera) -> pd.DataFrame:
    """Truth rows of T_W_body turned into T_W_camera = T_W_body * T_body_camera: centre
    c_W + R_W_body t, orientation q_W_body * q_body_camera (angles re-derived)."""
    if T.is_identity:
        return df
    out = df.copy()
    ok = (out["status"] == Status.OK).to_numpy()
    c = out.loc[ok, ["x_m", "y_m", "z_m"]].to_numpy(float)
    q = out.loc[ok, ["qw", "qx", "qy", "qz"]].to_numpy(float)
    c = c + _rot(q) @ T.t
    q = _qmul(q, T.q)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)  # one sign convention: w >= 0
    out.loc[ok, ["x_m", "y_m", "z_m"]] = c
    out.loc[ok, ["qw", "qx", "qy", "qz"]] = q
    if ok.any():
        out.loc[ok, ["roll_deg", "pitch_deg", "yaw_deg", "azimuth_deg"]] = derived_angles(c, q)
    return out


def load_truth(path, poses: pd.DataFrame, s: TruthSettings = TruthSettings()) -> pd.DataFrame:
    """Truth camera poses renamed to the frames of `poses`: a pose CSV joined by frame (as
    is), a TUM file or a bag pose topic matched by time."""
    p = Path(path)
    if is_bag_path(p):
        truth, by_time = read_poses(p, s.topic), True
    else:
        if p.is_dir():
            raise InputError(f"truth {p} is a folder but not a ROS 2 bag (no metadata.yaml)")
        if s.topic is not None:
            raise InputError(
                f"--truth-topic {s.topic} picks a pose topic of a ROS bag; {p} is not a bag"
            )
        fmt = guess_format(p)
        truth, by_time = read_trajectory(p, fmt), fmt != "csv"
    truth = body_to_camera(truth, s.body_to_camera)
    if not by_time:
        if s.t_offset_s:
            raise InputError(
                f"--t-offset applies to truth matched by time (TUM, a bag); {p} is a pose "
                "CSV, joined by frame"
            )
        return truth
    return match_times(truth, poses, s.t_max_diff_s, s.t_offset_s)
