"""Every picture mirage draws: the report plot, a model's top view, the calibration report
and the tracking overlay.

The figure functions take data and return a matplotlib Figure; `save_png` writes one
atomically. matplotlib is imported inside the functions (it costs ~0.3 s of start-up that
commands without a plot should not pay) and figures are made without pyplot, so nothing
here touches a global backend or figure list: PNGs are rendered by Agg.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from .fileio import atomic_path
from .records import Status

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from .calibrate import Calibration
    from .camera import Camera
    from .model import LandmarkModel
    from .path import DesiredPath
    from .records import FrameRecord
    from .report import Report


def import_matplotlib():
    """matplotlib, imported once. It validates $MPLBACKEND on import (a bad value is a
    ValueError); mirage draws PNGs with Agg and never uses a backend, so a bad value is a
    warning and is dropped for this process."""
    import os
    import sys

    if "matplotlib" in sys.modules:
        return sys.modules["matplotlib"]
    try:
        import matplotlib
    except ValueError as e:
        backend = os.environ.pop("MPLBACKEND", None)
        if backend is None or "backend" not in str(e).lower():
            raise
        from .logs import log

        log.warning(
            f"MPLBACKEND={backend!r} is not a matplotlib backend; ignored (mirage writes "
            "PNGs with Agg)"
        )
        for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
            del sys.modules[name]
        import matplotlib
    return matplotlib


def _figure(**kw) -> Figure:
    import_matplotlib()
    from matplotlib.figure import Figure

    return Figure(**kw)


def save_png(fig: Figure, path, dpi: int, **kw) -> None:
    """Write `fig` as a PNG at `path` atomically (a failed write leaves no half file)."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, **kw)


# --------------------------------------------------------------------------------------
# mirage report
# --------------------------------------------------------------------------------------
REPORT_DPI = 100


# what a positive error means, under each signed axis's name (the report's conventions)
SIGN_NOTES = {
    "cross_track_m": "\n+ left of path",
    "height_error_m": "\n+ above path",
    "heading_error_deg": "\n+ turned left (ccw)",
    "along_track_m": "\n+ ahead of time",
}


def report_figure(rep: Report, path: DesiredPath) -> Figure:
    """Top view (desired path, estimate, truth, lost frames) and errors over time."""
    from .path import CirclePath
    from .report import SIGNED, TRUTH_COLUMNS

    tab = rep.table
    err_cols = [c for c in tab.columns if c in SIGNED or c in TRUTH_COLUMNS]
    t = tab["time_s"].to_numpy(float)
    xlabel = "time (s)"
    if not np.isfinite(t).any():
        t, xlabel = np.arange(len(tab), dtype=float), "frame"
    ok = (tab["status"] == Status.OK).to_numpy()
    edges = np.flatnonzero(np.diff(np.r_[0, (~ok).astype(np.int8), 0]))
    lost_runs = list(zip(edges[::2], edges[1::2], strict=True))
    step = _step(t)

    fig = _figure(figsize=(13, max(6.0, 1.9 * len(err_cols))))
    gs = fig.add_gridspec(len(err_cols), 2, width_ratios=[1.15, 1])
    ax = fig.add_subplot(gs[:, 0])
    d = path.sample(361)
    ax.plot(d[:, 0], d[:, 1], "-", color="0.5", lw=2, label="desired path")
    k = max(1, len(d) // 36)
    if isinstance(path, CirclePath) and path.direction == "cw":
        d = d[::-1]
    ax.annotate("", d[k, :2], d[0, :2], arrowprops={"arrowstyle": "->", "color": "0.3", "lw": 2})
    if rep.truth is not None:
        tt = rep.truth
        ax.plot(tt["x_m"], tt["y_m"], "-", color="tab:green", lw=3, alpha=0.5, label="truth")
        if (~ok).any():
            ax.plot(
                tt["x_m"].to_numpy(float)[~ok],
                tt["y_m"].to_numpy(float)[~ok],
                "x",
                color="tab:red",
                ms=4,
                label=f"lost ({(~ok).sum()} frames, at truth)",
            )
    ax.plot(tab["x_m"], tab["y_m"], ".-", color="tab:blue", ms=2, lw=0.8, label="estimate")
    if (~ok).any() and rep.truth is None:
        # no truth: mark lost frames at the last known position
        last = tab[["x_m", "y_m"]].ffill().to_numpy(float)[~ok]
        ax.plot(last[:, 0], last[:, 1], "x", color="tab:red", ms=4, label="lost (last pose)")
    ax.plot([0], [0], "k*", ms=14, label="landmark")
    ax.set(aspect="equal", xlabel="x (m)", ylabel="y (m)", title="top view")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(0.0, -0.09), ncol=3)
    tracked = rep.summary["tracked_pct"]
    fig.suptitle(f"mirage report: {len(tab)} frames, {tracked:.1f}% tracked")
    for i, c in enumerate(err_cols):
        a = fig.add_subplot(gs[i, 1])
        a.plot(t, tab[c].to_numpy(float), "-", lw=1)
        a.axhline(0, color="k", lw=0.5)
        for n, (j0, j1) in enumerate(lost_runs):
            a.axvspan(t[j0] - 0.5 * step, t[j1 - 1] + 0.5 * step, color="tab:red", alpha=0.12,
                      label="not tracked" if n == 0 else None)  # fmt: skip
        if i == 0 and lost_runs:
            a.legend(fontsize=7, loc="upper right")
        a.set_ylabel(c.replace("_", " ") + SIGN_NOTES.get(c, ""), fontsize=8)
        a.grid(alpha=0.3)
        if i == len(err_cols) - 1:
            a.set_xlabel(xlabel)
    fig.tight_layout()
    return fig


