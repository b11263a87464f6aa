"""`mirage track VIDEO`: a pose per frame, written row by row (brief, section 4.3)."""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

import click
import cv2
import numpy as np

from .. import refine, runtime, signals, track
from ..camera import Camera
from ..errors import EnvironmentFailure, InputError, NothingFound, OutputError
from ..fileio import (
    atomic_path,
    check_writable,
    refuse_overwrite,
    require_file,
    video_frames_written,
)
from ..frames import FrameSource, gray_frames, matching_camera, prefetch, with_topic
from ..model import LandmarkModel
from ..plotting import draw_overlay
from ..records import Status
from ..smooth import Smoother, SmoothSettings
from ..solver import METHODS
from ..track import Tracker, TrackSettings, warm_up
from ..trajectory import FORMATS, TRACK_COLUMNS, TrajectoryWriter
from ..validate import frame_range
from ..viewer import TrackRecording, check_room, rerun_module
from . import ui
from .options import (
    FRAME_OR_TIME,
    BoundedInt,
    FiniteFloat,
    camera_option,
    file_option,
    inputs_argument,
    option_errors,
    output_option,
    shown,
    topic_option,
)


def also_write_options(f):
    """`--tum FILE`, `--kitti FILE`, ...: one option per trajectory format in FORMATS that
    declares a flag, in FORMATS order; the parameter is the format's name."""
    flagged = [(name, fmt) for name, fmt in FORMATS.items() if fmt.flag]
    for name, fmt in reversed(flagged):  # decorators apply bottom-up
        f = file_option(fmt.flag, name, help=fmt.help)(f)
    return f


# --------------------------------------------------------------------------------------
# command
# --------------------------------------------------------------------------------------
@click.command("track")
@inputs_argument("video", metavar="VIDEO")
@file_option("--model", "model_path", required=True, help="Landmark model from build-model.")
@camera_option(
    "Camera YAML (default: a ROS bag's camera_info, else the camera stored in the model)."
)
@topic_option()
@output_option("poses.csv", "Pose CSV to write.")
@shown("--method", type=click.Choice(METHODS), default=TrackSettings.method)
@click.option(
    "--start",
    type=FRAME_OR_TIME,
    default=None,
    help="First frame: frame number or seconds ('4s').",
)
@click.option("--end", type=FRAME_OR_TIME, default=None, help="Stop before this frame / time.")
@click.option(
    "--fps",
    type=FiniteFloat(min=0, min_open=True),
    default=None,
    help="Images: frame rate, time_s = index / FPS [default: times in the file names, if any].",
)
@shown("--every", type=BoundedInt(min=1), default=1, help="Process every N-th frame.")
@shown(
    "--redetect-every",
    type=BoundedInt(min=1),
    default=TrackSettings.redetect_every,
    help="Full feature detection at least every N frames (optical flow between).",
)
@click.option("--no-flow", is_flag=True, help="Detect and match in every frame (slower).")
@shown(
    "--smooth",
    type=BoundedInt(min=0),
    default=SmoothSettings.lag,
    help="Smooth each pose with the N frames before and after it (a constant-velocity "
    "prior; rows come N frames late); 0: each frame's own pose.",
)
@shown(
    "--min-inliers",
    type=BoundedInt(min=4, max=100_000),
    default=TrackSettings.min_inliers,
    help="Fewest inliers of a pose found without a prediction (while tracking: 6, and the "
    "pose's uncertainty decides).",
)
@shown(
    "--max-rmse",
    type=FiniteFloat(min=0, min_open=True),
    default=TrackSettings.max_rmse_px,
    help="Largest reprojection RMS (px) of an ok frame.",
)
@file_option("--overlay", help="Write a video with the landmark axes, inliers and status drawn.")
@file_option(
    "--rerun",
    "rerun_path",
    help="Write a Rerun recording (.rrd): frames, inliers, camera path, model; `rerun FILE`.",
)
@also_write_options
@option_errors
def track_cmd(
    video,
    model_path,
    camera_path,
    topic,
    output,
    method,
    start,
    end,
    fps,
    every,
    redetect_every,
    no_flow,
    smooth,
    min_inliers,
    max_rmse,
    overlay,
    rerun_path,
    **also,
):
    """Estimate the camera pose in every frame of VIDEO (a video file, or images).

    Example: mirage track orbit.mp4 --model landmark.mirage --camera camera.yaml -o poses.csv
    """
    also = {name: path for name, path in also.items() if path}  # format -> file
    refuse_overwrite(
        {"-o": output, "--overlay": overlay, "--rerun": rerun_path}
        | {FORMATS[n].flag: p for n, p in also.items()},
        {"VIDEO": video, "--model": model_path, "--camera": camera_path},
    )
    out = check_writable(output)
    for extra in (overlay, rerun_path, *also.values()):
        if extra:
            check_writable(extra)
    if rerun_path:
        rerun_module()  # without the [viz] extra: one line now, not after the tracking
        check_room(rerun_path)
    with ui.stage("load model"):
        model = LandmarkModel.load(require_file(model_path, "model file"))
    ui.detail(f"model {model_path}: {len(model.keyframes)} keyframes, {len(model.points)} points")
    with ui.stage("open input"):
        src = FrameSource(with_topic(video, topic), fps=fps)
    ui.detail(f"input: {src.count or 'unknown'} frames at {src.fps:g} frames/s")
    camera = tracking_camera(model, camera_path, src)
    first, last = frame_range(start, end, src.fps)  # an empty range fails before any output
    if src.count == 0 and src.is_video:
        ui.log.warning(f"{src.video}: frame count unknown; reading until the end")
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
    runtime.opencv_threads_for_two_callers()
    stats = track_to_files(
        src, tracker, out, first or 0, last, every, overlay, also, rerun_path,
        SmoothSettings(lag=smooth),
    )  # fmt: skip
    nothing_found(stats["rows"], out)


