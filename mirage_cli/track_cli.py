"""`mirage track VIDEO`: a pose per frame, written row by row (brief, section 4.3)."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import click
import cv2
import numpy as np

from . import refine, ui
from .camera import Camera
from .errors import InputError, OutputError
from .fileio import atomic_path, atomic_write, check_writable, require_file
from .frames import FrameSource, matching_camera
from .model import LandmarkModel
from .posecsv import PoseCSVWriter
from .solver import METHODS, warm_up
from .track import FrameResult, Tracker, TrackSettings

DIAG = ["keyframe", "matches", "inliers", "reproj_rmse_px", "iterations", "sigma_pos_m",
        "sigma_rot_deg", "ms", "mode"]  # fmt: skip


def parse_when(value: str | None, fps: float, option: str = "--start") -> int | None:
    """'12' frames, '2.5s' seconds, or None."""
    if value is None:
        return None
    v = str(value).strip().lower()
    try:
        if v.endswith("s"):
            return int(round(float(v[:-1]) * (fps or 30.0)))
        return int(v)
    except ValueError:
        raise click.BadParameter(
            f"{value!r}: use a frame number (120) or seconds (4s)", param_hint=f"'{option}'"
        ) from None


# --------------------------------------------------------------------------------------
# overlay
# --------------------------------------------------------------------------------------
def draw_overlay(img: np.ndarray, res: FrameResult, camera: Camera, axis_m: float) -> np.ndarray:
    out = img.copy()
    if res.status == "ok":
        if res.inlier_px is not None:  # 3x3 green dots, stamped with numpy
            p = np.rint(res.inlier_px).astype(int)
            h, w = out.shape[:2]
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    x, y = p[:, 0] + dx, p[:, 1] + dy
                    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
                    out[y[ok], x[ok]] = (0, 255, 0)
        ends = np.array([[0, 0, 0], [axis_m, 0, 0], [0, axis_m, 0], [0, 0, axis_m]], float)
        if (res.pose.transform(ends)[:, 2] > 0.01).all():  # W axes: x red, y green, z blue
            o, *tips = camera.project(ends, res.pose).round().astype(int)
            for tip, col in zip(tips, [(0, 0, 255), (0, 255, 0), (255, 0, 0)], strict=True):
                cv2.line(out, tuple(map(int, o)), tuple(map(int, tip)), col, 3, cv2.LINE_AA)
        text = f"ok  {res.inliers} inliers  {res.rmse_px:.2f}px  kf {res.keyframe}"
        color = (0, 220, 0)
    else:
        text, color = res.status.upper(), (0, 0, 255)
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 2)
    cv2.rectangle(out, (4, 4), (16 + w, 16 + h), (0, 0, 0), -1)
    cv2.putText(out, text, (10, 10 + h), cv2.FONT_HERSHEY_SIMPLEX, 0.6, color, 2, cv2.LINE_AA)
    return out


# --------------------------------------------------------------------------------------
# command
# --------------------------------------------------------------------------------------
@click.command("track")
@click.argument("video", nargs=-1, required=True, metavar="VIDEO")
@click.option(
    "--model",
    "model_path",
    required=True,
    type=click.Path(dir_okay=False),
    help="Landmark model from build-model.",
)
@click.option(
    "--camera",
    "camera_path",
    type=click.Path(dir_okay=False),
    help="Camera YAML (default: the camera stored in the model).",
)
@click.option(
    "-o",
    "--output",
    default="poses.csv",
    show_default=True,
    type=click.Path(dir_okay=False),
    help="Pose CSV to write.",
)
@click.option(
    "--method", type=click.Choice(METHODS), default=TrackSettings.method, show_default=True
)
@click.option("--start", default=None, help="First frame: frame number or seconds ('4s').")
@click.option("--end", default=None, help="Stop before this frame / time.")
@click.option(
    "--fps",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Images: frame rate, time_s = index / FPS [default: times in the file names, if any].",
)
@click.option(
    "--every",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Process every N-th frame.",
)
@click.option(
    "--redetect-every",
    type=click.IntRange(min=1),
    default=TrackSettings.redetect_every,
    show_default=True,
    help="Full feature detection at least every N frames (optical flow between).",
)
@click.option("--no-flow", is_flag=True, help="Detect and match in every frame (slower).")
@click.option(
    "--min-inliers",
    type=click.IntRange(min=4),
    default=TrackSettings.min_inliers,
    show_default=True,
)
@click.option(
    "--max-rmse",
    type=click.FloatRange(min=0, min_open=True),
    default=TrackSettings.max_rmse_px,
    show_default=True,
    help="Largest reprojection RMS (px) of an ok frame.",
)
@click.option(
    "--overlay",
    type=click.Path(dir_okay=False),
    help="Write a video with the landmark axes, inliers and status drawn.",
)
@click.option(
    "--tum",
    type=click.Path(dir_okay=False),
    help="Also write a TUM trajectory (time x y z qx qy qz qw) for evo & co.",
)
def track_cmd(
    video,
    model_path,
    camera_path,
    output,
    method,
    start,
    end,
    fps,
    every,
    redetect_every,
    no_flow,
    min_inliers,
    max_rmse,
    overlay,
    tum,
):
    """Estimate the camera pose in every frame of VIDEO (a video file, or images).

    Example: mirage track orbit.mp4 --model landmark.mirage --camera camera.yaml -o poses.csv
    """
    out = check_writable(output)
    for extra in (overlay, tum):
        if extra:
            check_writable(extra)
    model = LandmarkModel.load(require_file(model_path, "model file"))
    camera = model.camera
    if camera_path:
        camera = Camera.load(camera_path)
        if not camera.same_as(model.camera, tol_px=1.0):
            raise InputError(
                f"model {model_path} was built with another camera than "
                f"{camera_path}; rebuild the model or pass the model's camera"
            )
    src = FrameSource(list(video), fps=fps)
    if src.count == 0 and src.is_video:
        ui.log.warning(f"{src.video}: frame count unknown; reading until the end")
    camera = matching_camera(camera, *src.size)
    if method == "ap3p":
        ui.log.warning("ap3p solves from 3 points only: for comparing solvers, not for results")
    settings = TrackSettings(
        method=method,
        redetect_every=redetect_every,
        flow=not no_flow,
        min_inliers=min_inliers,
        max_rmse_px=max_rmse,
    )
    tracker = Tracker(model, camera, settings)
    if not refine.cached_on_disk():
        ui.echo("compiling the pose solver for this machine (first run only, about 10 s)")
    warm_up()  # compile or load it before the first frame's clock starts
    first, last = parse_when(start, src.fps), parse_when(end, src.fps, "--end")
    axis_m = float(np.ptp(model.points, axis=0).max() * 0.4) if len(model.points) else 0.2

    stats = _run(src, tracker, out, camera, first or 0, last, every, overlay, tum, axis_m)
    _summary(stats, out)
    if stats["interrupted"]:
        raise click.exceptions.Exit(130)


def _run(src, tracker, out: Path, camera, first, last, every, overlay, tum, axis_m) -> dict:
    rows: list[tuple] = []
    stack = contextlib.ExitStack()
    ov_tmp = stack.enter_context(atomic_path(overlay)) if overlay else None
    t_start = time.perf_counter()
    total = None
    if src.count:
        total = len(range(first, min(src.count, last) if last else src.count, every))
    interrupted = False
    with stack:
        try:
            _loop(src, tracker, out, camera, first, last, every, ov_tmp, axis_m, total, rows)
        except KeyboardInterrupt:
            interrupted = True
    elapsed = time.perf_counter() - t_start
    if tum:
        _write_tum(tum, rows, src.fps)
    if interrupted:
        ui.log.warning(f"interrupted: kept the {len(rows)} frames done so far in {out}")
    if not rows:
        raise InputError("no frames in the selected range (check --start/--end)")
    return {"rows": rows, "elapsed": elapsed, "interrupted": interrupted}


def _loop(src, tracker, out, camera, first, last, every, ov_tmp, axis_m, total, rows) -> None:
    writer_ov = None
    try:
        with PoseCSVWriter(out, DIAG) as w, ui.progress(total, "tracking") as bar:
            t_loop = time.perf_counter()
            for _, fid, t, img in src.frames(first, last, every):
                t0 = time.perf_counter()
                if img is None:
                    res = FrameResult("decode_error")
                else:
                    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
                    if gray.shape[::-1] != camera.size:
                        res = FrameResult("size_mismatch")
                    else:
                        res = tracker.process(gray)
                ms = (time.perf_counter() - t0) * 1000
                w.write(
                    fid,
                    t,
                    res.status,
                    res.pose,
                    keyframe=res.keyframe,
                    matches=res.matches,
                    inliers=res.inliers,
                    reproj_rmse_px=res.rmse_px,
                    iterations=res.iterations,
                    sigma_pos_m=res.sigma_pos_m,
                    sigma_rot_deg=res.sigma_rot_deg,
                    ms=round(ms, 2),
                    mode=res.mode,
                )
                rows.append((fid, t, res.status, res.inliers, res.pose))
                if ov_tmp is not None and img is not None:
                    if writer_ov is None:
                        fps = src.fps / every if src.fps else 10.0
                        writer_ov = cv2.VideoWriter(
                            str(ov_tmp),
                            cv2.VideoWriter_fourcc(*"mp4v"),
                            fps,
                            (img.shape[1], img.shape[0]),
                        )
                        if not writer_ov.isOpened():
                            raise OutputError("cannot write the overlay video (mp4v)")
                    writer_ov.write(draw_overlay(img, res, camera, axis_m))
                done = len(rows)
                if done % 10 == 0:
                    rate = done / max(time.perf_counter() - t_loop, 1e-9)
                    bar.update(10, f"{rate:.0f} frames/s")
    finally:
        if writer_ov is not None:
            writer_ov.release()


def _write_tum(path, rows, fps) -> None:
    """TUM RGB-D format: timestamp tx ty tz qx qy qz qw (camera pose in W), ok frames only."""
    with atomic_write(path) as f:
        f.write("# timestamp tx ty tz qx qy qz qw (mirage track, camera-to-world)\n")
        for i, (fid, t, status, _, pose) in enumerate(rows):
            if status != "ok":
                continue
            ts = t if np.isfinite(t) else (fid / fps if isinstance(fid, int) and fps else i)
            c, q = pose.center, pose.quat_wxyz
            f.write(
                f"{ts:.6f} {c[0]:.6f} {c[1]:.6f} {c[2]:.6f} "
                f"{q[1]:.9f} {q[2]:.9f} {q[3]:.9f} {q[0]:.9f}\n"
            )


def _summary(stats: dict, out: Path) -> None:
    rows = stats["rows"]
    status = np.array([r[2] for r in rows])
    ok = status == "ok"
    n = len(rows)
    runs, cur = [], 0
    for s in ok:
        cur = 0 if s else cur + 1
        if cur == 1:
            runs.append(1)
        elif cur > 1:
            runs[-1] = cur
    inl = np.array([r[3] for r in rows])[ok]
    fps = n / stats["elapsed"] if stats["elapsed"] > 0 else float("inf")
    ui.echo(
        f"track: {n} frames, {ok.sum()} ok ({100 * ok.mean():.1f}%), "
        f"{len(runs)} lost stretch(es)" + (f", longest {max(runs)} frames" if runs else "")
    )
    other = sorted(set(status) - {"ok", "lost"})
    if other:
        ui.echo("       " + ", ".join(f"{(status == s).sum()} {s}" for s in other))
    if ok.any():
        ui.echo(f"       median inliers {np.median(inl):.0f}, throughput {fps:.1f} frames/s")
    ui.echo(f"       poses written to {out}")