def _step(t: np.ndarray) -> float:
    """Median frame interval (1 when unknown): the width of one lost frame's band."""
    d = np.diff(t)
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if len(d) else 1.0


# --------------------------------------------------------------------------------------
# mirage inspect --plot
# --------------------------------------------------------------------------------------
TOP_VIEW_DPI = 110


def top_view_figure(model: LandmarkModel) -> Figure:
    """A model from above: 3D points coloured by height, keyframes with their view axes
    and linked-point counts. Saved with bbox_inches="tight"."""
    fig = _figure(figsize=(7, 7))
    ax = fig.add_subplot()
    X = model.points
    if len(X):
        sc = ax.scatter(X[:, 0], X[:, 1], s=2, c=X[:, 2], cmap="viridis", label="3D points")
        fig.colorbar(sc, ax=ax, shrink=0.7, label="z (m)")
    C = np.array([kf.pose.center for kf in model.keyframes])
    axis = np.array([kf.pose.R[2] for kf in model.keyframes])
    ax.scatter(C[:, 0], C[:, 1], marker="^", c="tab:red", s=30, label="keyframes")
    ax.quiver(C[:, 0], C[:, 1], axis[:, 0], axis[:, 1], color="tab:red", width=0.003)
    for kf, c in zip(model.keyframes, C, strict=True):
        ax.annotate(f"{kf.n_linked}", c[:2], fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    s = model.summary()
    ax.set_title(
        f"{s['keyframes']} keyframes, {s['points']} points, "
        f"RMS {s['rms_reprojection_px']:.2f} px (labels: points per keyframe)"
    )
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    return fig


# --------------------------------------------------------------------------------------
# mirage calibrate --report
# --------------------------------------------------------------------------------------
CALIBRATION_DPI = 110


def calibration_figure(c: Calibration) -> Figure:
    """Corner coverage over the image (rejected views as red crosses) and per-view RMS."""
    matplotlib = import_matplotlib()
    from matplotlib.patches import Rectangle

    w, h = c.image_size
    fig = _figure(figsize=(12, 4.5))
    ax1, ax2 = fig.subplots(1, 2, width_ratios=[1.1, 1])
    cmap = matplotlib.colormaps["viridis"]
    for i, v in enumerate(c.views):
        ax1.plot(
            v.corners[:, 0], v.corners[:, 1], ".", ms=3, color=cmap(i / max(1, len(c.views) - 1))
        )
    for v, _ in c.rejected:
        ax1.plot(v.corners[:, 0], v.corners[:, 1], "x", ms=3, color="red")
    ax1.set(
        xlim=(0, w),
        ylim=(h, 0),
        aspect="equal",
        xlabel="x (px)",
        ylabel="y (px)",
        title=f"corner coverage ({len(c.views)} views; rejected x red)",
    )
    ax1.add_patch(Rectangle((0, 0), w, h, fill=False, lw=1, color="k"))

    names = [v.name for v in c.views] + [v.name for v, _ in c.rejected]
    errs = np.r_[c.view_errors_px, [e for _, e in c.rejected]]
    colors = ["tab:blue"] * len(c.views) + ["tab:red"] * len(c.rejected)
    ax2.bar(range(len(errs)), errs, color=colors)
    ax2.axhline(c.rms_px, color="k", lw=1, ls="--", label=f"overall RMS {c.rms_px:.3f} px")
    if c.threshold_px is not None and c.threshold_px < 2 * errs.max():
        ax2.axhline(c.threshold_px, color="tab:red", lw=1, ls=":", label="rejection limit")
    ax2.set_xticks(range(len(errs)), names, rotation=90, fontsize=7)
    ax2.set(ylabel="RMS reprojection error (px)", title="per-view error")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------------------
# mirage track --overlay
# --------------------------------------------------------------------------------------
def draw_overlay(img: np.ndarray, res: FrameRecord, camera: Camera, axis_m: float) -> np.ndarray:
    """A copy of the frame with the inliers (green dots), W's axes (x red, y green, z blue)
    and the status drawn; `res` is the frame's tracking result."""
    out = img.copy()
    if res.status == Status.OK:
        if res.inlier_px is not None:  # 3x3 green dots, stamped with numpy
            p = np.rint(res.inlier_px).astype(int)
            h, w = out.shape[:2]
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    x, y = p[:, 0] + dx, p[:, 1] + dy
                    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
                    out[y[ok], x[ok]] = (0, 255, 0)
        ends = np.array([[0, 0, 0], [axis_m, 0, 0], [0, axis_m, 0], [0, 0, axis_m]], float)
        if (res.pose.transform(ends)[:, 2] > 0.01).all():
            o, *tips = camera.project(ends, res.pose).round().astype(int)
            for tip, col in zip(tips, [(0, 0, 255), (0, 255, 0), (255, 0, 0)], strict=True):
                cv2.line(out, tuple(map(int, o)), tuple(map(int, tip)), col, 3, cv2.LINE_AA)
        text = f"ok  {res.inliers} inliers  {res.rmse_px:.2f}px  kf {res.keyframe}"
        color = (0, 220, 0)
    else:
        text, color = str(res.status).upper(), (0, 0, 255)
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 2)
    cv2.rectangle(out, (4, 4), (16 + w, 16 + h), (0, 0, 0), -1)
    cv2.putText(out, text, (10, 10 + h), cv2.FONT_HERSHEY_SIMPLEX, 0.6, color, 2, cv2.LINE_AA)
    stamp = _frame_stamp(res)
    if stamp:  # bottom left: which frame of the video this is, to find it in the CSV
        (w, h), _ = cv2.getTextSize(stamp, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        y1 = out.shape[0] - 4
        cv2.rectangle(out, (4, y1 - 12 - h), (16 + w, y1), (0, 0, 0), -1)
        cv2.putText(out, stamp, (10, y1 - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                    cv2.LINE_AA)  # fmt: skip
    return out


def _frame_stamp(res) -> str:
    """'frame 42  1.400 s' (the CSV's frame and time_s), or '' when the record has none."""
    frame, t = getattr(res, "frame", None), getattr(res, "time_s", None)
    if frame is None or frame == "":
        return ""
    text = f"frame {frame}"
    if t is not None and np.isfinite(t):
        text += f"  {t:.3f} s"
    return text
