"""`mirage build-model` and `mirage inspect`: thin CLI over mirage_cli.build_model / model."""

from __future__ import annotations

import time

import click

from .. import signals
from ..boards import load_board
from ..build_model import ROI, UP_AXES, BuildResult, BuildSettings, coverage_warning
from ..camera import Camera, lens_fold_warning
from ..errors import InputError
from ..features import DETECTORS, DetectorSettings
from ..fileio import check_writable, refuse_overwrite
from ..frames import FrameSource, resolve_inputs, with_topic
from ..model import REACH_DEG, LandmarkModel
from ..pipelines.build import build
from ..pipelines.build import save_model as write_model
from ..plotting import TOP_VIEW_DPI, save_png, top_view_figure
from ..viewer import check_room, record_model, rerun_module
from . import ui
from .config import default_of
from .options import (
    FILE,
    BoundedInt,
    FiniteFloat,
    camera_option,
    file_option,
    inputs_argument,
    output_option,
    shown,
    topic_option,
)


def model_lines(model: LandmarkModel) -> list[str]:
    s = model.summary()
    return [
        f"keyframes          {s['keyframes']} ({s['detector']}, every {s['spacing_deg']:.0f} deg)",
        f"3D points          {s['points']} (linked per keyframe: min "
        f"{s['linked_per_keyframe_min']}, median {s['linked_per_keyframe_median']:.0f})",
        f"mean track length  {s['mean_track_length']:.2f} views",
        f"reprojection error mean {s['mean_reprojection_px']:.3f} px, "
        f"RMS {s['rms_reprojection_px']:.3f} px",
        f"azimuth coverage   {s['azimuth_coverage_deg']:.0f} deg within {REACH_DEG:g} deg of a "
        f"keyframe (largest gap {s['largest_gap_deg']:.0f} deg)",
        *_kept_lines(model),
        *_roi_lines(model),
        *_up_lines(model),
        *_check_lines(model),
        *_view_lines(model),
    ]


def _view_lines(model: LandmarkModel) -> list[str]:
    out = []
    if model.has_tilted:
        n = sum(len(kf.tilted[2]) for kf in model.keyframes)
        out.append(f"tilted views       {n} features of the keyframes as from 45 and 60 deg higher")
    if model.has_images:
        mb = sum(len(kf.image) for kf in model.keyframes) / 1e6
        n = len(model.keyframes)
        out.append(f"keyframe images    {n} ({mb:.1f} MB), for patches (far, from above)")
    return out


def _kept_lines(model: LandmarkModel) -> list[str]:
    """How many keyframes were kept for their azimuth and how many for their view change."""
    kept = model.meta.get("kept") or {}
    if not kept:
        return []
    by_change = sum(str(v).startswith("view change") for v in kept.values())
    return [
        f"kept because       {len(kept) - by_change} azimuth bin(s), {by_change} view "
        "change(s) (a camera moving sideways or forward)"
    ]


def _check_lines(model: LandmarkModel) -> list[str]:
    c = model.meta.get("check") or {}
    if not c.get("keyframes"):
        return []
    return [
        f"keyframe check     {c['keyframes']} keyframes solved from the others' points: off by "
        f"median {1000 * c['median_error_m']:.2f} mm / {c['median_error_deg']:.3f} deg, error "
        f"scale {c['error_scale']:.2f} (x the predicted sigma; widens every tracked sigma)"
    ]


def _up_lines(model: LandmarkModel) -> list[str]:
    up = model.meta.get("up")
    if not up:
        return []
    how = f" ({up['how']})" if up.get("how") else ""
    return [f"up axis            {up.get('axis')} of the pose file's frame" + how]


def _roi_lines(model: LandmarkModel) -> list[str]:
    roi = model.meta.get("roi")
    if not roi:
        return []
    vals = ", ".join(f"{float(v):.3g}" for v in roi.get("values") or [])
    why = f" ({roi['reason']})" if roi.get("reason") else ""
    return [f"volume of interest {roi.get('kind')}" + (f" [{vals}] m" if vals else "") + why]


