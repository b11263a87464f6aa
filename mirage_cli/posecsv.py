"""The one pose-CSV schema (brief, section 3): writer that flushes every row, validating reader."""

from __future__ import annotations

import contextlib
import csv
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import InputError
from .fileio import check_writable, read_csv, require_file
from .pose import R_CB, Pose

POSE_COLUMNS = [
    "frame", "time_s", "status", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz",
    "roll_deg", "pitch_deg", "yaw_deg", "azimuth_deg",
]  # fmt: skip
REQUIRED_INPUT = ["x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"]


def pose_fields(pose: Pose | None) -> list[str]:
    """The ten pose cells of a row (empty strings when there is no pose)."""
    if pose is None:
        return [""] * 11
    c, q, rpy = pose.center, pose.quat_wxyz, pose.rpy_deg
    return (
        [f"{v:.6f}" for v in c]
        + [f"{v:.9f}" for v in q]
        + [f"{v:.4f}" for v in rpy]
        + [f"{pose.azimuth_deg:.4f}"]
    )


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float | np.floating):
        return "" if not np.isfinite(v) else f"{float(v):.6g}"
    return str(v)


class PoseCSVWriter:
    """Writes rows as they come and flushes each, into `<out>.partial` until `close()`.

    An interrupted run keeps every finished row in the partial file; `close(keep=True)`
    (also on Ctrl-C) moves it into place, `close(keep=False)` discards it.
    """

    def __init__(self, path, extra_columns: Sequence[str] = ()):
        self.path = check_writable(path)
        self.extra = list(extra_columns)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{self.path.name}.", suffix=".partial", dir=self.path.parent or "."
        )
        self.tmp = Path(tmp)
        os.chmod(tmp, 0o644)
        self._f = os.fdopen(fd, "w", newline="")
        self._w = csv.writer(self._f, lineterminator="\n")
        self._w.writerow(POSE_COLUMNS + self.extra)
        self._f.flush()
        self.rows = 0

    def write(self, frame, time_s, status: str, pose: Pose | None, **extra) -> None:
        t = "" if time_s is None or not np.isfinite(time_s) else f"{time_s:.6f}"
        row = [str(frame), t, status] + pose_fields(pose if status == "ok" else None)
        row += [_fmt(extra.get(k)) for k in self.extra]
        self._w.writerow(row)
        self._f.flush()
        self.rows += 1

    def close(self, keep: bool = True) -> None:
        if self._f.closed:
            return
        self._f.flush()
        os.fsync(self._f.fileno())
        self._f.close()
        if keep:
            os.replace(self.tmp, self.path)
        else:
            with contextlib.suppress(OSError):
                self.tmp.unlink()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        # Ctrl-C keeps the frames done so far; an error keeps any good file already there.
        self.close(keep=exc_type is None or issubclass(exc_type, KeyboardInterrupt))
        return False


def write_pose_csv(path, frames: Iterable, poses: Iterable[Pose | None], times=None) -> None:
    """Write a whole pose CSV at once (truth files, keyframe poses)."""
    frames = list(frames)
    times = [None] * len(frames) if times is None else list(times)
    with PoseCSVWriter(path) as w:
        for f, p, t in zip(frames, poses, times, strict=True):
            w.write(f, t, "ok" if p is not None else "lost", p)


