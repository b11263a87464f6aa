"""Path-tracking report (brief, section 4.4): per-frame error table and summary.

Pure core: takes validated pose tables (mirage_cli.trajectory) and a desired path
(mirage_cli.path) and does no I/O: report_cli writes the files, mirage_cli.plotting draws
the plot. Everything is vectorised over frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from .errors import InputError
from .path import DesiredPath
from .records import Status

BASE_COLUMNS = [
    "frame", "time_s", "status", "x_m", "y_m", "z_m",
    "path_s_m", "cross_track_m", "height_error_m", "heading_error_deg",
]  # fmt: skip
TRUTH_COLUMNS = ["position_error_m", "rotation_error_deg"]
SIGNED = ("cross_track_m", "height_error_m", "heading_error_deg", "along_track_m")


@dataclass(frozen=True)
class Report:
    table: pd.DataFrame  # one row per frame, columns as written to report.csv
    summary: dict  # plain types, ready for YAML
    truth: pd.DataFrame | None = None  # truth rows aligned with `table` (for plots)


def frame_key(frames: pd.Series) -> pd.Series:
    """Join key: '12', '12.0' and ' 12' are the same frame; image names stay as they are."""
    s = frames.astype(str).str.strip()
    num = pd.to_numeric(s, errors="coerce")
    integral = num.notna() & (num == np.round(num))
    out = s.copy()
    out[integral] = num[integral].astype("int64").astype(str)
    return out


def quat_angle_deg(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Rotation angle between unit quaternions, row by row (same as Pose.angle_to)."""
    d = np.abs(np.einsum("ij,ij->i", q1, q2))
    return np.degrees(2.0 * np.arccos(np.clip(d, 0.0, 1.0)))


