"""`mirage calibrate`: thin CLI over mirage_cli.calibrate (options, summary, report plot)."""

from __future__ import annotations

import click

from ..boards import MARKER_FRACTION, Board, parse_size
from ..calibrate import CalibOptions, Calibration, Detections, detect_images, detect_video
from ..fileio import check_writable, refuse_overwrite
from ..frames import FrameSource, resolve_inputs, with_topic
from ..pipelines.calibrate import calibrate_to_file
from . import ui
from .config import default_of
from .options import (
    BoundedInt,
    FiniteFloat,
    file_option,
    inputs_argument,
    output_option,
    shown,
    topic_option,
)

_K_NAMES = ("fx", "fy", "cx", "cy")


def parse_board(ctx, param, value):
    if value is None:
        return None
    try:
        return parse_size(value)
    except ValueError as e:
        raise click.BadParameter(str(e), ctx, param) from None


def _positive(ctx, param, value):
    if value is not None and not value > 0:
        raise click.BadParameter(f"must be > 0, got {value}", ctx, param)
    return value


MAX_PLAUSIBLE_SQUARE_M = 0.5  # a printed or plotted board's square; larger is a unit slip


def _positive_option(*decls: str, **kw):
    """A number that must be > 0 when given."""
    return click.option(*decls, type=FiniteFloat(), callback=_positive, **kw)