class _Stages:
    """One progress bar per stage of the build (silent when stdout is not a terminal)."""

    def __init__(self):
        self.name, self.cm, self.bar = None, None, None

    def __call__(self, name: str, k: int, n: int) -> None:
        if name != self.name:
            self.close()
            self.name, self.cm = name, ui.progress(n, name)
            self.bar = self.cm.__enter__()
        self.bar.update(1)

    def close(self) -> None:
        if self.cm is not None:
            self.cm.__exit__(None, None, None)
        self.name, self.cm, self.bar = None, None, None


@click.command("build-model")
@inputs_argument()
@camera_option("Camera YAML (from mirage calibrate) [default: a ROS bag's camera_info].")
@topic_option()
@file_option(
    "--poses",
    "poses_path",
    help="Pose CSV: one row per image (frame = file name) or video frame (frame = index).",
)
@file_option(
    "--board",
    "board_path",
    help="Board YAML: a ChArUco / ArUco grid board in view gives each pose and defines W.",
)
@output_option("landmark.mirage", "Model file to write.")
@shown(
    "--spacing-deg",
    type=FiniteFloat(1, 90),
    default=BuildSettings.spacing_deg,
    help="One keyframe per this much azimuth (per elevation band).",
)
@shown("--detector", type=click.Choice(DETECTORS), default=DetectorSettings.name)
@shown(
    "--nfeatures",
    type=BoundedInt(min=50, max=1_000_000),
    default=DetectorSettings.nfeatures,
    help="Features detected per view.",
)
@shown(
    "--roi",
    default=default_of(BuildSettings, "roi").kind,
    help="Volume of interest: auto | none | R,ZMIN,ZMAX (cylinder about the origin) | "
    "XMIN,XMAX,YMIN,YMAX,ZMIN,ZMAX (box), metres.",
)
@shown(
    "--up",
    type=click.Choice(UP_AXES),
    default=BuildSettings.up,
    help="The world frame's up axis (the pose file's or board's W): auto finds it from the "
    "views' camera up direction. The model is kept levelled; poses are written in W.",
)
@shown(
    "--max-reproj-px",
    type=FiniteFloat(min=0.1),
    default=BuildSettings.max_reproj_px,
    help="Keep points that reproject within this in every view.",
)
@shown(
    "--min-angle-deg",
    type=FiniteFloat(min=0, max=90),
    default=BuildSettings.min_angle_deg,
    help="Minimum triangulation angle.",
)
@click.option(
    "--tilted-views/--no-tilted-views",
    default=BuildSettings.tilted_views,
    show_default=True,
    help="Also store each keyframe's features as seen from 45 and 60 deg higher (views "
    "squashed along the up axis), for videos from well above the keyframes (a drone over "
    "a model made on foot). Off: a 30% smaller, faster-built model.",
)
@click.option(
    "--keyframe-images/--no-keyframe-images",
    default=BuildSettings.keyframe_images,
    show_default=True,
    help="Store the keyframes' grey images (PNG, about 0.14 MB each at 640x480): the points "
    "of a far landmark, or of a view from well above the keyframes, are then placed by "
    "their keyframe patches, to a fraction of a pixel. Off: a smaller model; such frames "
    "by keypoints alone.",
)
def build_model_cmd(
    inputs,
    camera_path,
    topic,
    poses_path,
    board_path,
    output,
    spacing_deg,
    detector,
    nfeatures,
    roi,
    up,
    max_reproj_px,
    min_angle_deg,
    tilted_views,
    keyframe_images,
):
    """Build a 360-degree landmark model from images (a folder or glob) or a video.

    Each view's pose comes from a pose CSV (--poses) or a fiducial board in view
    (--board). Example:

    \b
      mirage build-model sample_data/keyframes \\
        --poses sample_data/keyframes/poses.csv \\
        --camera sample_data/camera_truth.yaml -o landmark.mirage
    """
    if (poses_path is None) == (board_path is None):
        raise InputError("give exactly one of --poses FILE or --board FILE")
    refuse_overwrite(
        {"-o": output},
        {"INPUT": inputs, "--camera": camera_path, "--poses": poses_path, "--board": board_path},
    )
    check_writable(output)
    t0 = time.perf_counter()
    sources = with_topic(inputs, topic)  # a bag input carries its --topic
    camera = Camera.load(camera_path) if camera_path else _bag_camera(sources)
    if (fold := lens_fold_warning(camera)) is not None:
        ui.log.warning(f"{fold}; recalibrate with the board in the corners")
    board = load_board(board_path) if board_path else None
    settings = BuildSettings(
        detector=DetectorSettings(detector, nfeatures),
        spacing_deg=spacing_deg,
        max_reproj_px=max_reproj_px,
        min_angle_deg=min_angle_deg,
        roi=ROI.parse(roi),
        up=up,
        tilted_views=tilted_views,
        keyframe_images=keyframe_images,
    )
    stages = _Stages()
    try:
        res = build(sources, camera, settings, poses_path, board, stages)
    finally:
        stages.close()
    source = {
        "inputs": list(inputs),
        "topic": topic,
        "poses": poses_path,
        "board": board.to_yaml() if board else None,
    }
    signals.check()  # a signal swallowed by compiled code must not replace the model
    save_model(res, output, source, t0)