def align_truth(poses: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Truth rows in the order of `poses` (NaN where a frame has no truth)."""
    tk = frame_key(truth["frame"])
    if tk.duplicated().any():
        raise InputError(f"truth file: frame {tk[tk.duplicated()].iloc[0]} appears twice")
    pk = frame_key(poses["frame"])
    if not pk.isin(set(tk)).any():
        raise InputError(
            "truth frames do not overlap the pose frames (e.g. pose frame "
            f"{poses['frame'].iloc[0]!r}, truth frame {truth['frame'].iloc[0]!r}); "
            "is it the truth of this video?"
        )
    t = truth.assign(_key=tk.to_numpy()).set_index("_key")
    return t.reindex(pk.to_numpy()).reset_index(drop=True)


def make_report(
    poses: pd.DataFrame, path: DesiredPath, truth: pd.DataFrame | None = None
) -> Report:
    """Per-frame errors and the summary for a pose table from `read_pose_csv`."""
    ok = (poses["status"] == Status.OK).to_numpy()
    xyz = poses[["x_m", "y_m", "z_m"]].to_numpy(float)
    xyz[~ok] = np.nan
    times = poses["time_s"].to_numpy(float)
    e = path.errors(xyz, poses["yaw_deg"].to_numpy(float), times)
    cols = {
        "frame": poses["frame"].to_numpy(),
        "time_s": times,
        "status": poses["status"].to_numpy(),
        "x_m": xyz[:, 0],
        "y_m": xyz[:, 1],
        "z_m": xyz[:, 2],
        "path_s_m": e.path_s_m,
        "cross_track_m": e.cross_track_m,
        "height_error_m": e.height_error_m,
        "heading_error_deg": e.heading_error_deg,
    }
    if e.along_track_m is not None:
        cols["along_track_m"] = e.along_track_m
    aligned = None
    if truth is not None:
        aligned = align_truth(poses, truth)
        tok = (aligned["status"] == Status.OK).to_numpy()
        txyz = aligned[["x_m", "y_m", "z_m"]].to_numpy(float)
        tq = aligned[["qw", "qx", "qy", "qz"]].to_numpy(float)
        pq = poses[["qw", "qx", "qy", "qz"]].to_numpy(float)
        both = ok & tok
        pos = np.full(len(poses), np.nan)
        rot = np.full(len(poses), np.nan)
        pos[both] = np.linalg.norm(xyz[both] - txyz[both], axis=1)
        rot[both] = quat_angle_deg(pq[both], tq[both])
        cols["position_error_m"], cols["rotation_error_deg"] = pos, rot
    table = pd.DataFrame(cols)
    return Report(table, summarize(table, truth is not None, aligned), aligned)


def _stats(v: np.ndarray, signed: bool) -> dict:
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {"n": 0, "mean": None, "rms": None, "p95": None, "max": None}
    a = np.abs(v)
    out = {
        "n": int(len(v)),
        "mean": _r(np.mean(v)),
        "rms": _r(np.sqrt(np.mean(v**2))),
        "p95": _r(np.percentile(a, 95)),
        "max": _r(a.max()),
    }
    if not signed:
        out["median"] = _r(np.median(v))
    return out


def _r(v) -> float:
    """Seven significant digits: readable YAML, far below any error we measure."""
    return float(f"{float(v):.7g}")


def longest_run(mask: np.ndarray) -> tuple[int, int]:
    """(length, start index) of the longest run of True in `mask` ((0, -1) when none)."""
    m = np.r_[False, np.asarray(mask, bool), False].astype(np.int8)
    edges = np.flatnonzero(np.diff(m))
    starts, ends = edges[::2], edges[1::2]
    if len(starts) == 0:
        return 0, -1
    k = int(np.argmax(ends - starts))
    return int(ends[k] - starts[k]), int(starts[k])


def summarize(table: pd.DataFrame, with_truth: bool, truth: pd.DataFrame | None = None) -> dict:
    """Frames, tracked %, mean / RMS / p95 / max of every error (p95 and max of |error|),
    and the longest lost stretch in frames and seconds."""
    n = len(table)
    ok = (table["status"] == Status.OK).to_numpy()
    lost = ~ok
    run, start = longest_run(lost)
    t = table["time_s"].to_numpy(float)
    dt = np.diff(t)
    dt = dt[np.isfinite(dt) & (dt > 0)]
    frame_dt = float(np.median(dt)) if len(dt) else float("nan")
    seconds = run * frame_dt if run else 0.0
    s = {
        "frames": int(n),
        "tracked": int(ok.sum()),
        "tracked_pct": round(float(100.0 * ok.mean()) if n else 0.0, 3),
        "lost": int(lost.sum()),
        "statuses": {str(k): int(v) for k, v in table["status"].value_counts().items()},
        "longest_lost": {
            "frames": run,
            "seconds": None if not np.isfinite(seconds) else round(float(seconds), 4),
            "first_frame": str(table["frame"].iloc[start]) if run else None,
        },
        "errors": {},
    }
    names = [c for c in BASE_COLUMNS[7:] + ["along_track_m"] if c in table.columns]
    if with_truth:
        names += TRUTH_COLUMNS
        if truth is not None:
            s["truth_frames"] = int(truth["status"].notna().sum())
            # excluded from the truth errors: no truth row (or none within the time tolerance)
            s["frames_without_truth"] = int(n - s["truth_frames"])
            if "landmark_visible" in truth.columns:
                s["visibility"] = _visibility(ok, truth["landmark_visible"])
    for c in names:
        s["errors"][c] = _stats(table[c].to_numpy(float), c in SIGNED)
    return s


def _visibility(ok: np.ndarray, visible: pd.Series) -> dict:
    """Tracked share where the landmark is in view (truth visibility >= 0.5), and 'ok'
    frames where it is essentially out of view (<= 0.05): a wrong pose is worse than none."""
    v = pd.to_numeric(visible, errors="coerce").to_numpy(float)
    seen, hidden = v >= 0.5, v <= 0.05
    return {
        "frames_in_view": int(seen.sum()),
        "tracked_in_view_pct": round(float(100.0 * ok[seen].mean()), 3) if seen.any() else None,
        "frames_out_of_view": int(hidden.sum()),
        "ok_out_of_view": int((ok & hidden).sum()),
    }
