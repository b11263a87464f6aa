"""`mirage report`: thin CLI over mirage_cli.report (table, summary YAML, plot)."""

from __future__ import annotations

import os

import click

from ..errors import InputError
from ..fileio import check_writable, refuse_overwrite
from ..pipelines.report import nothing_tracked, report, write_report
from ..report import Report
from ..truth import BodyToCamera, TruthSettings
from . import ui
from .options import FILE, FiniteFloat, file_option, output_option, shown

_UNITS = {"_m": "m", "_deg": "deg"}


def report_lines(s: dict) -> list[str]:
    """The summary as a small text table."""
    ll = s["longest_lost"]
    sec = f", {ll['seconds']:.2f} s" if ll["seconds"] is not None and ll["frames"] else ""
    lines = [
        f"report: {s['frames']} frames, {s['tracked']} tracked ({s['tracked_pct']:.1f}%), "
        f"longest lost stretch {ll['frames']} frames{sec}",
        f"  {'error':<20}{'mean':>10}{'RMS':>10}{'p95 |e|':>10}{'max |e|':>10}",
    ]
    if s.get("frames_without_truth"):
        lines.insert(
            1,
            f"  {s['frames_without_truth']} frame(s) without truth (none within the time "
            "tolerance, or no row): left out of the truth errors",
        )
    vis = s.get("visibility")
    if vis and vis["tracked_in_view_pct"] is not None:
        lines.insert(
            1,
            f"  landmark in view in {vis['frames_in_view']} frames: "
            f"{vis['tracked_in_view_pct']:.1f}% tracked; out of view in "
            f"{vis['frames_out_of_view']} frames: {vis['ok_out_of_view']} ok (should be 0)",
        )
    for name, st in s["errors"].items():
        if st["n"] == 0:
            lines.append(f"  {name:<20}{'(no frames)':>10}")
            continue
        vals = "".join(f"{st[k]:>10.4f}" for k in ("mean", "rms", "p95", "max"))
        lines.append(f"  {name:<20}{vals}")
    return lines


@click.command("report")
@click.argument("poses", type=FILE)
@file_option(
    "--path",
    "path",
    required=True,
    help="Desired path: YAML (type: circle | polyline) or waypoint CSV x_m,y_m,z_m[,time_s].",
)
@click.option(
    "--truth",
    type=click.Path(),
    help="Ground truth: pose CSV (joined by frame), TUM file or ROS bag pose topic (nearest "
    "time within --t-max-diff); adds position and rotation error.",
)
@click.option(
    "--truth-topic",
    metavar="NAME",
    help="Bag truth: the pose topic (PoseStamped, PoseWithCovarianceStamped, Odometry, "
    "TransformStamped) [default: the bag's only pose topic].",
)
@click.option(
    "--truth-transform",
    metavar="'X Y Z QW QX QY QZ'|FILE",
    help="T_body_camera: the camera's pose in the tracked body's frame (centre in metres, "
    "quaternion of R_body_camera, camera frame x right, y down, z forward), so that "
    "T_W_camera = T_W_body * T_body_camera; or a file holding that line [default: identity, "
    "the truth is the camera].",
)
@shown(
    "--t-offset",
    type=FiniteFloat(),
    default=TruthSettings.t_offset_s,
    help="Seconds added to the truth stamps before matching them to the frames (TUM, bag).",
)
@shown(
    "--t-max-diff",
    type=FiniteFloat(min=0, min_open=True),
    default=TruthSettings.t_max_diff_s,
    help="Largest time difference (s) between a frame and its truth; frames beyond it get no "
    "truth error.",
)
@output_option("report.csv", "Per-frame error CSV to write.")
@file_option("--summary", help="Also write the summary YAML.")
@file_option("--plot", help="Also write a PNG plot.")
def report_cmd(
    poses, path, truth, truth_topic, truth_transform, t_offset, t_max_diff, output, summary, plot
):
    """Path-following errors of a pose CSV against the desired path (and the truth).

    \b
    Example:
      mirage report poses.csv --path desired_path.yaml --truth truth.csv \\
          -o report.csv --summary summary.yaml --plot report.png
      mirage report poses.csv --path desired_path.yaml --truth flight.bag \\
          --truth-topic /mocap/pose --truth-transform "0.05 0 -0.03 0.5 -0.5 0.5 -0.5"
    """
    refuse_overwrite(
        {"-o": output, "--summary": summary, "--plot": plot},
        {
            "POSES": poses,
            "--path": path,
            "--truth": truth,
            # a file holding the transform (a literal '0 0 0 1 0 0 0' names no file)
            "--truth-transform": truth_transform
            if truth_transform and os.path.exists(os.path.expanduser(truth_transform))
            else None,
        },
    )
    for out in (output, summary, plot):
        if out:
            check_writable(out)
    settings = TruthSettings(truth_topic, BodyToCamera.parse(truth_transform), t_offset, t_max_diff)
    if not truth and (truth_topic or truth_transform or t_offset):
        raise InputError("--truth-topic, --truth-transform and --t-offset need --truth FILE")
    res = report(poses, path, truth, settings, reporter=ui)
    with ui.stage("write the outputs"):
        publish_report(res.report, res.desired, output, summary, plot)


def publish_report(rep: Report, desired, output, summary=None, plot=None) -> None:
    """Write the report's files and print its summary."""
    write_report(rep, output, summary, plot, desired)
    for line in report_lines(rep.summary):
        ui.echo(line)
    wrote = [str(p) for p in (output, summary, plot) if p]
    ui.echo(f"wrote {', '.join(wrote)}")
    if nothing_tracked(rep):
        ui.log.warning("no frame was tracked: every error is empty")