@click.command("calibrate")
@inputs_argument()
@click.option(
    "--board",
    required=True,
    callback=parse_board,
    help="Chessboard: inner corners COLSxROWS (e.g. 9x6). ChArUco: squares.",
)
@_positive_option("--square", required=True, help="Square side in metres (e.g. 0.025).")
@output_option("camera.yaml", "Camera YAML to write.")
@shown(
    "--pattern",
    type=click.Choice(["chessboard", "charuco"]),
    default=default_of(Board, "pattern"),
)
@_positive_option(
    "--marker", help=f"ChArUco marker side in metres [default: {MARKER_FRACTION:g} x square]."
)
@shown("--dictionary", default=default_of(Board, "dictionary"), help="ChArUco ArUco dictionary.")
@click.option(
    "--legacy-pattern",
    is_flag=True,
    help="ChArUco board made with OpenCV < 4.6 (even number of rows).",
)
@shown(
    "--every",
    type=BoundedInt(min=1),
    default=default_of(detect_video, "every"),
    help="Video: look at every K-th frame.",
)
@shown(
    "--min-motion",
    type=FiniteFloat(min=0),
    default=default_of(detect_video, "min_motion_px"),
    help="Video: skip views whose corners moved less than this (px).",
)
@shown(
    "--model",
    type=click.Choice(["5", "8"]),
    default=str(CalibOptions.model),
    help="Distortion coefficients: 5 (k1 k2 p1 p2 k3) or 8 (rational).",
)
@click.option("--fix-aspect", is_flag=True, help="Estimate one focal length (fx = fy).")
@click.option("--fix-principal-point", is_flag=True, help="Keep cx, cy at the image centre.")
@click.option("--zero-tangent", is_flag=True, help="Fix p1 = p2 = 0.")
@_positive_option(
    "--max-view-error",
    help="Reject views with RMS above this (px) [default: > max("
    f"{CalibOptions.reject_factor:g}x median, median + {CalibOptions.reject_margin_px:g} px)].",
)
@_positive_option(
    "--reject-factor",
    default=CalibOptions.reject_factor,
    show_default=True,
    help="Outlier views: RMS above this x median.",
)
@file_option("--report", default=None, help="Write a PNG with corner coverage and per-view errors.")
@click.option(
    "--subpix-window",
    type=BoundedInt(min=1, max=100),
    default=None,
    help="Fixed cornerSubPix half-window in px [default: 1/4 of the corner spacing, "
    "max 8]; 11 reproduces OpenCV's calibration sample.",
)
@click.option(
    "--workers",
    type=BoundedInt(min=1),
    default=None,
    help="Detection threads [default: CPUs, max 4].",
)
@topic_option()
def calibrate(
    inputs,
    board,
    square,
    output,
    pattern,
    marker,
    dictionary,
    legacy_pattern,
    every,
    min_motion,
    model,
    fix_aspect,
    fix_principal_point,
    zero_tangent,
    max_view_error,
    reject_factor,
    report,
    subpix_window,
    workers,
    topic,
):
    """Calibrate the camera from chessboard or ChArUco images, a folder, a glob or a video.

    \b
    Example:
      mirage calibrate calib/*.jpg --board 9x6 --square 0.025 -o camera.yaml
    """
    refuse_overwrite({"-o": output, "--report": report}, {"INPUT": inputs})
    check_writable(output)  # fail now, not after minutes of detection
    if report:
        check_writable(report)
    for flag, value in (("--square", square), ("--marker", marker)):
        if value is not None and value > MAX_PLAUSIBLE_SQUARE_M:
            ui.log.warning(
                f"{flag} {value:g} is in metres: a {value:g} m square; if you meant "
                f"millimetres, use {flag} {value / 1000:g} (the camera's distances scale with it)"
            )
    target = Board(board[0], board[1], square, pattern, marker, dictionary, legacy_pattern)
    opts = CalibOptions(
        model=int(model),
        fix_aspect=fix_aspect,
        fix_principal_point=fix_principal_point,
        zero_tangent=zero_tangent,
        reject_factor=reject_factor,
        max_view_error_px=max_view_error,
    )
    media = resolve_inputs(with_topic(inputs, topic), what="board images")
    if media.is_video:
        n = FrameSource([media.video]).count
        with ui.progress((n + every - 1) // every if n else None, "detecting") as bar:
            det = detect_video(
                media.video, target, every, min_motion, workers, bar.update, subpix_window
            )
    else:
        with ui.progress(len(media.images), "detecting") as bar:
            det = detect_images(media.images, target, workers, bar.update, subpix_window)
    calibrate_detections(det, target, opts, output, report)


def calibrate_detections(det: Detections, target: Board, opts: CalibOptions, output, report=None):
    """Calibrate from detected views, write the camera YAML (and plot), print the summary."""
    calib = calibrate_to_file(det, target, opts, output, report)
    _summary(calib, det, target, output, report)


def _summary(c: Calibration, det: Detections, b: Board, output, report) -> None:
    what = "frames" if det.views and det.views[0].frame is not None else "images"
    s = c.std_intrinsics
    ui.echo(f"board {b.label} {b.pattern}, square {b.square_m * 1000:g} mm")
    line = f"views: {len(det.views)} found in {det.examined} {what}"
    if det.not_found:
        line += f" ({len(det.not_found)} without board)"
    if det.unreadable:
        line += f", {len(det.unreadable)} unreadable"
    if det.duplicates:
        line += f", {det.duplicates} near-duplicates skipped"
    ui.echo(line)
    ui.echo(f"used:  {len(c.views)} views, {len(c.rejected)} rejected")
    for v, e in c.rejected:
        ui.echo(f"  rejected {v.name}: RMS {e:.2f} px > limit {c.threshold_px:.2f} px")
    ui.echo(f"RMS reprojection error: {c.rms_px:.3f} px")
    pm = {k: f"+- {v:.2f}" if v > 0 else "(fixed)" for k, v in s.items()}
    ui.echo(f"fx {c.K[0, 0]:.2f} {pm['fx']}   fy {c.K[1, 1]:.2f} {pm['fy']} px")
    ui.echo(f"cx {c.K[0, 2]:.2f} {pm['cx']}   cy {c.K[1, 2]:.2f} {pm['cy']} px")
    dist = "  ".join(f"{n} {v:+.4f}" for n, v in zip(_dist_names(c), c.dist, strict=True))
    ui.echo(f"distortion: {dist}")
    ui.echo(f"wrote {output}" + (f" and {report}" if report else ""))
    for w in c.warnings:
        ui.log.warning(w)


def _dist_names(c: Calibration) -> list[str]:
    return [k for k in c.std_intrinsics if k not in _K_NAMES]