def nothing_found(rows, out) -> None:
    """No frame ok: say why in one line (exit 3), after the outputs are written."""
    status = [str(r[0]) for r in rows]
    if not status or Status.OK.value in status:
        return
    raise NothingFound(
        f"the landmark was not found in any of the {len(status)} frames ({out} written, no pose): "
        "check that --model is this landmark's model and --camera this video's camera"
    )


def tracking_camera(model, camera_path, src):
    """The camera to track `src` with: the camera file, else a bag's camera_info, else the
    model's own (at the frames' size). Another camera than the model's is fine (a model
    built from a phone's photos, a flight filmed by the drone's camera): the model is 3D
    points and scale-invariant descriptors, and the tracker projects with this camera."""
    camera, origin = model.camera, None
    if camera_path:
        camera, origin = Camera.load(camera_path), str(camera_path)
    elif (info := src.camera()) is not None:
        camera, origin = info, f"the camera_info of {src.bag.topic}"
    if origin and not camera.same_as(model.camera, tol_px=1.0):
        ui.echo(
            f"track: the model was built with another camera ({_describe(model.camera)}); "
            f"tracking with {origin} ({_describe(camera)})"
        )
    return matching_camera(camera, *src.size)


def _describe(camera: Camera) -> str:
    return f"{camera.width}x{camera.height}, fx {camera.K[0, 0]:.0f} px"


def track_to_files(
    src, tracker, output, first=0, last=None, every=1, overlay=None, also=None, rerun=None,
    smooth: SmoothSettings | None = None,
) -> dict:  # fmt: skip
    """Track the frames, writing each record to the pose CSV (and to `also`, format name ->
    file, e.g. {"tum": "poses.tum"}, the overlay and the Rerun recording) as it comes
    (`smooth.lag` frames late: default settings when None; lag 0: unsmoothed);
    print the summary and return the run's figures (`rows`: status and inliers per frame).
    Ctrl-C or SIGTERM keeps the finished frames in every output, then the interrupt goes
    on (exit 130 / 143)."""
    if not refine.cached_on_disk():
        ui.echo("compiling the pose solver for this machine (first run only, about 10 s)")
    # compile or load it before the first frame's clock starts; loading from the cache
    # (under a second) runs numba's callbacks, which would swallow a signal: held meanwhile
    with (
        ui.stage("load the compiled solver"),
        signals.deferred() if refine.cached_on_disk() else contextlib.nullcontext(),
    ):
        warm_up()
    signals.check()
    runtime.keep_freed_memory()  # every detection's pyramid reuses the last one's pages
    points = tracker.model.points
    axis_m = float(np.ptp(points, axis=0).max() * 0.4) if len(points) else 0.2
    outputs = [(output, "csv")] + [(path, fmt) for fmt, path in (also or {}).items() if path]
    smoother = Smoother(smooth or SmoothSettings())
    stats = _track(
        src, tracker, outputs, tracker.camera, first, last, every, overlay, axis_m, rerun,
        smoother,
    )  # fmt: skip
    ui.detail(f"stage tracking: {stats['elapsed']:.2f} s")
    _summary(stats, output)
    if ui.verbose():
        for line in refusal_lines(stats["records"]):
            ui.detail(line)
    if rerun:
        ui.echo(f"       Rerun recording {rerun} (view it with: rerun {rerun})")
    if stats["interrupted"] is not None:
        raise stats["interrupted"]  # after the outputs are in place
    return stats