def read_pose_csv(path, require_pose: bool = True) -> pd.DataFrame:
    """Read and validate a pose CSV.

    Returns a DataFrame with a `frame` column (from `frame` or `image`), `status`
    (default "ok"), numeric pose columns (NaN where not ok) and the derived angle
    columns recomputed from the quaternion. Every problem names the column and row.
    """
    p = require_file(path, "pose file")
    header = f"a header row: {','.join(POSE_COLUMNS[:10])}"
    df = read_csv(p, "pose file", header, dtype=str, keep_default_na=False)
    if "frame" not in df.columns:
        if "image" not in df.columns:
            raise InputError(
                f"pose file {p}: no 'frame' or 'image' column "
                f"(columns found: {', '.join(df.columns)})"
            )
        df = df.rename(columns={"image": "frame"})
    if require_pose:
        missing = [c for c in REQUIRED_INPUT if c not in df.columns]
        if missing:
            raise InputError(f"pose file {p}: missing column(s) {', '.join(missing)}")
    if df.empty:
        raise InputError(f"pose file {p} has a header but no rows")
    if "status" not in df.columns:
        df["status"] = "ok"
    df["status"] = df["status"].str.strip().replace("", "ok")
    ok = df["status"] == "ok"
    for col in ["time_s"] + REQUIRED_INPUT:
        if col not in df.columns:
            df[col] = np.nan
            continue
        raw = df[col].str.strip()
        num = pd.to_numeric(raw, errors="coerce")
        bad = (num.isna() & (raw != "")) | (ok & num.isna() & (col in REQUIRED_INPUT))
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            what = repr(df[col].iloc[i]) if raw.iloc[i] else "an empty cell"
            raise InputError(
                f"pose file {p}: column '{col}' row {i + 2} (frame "
                f"{df['frame'].iloc[i]}) has {what}, expected a number"
            )
        df[col] = num
    if require_pose:
        q = df.loc[ok, ["qw", "qx", "qy", "qz"]].to_numpy()
        n = np.linalg.norm(q, axis=1)
        if np.any(n < 1e-6):
            i = int(np.flatnonzero(ok.to_numpy())[np.argmax(n < 1e-6)])
            raise InputError(f"pose file {p}: row {i + 2} has a zero quaternion")
        df.loc[ok, ["qw", "qx", "qy", "qz"]] = q / n[:, None]
        angles = np.full((len(df), 4), np.nan)
        okn = ok.to_numpy()
        angles[okn] = derived_angles(
            df.loc[ok, ["x_m", "y_m", "z_m"]].to_numpy(),
            df.loc[ok, ["qw", "qx", "qy", "qz"]].to_numpy(),
        )
        df[["roll_deg", "pitch_deg", "yaw_deg", "azimuth_deg"]] = angles
    df["frame"] = df["frame"].str.strip()
    known = set(POSE_COLUMNS) | {"status"}
    for col in df.columns:  # extra diagnostic columns: numeric when every cell is
        if col not in known and not pd.api.types.is_numeric_dtype(df[col]):
            raw = df[col].str.strip()
            num = pd.to_numeric(raw, errors="coerce")
            if not (num.isna() & (raw != "")).any():
                df[col] = num
    return df


def derived_angles(centers: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """(N,4) roll, pitch, yaw (REP-103, camera body frame) and azimuth in degrees, for
    camera centres (N,3) and unit quaternions (N,4) of R_WC: the file's derived columns."""
    w, x, y, z = quats.T
    # R_WC rows as in pose.matrix_from_quat, then R_WB = R_WC @ R_CB (body x = optical axis)
    R = np.empty((len(quats), 3, 3))
    R[:, 0] = np.column_stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)])
    R[:, 1] = np.column_stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)])
    R[:, 2] = np.column_stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)])
    B = R @ R_CB
    pitch = np.arctan2(-B[:, 2, 0], np.hypot(B[:, 0, 0], B[:, 1, 0]))
    roll = np.arctan2(B[:, 2, 1], B[:, 2, 2])
    yaw = np.arctan2(B[:, 1, 0], B[:, 0, 0])
    az = np.degrees(np.arctan2(centers[:, 1], centers[:, 0]))
    az[az <= -180.0] = 180.0
    return np.column_stack([np.degrees(roll), np.degrees(pitch), np.degrees(yaw), az])


def row_pose(row) -> Pose | None:
    """Pose of one row of `read_pose_csv`'s frame (None when not ok)."""
    if row.get("status", "ok") != "ok":
        return None
    return Pose.from_center_quat(
        [row["x_m"], row["y_m"], row["z_m"]], [row["qw"], row["qx"], row["qy"], row["qz"]]
    )


def poses_by_frame(df: pd.DataFrame) -> dict[str, Pose]:
    """Map frame id (as text) -> Pose for every ok row."""
    return {str(r["frame"]): row_pose(r) for _, r in df.iterrows() if r["status"] == "ok"}
