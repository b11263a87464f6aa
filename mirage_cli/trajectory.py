"""Trajectories: reading and writing the per-frame records (records.py) by format.

One record type (`FrameRecord`) flows from tracking to every output; each file format is a
row function plus an entry in `FORMATS` (and a reader), so a new format touches nothing
else. The pose CSV (brief, section 3) is the one schema of track output, ground truth and
build-model input; TUM and KITTI are for evo and friends.
"""

from __future__ import annotations

import contextlib
import csv
import io
import os
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import validate
from .errors import InputError
from .fileio import (
    check_writable,
    forget_temp,
    is_special,
    mkstemp_near,
    read_csv,
    require_file,
    write_failure,
)
from .pose import R_CB, Pose
from .records import FrameRecord, Status

if TYPE_CHECKING:  # pandas and scipy load with the readers: writing needs neither
    import pandas as pd


POSE_COLUMNS = [
    "frame", "time_s", "status", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz",
    "roll_deg", "pitch_deg", "yaw_deg", "azimuth_deg",
]  # fmt: skip
REQUIRED_INPUT = ["x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"]
# diagnostic columns of `mirage track`'s pose CSV, after the pose
TRACK_COLUMNS = ["keyframe", "matches", "inliers", "reproj_rmse_px", "iterations",
                 "sigma_pos_m", "sigma_rot_deg", "ms", "mode", "reason"]  # fmt: skip
_ATTR = {"reproj_rmse_px": "rmse_px"}


def pose_fields(pose: Pose | None) -> list[str]:
    """The eleven pose cells of a row (empty strings when there is no pose)."""
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


def _cell(rec: FrameRecord, column: str):
    if column in rec.extra:
        return rec.extra[column]
    return getattr(rec, _ATTR.get(column, column), None)