def _track(
    src, tracker, outputs, camera, first, last, every, overlay, axis_m, rerun, smoother
) -> dict:
    """Run the tracker over the frames and write every record to every output as it comes.
    An interrupt keeps the finished frames (outputs renamed into place with further signals
    held) and is returned, to be raised once the summary is out."""
    total = None
    if src.count:
        total = len(range(first, min(src.count, last) if last else src.count, every))
    done: list[tuple[str, int]] = []  # (status, inliers) per frame, for the summary
    decided: list[tuple] = []  # with -v: (frame, status, keyframe, inliers, matches, mode)
    verbose = ui.verbose()
    interrupted = None
    t_start = time.perf_counter()
    with contextlib.ExitStack() as hold, contextlib.ExitStack() as stack:
        # every format is offered the diagnostic columns; TUM's and KITTI's rows skip them
        writers = [
            stack.enter_context(TrajectoryWriter(path, fmt, TRACK_COLUMNS)) for path, fmt in outputs
        ]
        fps = src.fps / every if src.fps else 10.0
        ov = stack.enter_context(_Overlay(overlay, fps, camera, axis_m)) if overlay else None
        rrd = None
        if rerun:
            rrd = stack.enter_context(TrackRecording(rerun, tracker.model, camera))
        bar = stack.enter_context(ui.progress(total, "tracking"))
        keep = ov is not None or rrd is not None  # the overlays draw on the colour image
        frames = src.frames(first, last, every)
        frames = prefetch(frames if keep else gray_frames(frames))

        def emit(records):
            for rec in records:
                # a record goes to every output or to none: a signal waits until it is out
                # (else the overlay could hold a frame fewer than the CSV)
                with signals.deferred():
                    for w in writers:
                        w.write(rec)
                    if rrd is not None:  # before the overlay, which takes the image
                        rrd.write(rec)
                    if ov is not None:
                        ov.write(rec)
                    done.append((rec.status, rec.inliers))
                    if verbose:
                        decided.append((rec.frame, str(rec.status), rec.keyframe, rec.inliers,
                                        rec.matches, rec.mode))  # fmt: skip
                        ui.detail(frame_line(rec), 2)
                if len(done) % 10 == 0:
                    rate = len(done) / max(time.perf_counter() - t_start, 1e-9)
                    bar.update(10, f"{rate:.0f} frames/s")

        try:
            for rec in track.run(frames, tracker, keep_images=keep):
                emit(smoother.push(rec))
            with signals.deferred():  # the last frames held back by the smoother
                emit(smoother.flush())
        except KeyboardInterrupt as e:
            hold.enter_context(signals.deferred())  # a second signal waits for the files
            emit(smoother.flush())  # the frames already tracked are kept
            if not writers[0].rows:
                signals.note(e, f"no frame finished; {outputs[0][0]} not written")
                raise
            interrupted = e
        if not done and interrupted is None:
            raise InputError("no frames in the selected range (check --start/--end)")
    elapsed = time.perf_counter() - t_start
    if interrupted is not None:
        signals.note(interrupted, f"kept {writers[0].rows} frames in {outputs[0][0]}")
    return {"rows": done, "elapsed": elapsed, "interrupted": interrupted, "records": decided}


def frame_line(rec) -> str:
    """-vv: one line per frame, what was decided and from what."""
    why = f" ({rec.mode})" if getattr(rec, "mode", None) else ""
    kf = f", keyframe {rec.keyframe}" if getattr(rec, "keyframe", None) else ""
    return (
        f"frame {rec.frame}: {rec.status}{why}{kf}, {rec.inliers or 0} inliers of "
        f"{rec.matches or 0} matches"
    )