def _bag_camera(inputs) -> Camera:
    """Without --camera: the camera_info of a bag input's image topic."""
    media = resolve_inputs(inputs, "images of the landmark")
    if not media.is_bag:
        raise InputError("give --camera FILE (the camera YAML from mirage calibrate)")
    src = FrameSource([media.video])
    camera = src.camera()
    if camera is None:
        raise InputError(
            f"{media.video} has no calibrated camera_info for {src.bag.topic}; give --camera FILE"
        )
    return camera


def save_model(res: BuildResult, output, source: dict, t0: float) -> None:
    """Write a built model (with where it came from), warn about weak parts, summarise."""
    write_model(res, output, source)
    r = res.rejected
    ui.echo(f"build-model: wrote {output} in {time.perf_counter() - t0:.1f} s")
    for line in model_lines(res.model):
        ui.echo("  " + line)
    ui.echo(
        f"  candidates         {res.tracks} tracks from {res.matches} matches in {res.pairs} "
        f"keyframe pairs; dropped: {r['reprojection']} reprojection, {r['angle']} angle, "
        f"{r['behind']} behind camera, {r['roi']} outside ROI"
    )


@click.command("inspect")
@click.argument("model_path", metavar="MODEL", type=FILE)
@file_option("--plot", help="Write a top view (PNG) of the keyframes and 3D points.")
@file_option(
    "--rerun",
    "rerun_path",
    help="Write a Rerun recording (.rrd) of the 3D points and keyframe cameras.",
)
def inspect_cmd(model_path, plot, rerun_path):
    """Print a landmark model's summary; optionally plot it from above."""
    refuse_overwrite({"--plot": plot, "--rerun": rerun_path}, {"MODEL": model_path})
    if rerun_path:
        check_writable(rerun_path)
        rerun_module()  # without the [viz] extra: one line before any work
        check_room(rerun_path)
    t0 = time.perf_counter()
    model = LandmarkModel.load(model_path)
    dt = time.perf_counter() - t0
    if plot:
        check_writable(plot)
    ui.echo(f"{model_path}: format version {model.version}, loaded in {dt * 1000:.0f} ms")
    c = model.camera
    ui.echo(f"  camera             {c.width}x{c.height}, fx {c.fx:.1f} px")
    for line in model_lines(model):
        ui.echo("  " + line)
    kept = model.meta.get("kept") or {}
    for kf in model.keyframes:
        why = kept.get(kf.name, "")
        ui.echo(f"    {kf.name:<20} {kf.n_linked:5d} points" + (f"  kept: {why}" if why else ""))
    gap = coverage_warning(model)
    if gap:
        ui.log.warning(gap)
    if plot:
        save_png(top_view_figure(model), plot, TOP_VIEW_DPI, bbox_inches="tight")
        ui.echo(f"  plot               {plot}")
    if rerun_path:
        record_model(rerun_path, model)
        ui.echo(f"  Rerun recording    {rerun_path} (view it with: rerun {rerun_path})")