def _csv_line(cells: Sequence[str]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(cells)
    return buf.getvalue()


def _csv_row(rec: FrameRecord, index: int, extra: Sequence[str]) -> str:
    t = "" if rec.time_s is None or not np.isfinite(rec.time_s) else f"{rec.time_s:.6f}"
    cells = [str(rec.frame), t, str(rec.status)] + pose_fields(rec.pose if rec.ok else None)
    return _csv_line(cells + [_fmt(_cell(rec, k)) for k in extra])


def _tum_row(rec: FrameRecord, index: int, extra: Sequence[str]) -> str | None:
    """`time tx ty tz qx qy qz qw` of T_WC, ok frames only; without times, the row number."""
    if not rec.ok:
        return None
    ts = rec.time_s if rec.time_s is not None and np.isfinite(rec.time_s) else index
    c, q = rec.pose.center, rec.pose.quat_wxyz
    return (
        f"{ts:.6f} {c[0]:.6f} {c[1]:.6f} {c[2]:.6f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f} {q[0]:.9f}\n"
    )


def _kitti_row(rec: FrameRecord, index: int, extra: Sequence[str]) -> str | None:
    """The 3x4 camera-to-world matrix [R_WC | centre], row-major, ok frames only."""
    if not rec.ok:
        return None
    T = np.column_stack([rec.pose.R_wc, rec.pose.center])
    return " ".join(f"{v:.9f}" if j % 4 < 3 else f"{v:.6f}" for j, v in enumerate(T.ravel())) + "\n"


@dataclass(frozen=True)
class Format:
    """A trajectory file format: its header, one line per record (None: no line), a reader,
    and how the CLI knows it: `flag` (with its `help`) makes `mirage track FLAG FILE` also
    write it; `guess_format` takes a file for it by name (`suffixes`) or by its first data
    line (`fields` numbers)."""

    header: Callable[[Sequence[str]], str]
    row: Callable[[FrameRecord, int, Sequence[str]], str | None]
    read: Callable[[Path], pd.DataFrame]
    flag: str = ""  # e.g. "--tum"; "" for no track option
    help: str = ""
    suffixes: tuple[str, ...] = ()  # lower case, with the dot
    fields: int = 0  # whitespace-separated numbers a data line; 0: not recognised by content


class TrajectoryWriter:
    """Writes records as they come and flushes each, into a hidden partial file until
    `close()`.

    An interrupted run keeps every finished row: `close(keep=True)` (also on Ctrl-C and
    SIGTERM) moves the file into place, `close(keep=False)` discards it. A file without
    rows never replaces anything, so a run that fails before its first frame leaves a
    previous good file as it was; a full disk is one line naming the file.
    """

    def __init__(self, path, fmt: str = "csv", extra_columns: Sequence[str] = ()):
        self.path = check_writable(path)
        self.format = FORMATS[fmt]
        self.extra = list(extra_columns)
        self.rows = 0
        if is_special(self.path):  # /dev/null, a FIFO, /dev/stdout: rows go straight there
            self.tmp = None
            try:
                self._f = open(self.path, "w", newline="")  # noqa: SIM115
            except OSError as e:
                raise write_failure(self.path, e) from None
        else:
            fd, self.tmp = mkstemp_near(self.path, ".partial")
            os.chmod(self.tmp, 0o644)
            self._f = os.fdopen(fd, "w", newline="")
        self._guard(lambda: (self._f.write(self.format.header(self.extra)), self._f.flush()))

    def _guard(self, fn) -> None:
        """Run a write; an OS error (full disk) discards the file and names the output."""
        try:
            fn()
        except OSError as e:
            self._discard()
            raise write_failure(self.path, e) from None

    def write(self, rec: FrameRecord) -> None:
        line = self.format.row(rec, self.rows, self.extra)
        if line is not None:
            self._guard(lambda: (self._f.write(line), self._f.flush()))
        self.rows += 1

    def _discard(self) -> None:
        with contextlib.suppress(OSError):
            self._f.close()
        if self.tmp is None:
            return
        with contextlib.suppress(OSError):
            self.tmp.unlink()
        forget_temp(self.tmp)

    def close(self, keep: bool = True) -> None:
        if self._f.closed:
            return
        if not keep or self.rows == 0 or self.tmp is None:
            self._discard()
            return

        def finish():
            self._f.flush()
            os.fsync(self._f.fileno())
            self._f.close()
            os.replace(self.tmp, self.path)
            forget_temp(self.tmp)

        self._guard(finish)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        # Ctrl-C / SIGTERM keep the frames done so far; an error keeps any good file already
        # there (the KeyboardInterrupt family includes the CLI's SIGTERM exception).
        self.close(keep=exc_type is None or issubclass(exc_type, KeyboardInterrupt))
        return False


def write_trajectory(
    path, records: Iterable[FrameRecord], fmt: str = "csv", extra_columns: Sequence[str] = ()
) -> None:
    """Write a whole trajectory at once (truth files, keyframe poses)."""
    with TrajectoryWriter(path, fmt, extra_columns) as w:
        for rec in records:
            w.write(rec)


def read_trajectory(path, fmt: str | None = None) -> pd.DataFrame:
    """Any format's file as a pose-CSV table (frame, time_s, status, pose, angles);
    the format is guessed (`guess_format`) unless given."""
    return FORMATS[fmt or guess_format(path)].read(path)


def guess_format(path) -> str:
    """The `FORMATS` name of a file: by its suffix (.csv, .tum, .kitti), else by the number
    of fields on its first data line (8 TUM, 12 KITTI); 'csv' when neither tells."""
    p = Path(path)
    for name, f in FORMATS.items():
        if p.suffix.lower() in f.suffixes:
            return name
    if p.is_file():
        with open(p, errors="replace") as fh:
            for line in fh:
                words = line.split()
                if words and not words[0].startswith("#"):
                    return next((n for n, f in FORMATS.items() if f.fields == len(words)), "csv")
    return "csv"


def match_times(
    truth: pd.DataFrame, poses: pd.DataFrame, max_dt: float = 0.01, offset_s: float = 0.0
) -> pd.DataFrame:
    """Truth rows renamed to the pose frames nearest in time (within `max_dt` s, one truth
    row per frame), for truth that has times but not the poses' frame ids (TUM, a bag);
    `offset_s` is added to the truth times first (their time_s is returned shifted)."""
    t = truth["time_s"].to_numpy(float) + offset_s
    pt = poses["time_s"].to_numpy(float)
    if not (np.isfinite(t).all() and np.isfinite(pt).any()):
        raise InputError("matching truth by time needs times in both files (time_s column)")
    order = np.argsort(t)
    t = t[order]
    j = np.searchsorted(t, pt)
    cand = np.clip(np.stack([j - 1, j]), 0, len(t) - 1)  # the neighbours on either side
    near = cand[np.argmin(np.abs(t[cand] - pt), axis=0), np.arange(len(pt))]
    hit = np.abs(t[near] - pt) <= max_dt
    if not hit.any():
        raise InputError(
            f"truth times ({t[0]:.3f}-{t[-1]:.3f} s) do not overlap the pose times within "
            f"{max_dt * 1000:g} ms; is it the truth of this video?"
        )
    rows = truth.iloc[order[near[hit]]].copy()
    rows["time_s"] = t[near[hit]]
    rows["frame"] = poses["frame"].to_numpy()[hit]
    return rows.reset_index(drop=True)


def read_pose_csv(path, require_pose: bool = True) -> pd.DataFrame:
    """Read and validate a pose CSV.

    Returns a DataFrame with a `frame` column (from `frame` or `image`), `status`
    (default "ok"), numeric pose columns (NaN where not ok) and the derived angle
    columns recomputed from the quaternion. Every problem names the column and row.
    """
    import pandas as pd

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
        df["status"] = Status.OK.value
    df["status"] = df["status"].str.strip().replace("", Status.OK.value)
    words = {s.value for s in Status}
    unknown = ~df["status"].isin(words)
    if unknown.any():  # a word of another tool's ('OK', 'good'): its frames would be dropped
        i = int(np.flatnonzero(unknown.to_numpy())[0])
        raise InputError(
            f"pose file {p}: column 'status' row {i + 2} (frame {df['frame'].iloc[i]}) is "
            f"{df['status'].iloc[i]!r}; expected one of {', '.join(s.value for s in Status)} "
            "(or empty: ok)"
        )
    ok = df["status"] == Status.OK
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
    validate.pose_table(df, p, require_pose)
    if require_pose:
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
    if row.get("status", Status.OK) != Status.OK:
        return None
    return Pose.from_center_quat(
        [row["x_m"], row["y_m"], row["z_m"]], [row["qw"], row["qx"], row["qy"], row["qz"]]
    )


def poses_by_frame(df: pd.DataFrame) -> dict[str, Pose]:
    """Map frame id (as text) -> Pose for every ok row."""
    return {str(r["frame"]): row_pose(r) for _, r in df.iterrows() if r["status"] == Status.OK}


def _numbers(path, what: str, width: int) -> np.ndarray:
    """The rows of a whitespace-separated numeric file ('#' comments), or a one-line error."""
    p = require_file(path, f"{what} file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty file is the error below, not a warning
            a = np.loadtxt(p, comments="#", ndmin=2)
    except ValueError as e:
        raise InputError(f"{what} file {p}: {e}") from None
    if a.size == 0 or a.shape[1] != width or not np.isfinite(a).all():
        raise InputError(f"{what} file {p}: expected rows of {width} finite numbers")
    return a


def pose_table(frames, times, centers: np.ndarray, quats: np.ndarray) -> pd.DataFrame:
    """A pose-CSV table of ok rows (quaternions normalised, angles derived)."""
    import pandas as pd

    quats = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    df = pd.DataFrame({"frame": [str(f) for f in frames], "time_s": times})
    df["status"] = Status.OK.value
    df[["x_m", "y_m", "z_m"]] = centers
    df[["qw", "qx", "qy", "qz"]] = quats
    df[["roll_deg", "pitch_deg", "yaw_deg", "azimuth_deg"]] = derived_angles(centers, quats)
    return df


def read_tum(path) -> pd.DataFrame:
    """A TUM file (`time tx ty tz qx qy qz qw`): frames are the row numbers."""
    a = _numbers(path, "TUM", 8)
    validate.unique_times(a[:, 0], path, "TUM")
    q = validate.unit_quaternion_rows(a[:, [7, 4, 5, 6]], path, "TUM")
    return pose_table(range(len(a)), a[:, 0], a[:, 1:4], q)


def read_kitti(path) -> pd.DataFrame:
    """A KITTI poses file (12 numbers of T_WC a line): frames are the row numbers, no times."""
    from scipy.spatial.transform import Rotation

    T = _numbers(path, "KITTI", 12).reshape(-1, 3, 4)
    validate.rotation_rows(T[:, :, :3], path, "KITTI")
    q = Rotation.from_matrix(T[:, :, :3]).as_quat()[:, [3, 0, 1, 2]]
    return pose_table(range(len(T)), np.nan, T[:, :, 3], q)


TUM_HEADER = "# timestamp tx ty tz qx qy qz qw (mirage track, camera-to-world)\n"

FORMATS: dict[str, Format] = {
    "csv": Format(
        lambda extra: _csv_line(POSE_COLUMNS + list(extra)),
        _csv_row,
        read_pose_csv,
        suffixes=(".csv",),
    ),  # track's -o/--output
    "tum": Format(
        lambda extra: TUM_HEADER,
        _tum_row,
        read_tum,
        flag="--tum",
        help="Also write a TUM trajectory (time x y z qx qy qz qw) for evo & co.",
        suffixes=(".tum",),
        fields=8,
    ),
    "kitti": Format(
        lambda extra: "",
        _kitti_row,
        read_kitti,
        flag="--kitti",
        help="Also write KITTI poses (3x4 camera-to-world matrix, 12 numbers a line).",
        suffixes=(".kitti",),
        fields=12,
    ),
}