def refusal_lines(records) -> list[str]:
    """-v after a run: the frames not ok by reason, and the keyframes poses came from."""
    from collections import Counter

    out = []
    refused = Counter(r[1] for r in records if r[1] != Status.OK.value)
    for status, n in refused.most_common():
        frames = [str(r[0]) for r in records if r[1] == status]
        shown_ = ", ".join(frames[:8]) + (", ..." if len(frames) > 8 else "")
        inl = [r[3] or 0 for r in records if r[1] == status]
        out.append(
            f"refused {n} frame(s) as {status} (median {np.median(inl):.0f} inliers): {shown_}"
        )
    kfs = Counter(r[2] for r in records if r[1] == Status.OK.value and r[2])
    if kfs:
        top = ", ".join(f"{k} ({n})" for k, n in kfs.most_common(5))
        out.append(f"keyframes of the ok frames (most used): {top}")
    modes = Counter(r[5] for r in records if r[5])
    if modes:
        out.append("modes: " + ", ".join(f"{m} {n}" for m, n in modes.most_common()))
    return out


class _Overlay:
    """The overlay video, opened at the first decoded frame (whose size it takes)."""

    def __init__(self, path, fps: float, camera, axis_m: float):
        # VideoWriter reports no write error: the video must read back with its frames (one
        # of slack: a signal can land between writing a frame and counting it)
        # (no suffix, e.g. /dev/null: an .mp4 temporary file, so that OpenCV picks a container)
        self._path = atomic_path(
            path,
            suffix=Path(path).suffix or ".mp4",
            verify=lambda p: video_frames_written(p) >= self.n - 1,
        )
        self.path = path
        self.fps, self.camera, self.axis_m = fps, camera, axis_m
        self.writer, self.n = None, 0

    def __enter__(self):
        self.tmp = self._path.__enter__()
        return self

    def write(self, rec) -> None:
        img, rec.image = rec.image, None
        if img is None:
            return
        if self.writer is None:
            self.writer = cv2.VideoWriter(
                str(self.tmp),
                cv2.VideoWriter_fourcc(*"mp4v"),
                self.fps,
                (img.shape[1], img.shape[0]),
            )
            if not self.writer.isOpened():
                raise overlay_failure(self.path, self.tmp)
        self.writer.write(draw_overlay(img, rec, self.camera, self.axis_m))
        self.n += 1

    def __exit__(self, *exc):
        if self.writer is not None:
            self.writer.release()
        return self._path.__exit__(*exc)


def overlay_failure(path, tmp) -> OutputError | EnvironmentFailure:
    """Why the overlay video did not open, naming the file: a full disk is the machine's
    failure (exit 1), anything else the output's (exit 2)."""
    with contextlib.suppress(OSError):
        fs = os.statvfs(Path(tmp).parent)
        if fs.f_bavail * fs.f_frsize < (1 << 20):
            return EnvironmentFailure(f"cannot write {path}: no space left on device")
    return OutputError(f"cannot write the overlay video {path} (OpenCV's mp4v writer did not open)")


def _summary(stats: dict, out: Path) -> None:
    rows = stats["rows"]
    status = np.array([str(r[0]) for r in rows])
    ok = status == Status.OK
    n = len(rows)
    runs, cur = [], 0
    for s in ok:
        cur = 0 if s else cur + 1
        if cur == 1:
            runs.append(1)
        elif cur > 1:
            runs[-1] = cur
    inl = np.array([r[1] for r in rows])[ok]
    fps = n / stats["elapsed"] if stats["elapsed"] > 0 else float("inf")
    ui.echo(
        f"track: {n} frames, {ok.sum()} ok ({100 * ok.mean():.1f}%), "
        f"{len(runs)} lost stretch(es)" + (f", longest {max(runs)} frames" if runs else "")
    )
    other = sorted(set(status) - {Status.OK.value, Status.LOST.value})
    if other:
        ui.echo("       " + ", ".join(f"{(status == s).sum()} {s}" for s in other))
    if ok.any():
        ui.echo(f"       median inliers {np.median(inl):.0f}, throughput {fps:.1f} frames/s")
    ui.echo(f"       poses written to {out}")
