"""`mirage track VIDEO`: a pose per frame, written row by row (brief, section 4.3)."""

from __future__ import annotations

from collections import Counter

import click
import numpy as np

from ..errors import OptionError
from ..fileio import check_writable, refuse_overwrite, require_file
from ..frames import FrameSource, with_topic
from ..model import LandmarkModel
from ..pipelines.track import TrackResult, nothing_found, open_job, start_warm_up
from ..pipelines.track import track as run_track
from ..records import Status
from ..solver import METHODS
from ..tracking import TrackSettings
from ..tracking.smooth import SmoothSettings
from ..trajectory import FORMATS
from ..viewer import check_room, rerun_module
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


def format_options(f):
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
    default=TrackSettings.max_ok_rmse_px,
    help="Largest reprojection RMS (px) of an ok frame.",
)
@shown(
    "--max-roll",
    type=FiniteFloat(min=0, max=180),
    default=TrackSettings.max_roll_deg,
    help="A pose rolled more than DEG beyond every keyframe (the world's up in the image) "
    "is implausible, not ok; 180: never.",
)
@click.option(
    "--extend",
    is_flag=True,
    help="Track twice: frames tracked well from views the keyframes lack (a drone above a "
    "model made on foot) join the model, and the frames not ok are tracked again.",
)
@file_option(
    "--extended-model",
    "extended_path",
    help="With --extend: also write the grown model (its next flight starts from it).",
)
@file_option("--overlay", help="Write a video with the landmark axes, inliers and status drawn.")
@file_option(
    "--rerun",
    "rerun_path",
    help="Write a Rerun recording (.rrd): frames, inliers, camera path, model; `rerun FILE`.",
)
@format_options
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
    max_roll,
    extend,
    extended_path,
    overlay,
    rerun_path,
    **format_paths,
):
    """Estimate the camera pose in every frame of VIDEO (a video file, or images).

    Example: mirage track orbit.mp4 --model landmark.mirage --camera camera.yaml -o poses.csv
    """
    formats = {name: path for name, path in format_paths.items() if path}  # format -> file
    if extended_path and not extend:
        raise OptionError("needs --extend (the model is grown by it)", "--extended-model")
    refuse_overwrite(
        {"-o": output, "--overlay": overlay, "--rerun": rerun_path}
        | {"--extended-model": extended_path}
        | {FORMATS[n].flag: p for n, p in formats.items()},
        {"VIDEO": video, "--model": model_path, "--camera": camera_path},
    )
    out = check_writable(output)
    for extra in (overlay, rerun_path, extended_path, *formats.values()):
        if extra:
            check_writable(extra)
    if rerun_path:
        rerun_module()  # without the [viz] extra: one line now, not after the tracking
        check_room(rerun_path)
    start_warm_up()  # the compiled kernels load while the model and the video open
    with ui.stage("load model"):
        model = LandmarkModel.load(require_file(model_path, "model file"))
    ui.detail(f"model {model_path}: {len(model.keyframes)} keyframes, {len(model.points)} points")
    with ui.stage("open input"):
        src = FrameSource(with_topic(video, topic), fps=fps)
    ui.detail(f"input: {src.count or 'unknown'} frames at {src.fps:g} frames/s")
    settings = TrackSettings(
        method=method,
        redetect_every=redetect_every,
        flow=not no_flow,
        min_inliers=min_inliers,
        max_ok_rmse_px=max_rmse,
        max_roll_deg=max_roll,
    )
    job = open_job(
        model, src, out, camera_path, settings, start, end, reporter=ui, every=every,
        smooth=SmoothSettings(lag=smooth), formats=formats, overlay=overlay, rerun=rerun_path,
        extend=extend, extended_model=extended_path and check_writable(extended_path),
    )  # fmt: skip
    result = run_track(job, reporter=ui)
    print_summary(result)
    if ui.verbose():
        for line in refusal_lines(result.records):
            ui.detail(line)
    if rerun_path:
        ui.echo(f"       Rerun recording {rerun_path} (view it with: rerun {rerun_path})")
    if result.interrupted is not None:
        raise result.interrupted  # after the outputs are in place
    nothing_found(result)


def refusal_lines(records) -> list[str]:
    """-v after a run: the frames not ok by reason, and the keyframes poses came from."""
    out = []
    refused: dict[tuple[str, str], list] = {}  # (status, reason) -> its records
    for r in records:
        if r[1] != Status.OK.value:
            refused.setdefault((r[1], r[7]), []).append(r)
    for (status, reason), rows in sorted(refused.items(), key=lambda kv: -len(kv[1])):
        n, frames = len(rows), [str(r[0]) for r in rows]
        shown_ = ", ".join(frames[:8]) + (", ..." if len(frames) > 8 else "")
        inl = [r[3] or 0 for r in rows]
        label = f"{status}, {reason}" if reason else status
        out.append(
            f"refused {n} frame(s) as {label} (median {np.median(inl):.0f} inliers): {shown_}"
        )
    kfs = Counter(r[2] for r in records if r[1] == Status.OK.value and r[2])
    if kfs:
        top = ", ".join(f"{k} ({n})" for k, n in kfs.most_common(5))
        out.append(f"keyframes of the ok frames (most used): {top}")
    modes = Counter(r[5] for r in records if r[5])
    if modes:
        out.append("modes: " + ", ".join(f"{m} {n}" for m, n in modes.most_common()))
    # what makes footage slow: why frames were detected rather than flowed
    causes = Counter(r[6] for r in records if r[5] in ("detect", "relocalise") and r[6])
    if causes:
        shown = ", ".join(f"{c} {n}" for c, n in causes.most_common())
        out.append(f"detected rather than flowed, why: {shown}")
    return out


def print_summary(result: TrackResult) -> None:
    rows = result.rows
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
    fps = result.frames_per_s
    ui.echo(
        f"track: {n} frames, {ok.sum()} ok ({100 * ok.mean():.1f}%), "
        f"{len(runs)} lost stretch(es)" + (f", longest {max(runs)} frames" if runs else "")
    )
    other = sorted(set(status) - {Status.OK.value, Status.LOST.value})
    if other:
        ui.echo("       " + ", ".join(f"{(status == s).sum()} {s}" for s in other))
    if result.added:
        ui.echo(f"       {result.added} tracked frames joined the model (--extend)")
    if ok.any():
        ui.echo(f"       median inliers {np.median(inl):.0f}, throughput {fps:.1f} frames/s")
    ui.echo(f"       poses written to {result.output}")
