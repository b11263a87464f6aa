"""A catalogue of bad inputs and faults across every command (issue 14).

Each case asserts the error contract: the exit code (2 a user error, 1 the machine, 130 /
143 a signal), exactly one line on stderr, no traceback, no Python warning, and every
file that existed before (good outputs, the inputs themselves) byte-identical after,
with no temporary file left behind. Argument and input cases run in-process through
`cli.main` (one import for all); signals, a closed stdout and start-up run as real
processes.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from conftest import ROOT, SAMPLE, own_signal_handlers, small_tmpfs

from mirage_cli import __version__, cli

CAL = ROOT / "tests" / "data" / "chessboard-right"
GOOD = "frame,x_m,y_m,z_m,qw,qx,qy,qz\n0,1,2,0.5,1,0,0,0\n1,1.1,2,0.5,1,0,0,0\n"
BAD_FILES = {
    "dup.csv": GOOD + "1,1.2,2,0.5,1,0,0,0\n",
    "dup_float.csv": GOOD + "1.0,1.2,2,0.5,1,0,0,0\n",
    "inf.csv": GOOD + "2,inf,2,0.5,1,0,0,0\n",
    "ninf.csv": GOOD + "2,1,-inf,0.5,1,0,0,0\n",
    "nan.csv": GOOD + "2,1,nan,0.5,1,0,0,0\n",
    "tinf.csv": "frame,time_s,x_m,y_m,z_m,qw,qx,qy,qz\n0,inf,1,2,0.5,1,0,0,0\n",
    "q2.csv": GOOD + "2,1,2,0.5,2,0,0,0\n",
    "q0.csv": GOOD + "2,1,2,0.5,0,0,0,0\n",
    "qhalf.csv": GOOD + "2,1,2,0.5,0.5,0.5,0,0\n",
    "empty.csv": "",
    "header.csv": "frame,x_m,y_m,z_m,qw,qx,qy,qz\n",
    "nocol.csv": "frame,x_m,y_m,z_m,qw,qx,qy\n0,1,2,3,1,0,0\n",
    "text.csv": "\x00\x01\x02garbage\xff",
    "bad.yaml": "type: circle\ncenter: [0, 0\n",
    "notzip.mirage": "this is not a model\n",
    "zero_q.tum": "0.0 1 2 0.5 0 0 0 1\n0.033 1 2 0.5 0 0 0 0\n",
    "big_q.tum": "0.0 1 2 0.5 0 0 0 1\n0.033 1 2 0.5 0 0 0 2\n",
    "dup_t.tum": "0.0 1 2 0.5 0 0 0 1\n0.0 1.1 2 0.5 0 0 0 1\n",
    "nan.tum": "0.0 1 2 nan 0 0 0 1\n",
    "scaled_r.kitti": "2 0 0 1 0 2 0 2 0 0 2 0.5\n",
    "mirror_r.kitti": "-1 0 0 1 0 1 0 2 0 0 1 0.5\n",
}
# good outputs that exist before every case: a failing run must leave them as they are
PROTECTED = {
    "out.csv": "frame,previous,good,output\n",
    "out.yaml": "previous: good camera\n",
    "out.png": "previous good plot",
    "out.mirage": "previous good model",
    "out.tum": "# previous good trajectory\n",
}


@dataclass
class Case:
    id: str
    args: list
    code: int = 2
    contains: str = ""
    needs: list = field(default_factory=list)  # extra setup: "kp_copy", "synth_cam", "config"


def C(id, *args, code=2, contains="", needs=()):  # noqa: N802 - a table row
    return pytest.param(Case(id, list(args), code, contains, list(needs)), id=id)


TRACK = ["track", "{V}", "--model", "{M}", "-o", "out.csv"]
CALIB = ["calibrate", "{CAL}", "--board", "9x6", "-o", "out.yaml"]
BUILD = ["build-model", "{KF}", "--camera", "{CAM}", "-o", "out.mirage"]
REPORT = ["report", "{TRUTH}", "--path", "{PATH}", "-o", "out.csv"]
SYNTH = ["synth", "synth_out"]

CASES = [
    # --- the program --------------------------------------------------------------------
    C("unknown-command", "frobnicate", contains="no such command"),
    C("unknown-option", "track", "--bogus", contains="--bogus"),
    C("missing-config", "--config", "nope.yaml", "synth", "x", contains="not found"),
    C("config-nan", "track", "{V}", "-o", "out.csv", needs=["config"], contains="--max-rmse"),
    # --- track: numeric options ------------------------------------------------------------
    C("track-max-rmse-nan", *TRACK, "--max-rmse", "nan", contains="--max-rmse"),
    C("track-max-rmse-inf", *TRACK, "--max-rmse", "inf", contains="finite"),
    C("track-max-rmse-neg", *TRACK, "--max-rmse", "-1", contains="--max-rmse"),
    C("track-max-rmse-zero", *TRACK, "--max-rmse", "0", contains="--max-rmse"),
    C("track-max-rmse-text", *TRACK, "--max-rmse", "abc", contains="--max-rmse"),
    C("track-start-infs", *TRACK, "--start", "infs", contains="--start"),
    C("track-start-nan", *TRACK, "--start", "nan", contains="--start"),
    C("track-start-nans", *TRACK, "--start", "nans", contains="--start"),
    C("track-start-neg", *TRACK, "--start", "-5", contains="--start"),
    C("track-start-neg-s", *TRACK, "--start", "-1s", contains="--start"),
    C("track-end-infs", *TRACK, "--end", "infs", contains="--end"),
    C("track-end-text", *TRACK, "--end", "soon", contains="--end"),
    C("track-end-before-start", *TRACK, "--start", "30", "--end", "10", contains="--end"),
    C("track-end-equals-start", *TRACK, "--start", "5", "--end", "5", contains="--end"),
    C("track-end-before-start-s", *TRACK, "--start", "2s", "--end", "1s", contains="--end"),
    C("track-start-past-end", *TRACK, "--start", "99999", contains="no frames"),
    C("track-every-zero", *TRACK, "--every", "0", contains="--every"),
    C("track-every-nan", *TRACK, "--every", "nan", contains="--every"),
    C("track-redetect-zero", *TRACK, "--redetect-every", "0", contains="--redetect-every"),
    C("track-min-inliers-3", *TRACK, "--min-inliers", "3", contains="--min-inliers"),
    C("track-min-inliers-frac", *TRACK, "--min-inliers", "4.5", contains="--min-inliers"),
    C("track-method", *TRACK, "--method", "bogus", contains="--method"),
    # --- track: files ---------------------------------------------------------------------
    C("track-out-is-video", "track", "{V}", "--model", "{M}", "-o", "{V}", contains="same file"),
    C("track-out-is-model", "track", "{V}", "--model", "{M}", "-o", "{M}", contains="same file"),
    C("track-overlay-is-video", *TRACK, "--overlay", "{V}", contains="same file"),
    C("track-tum-is-out", *TRACK, "--tum", "out.csv", contains="same file"),
    C("track-out-is-camera", *TRACK[:-1], "{CAM}", "--camera", "{CAM}", contains="same file"),
    C(
        "track-out-via-dotdot",
        *TRACK[:-1],
        "../{TMPNAME}/out.csv",
        "--tum",
        "out.csv",
        contains="same file",
    ),  # fmt: skip
    C("track-model-missing", "track", "{V}", "--model", "nope.mirage", contains="not found"),
    C("track-model-not-zip", "track", "{V}", "--model", "notzip.mirage", contains="model"),
    C("track-video-missing", "track", "nope.mp4", "--model", "{M}", contains="not found"),
    C("track-video-is-text", "track", "bad.yaml", "--model", "{M}", contains="bad.yaml"),
    C("track-out-missing-dir", *TRACK[:-1], "no/such/dir.csv", contains="does not exist"),
    C("track-out-is-dir", *TRACK[:-1], ".", contains="directory"),
    # --- calibrate ----------------------------------------------------------------------
    C("cal-square-nan", *CALIB, "--square", "nan", contains="--square"),
    C("cal-square-inf", *CALIB, "--square", "inf", contains="--square"),
    C("cal-square-neg", *CALIB, "--square", "-1", contains="--square"),
    C("cal-square-zero", *CALIB, "--square", "0", contains="--square"),
    C("cal-square-text", *CALIB, "--square", "big", contains="--square"),
    C("cal-marker-nan", *CALIB, "--square", "0.02", "--marker", "nan", contains="--marker"),
    C(
        "cal-min-motion-nan",
        *CALIB,
        "--square",
        "0.02",
        "--min-motion",
        "nan",
        contains="--min-motion",
    ),  # fmt: skip
    C(
        "cal-min-motion-neg",
        *CALIB,
        "--square",
        "0.02",
        "--min-motion",
        "-1",
        contains="--min-motion",
    ),  # fmt: skip
    C(
        "cal-max-view-inf",
        *CALIB,
        "--square",
        "0.02",
        "--max-view-error",
        "inf",
        contains="--max-view-error",
    ),  # fmt: skip
    C(
        "cal-reject-nan",
        *CALIB,
        "--square",
        "0.02",
        "--reject-factor",
        "nan",
        contains="--reject-factor",
    ),  # fmt: skip
    C("cal-every-zero", *CALIB, "--square", "0.02", "--every", "0", contains="--every"),
    C(
        "cal-board-one",
        "calibrate",
        "{CAL}",
        "--board",
        "9",
        "--square",
        "0.02",
        contains="--board",
    ),  # fmt: skip
    C(
        "cal-board-1x6",
        "calibrate",
        "{CAL}",
        "--board",
        "1x6",
        "--square",
        "0.02",
        contains="--board",
    ),  # fmt: skip
    C(
        "cal-board-nan",
        "calibrate",
        "{CAL}",
        "--board",
        "nanxnan",
        "--square",
        "0.02",
        contains="--board",
    ),  # fmt: skip
    C(
        "cal-subpix-zero",
        *CALIB,
        "--square",
        "0.02",
        "--subpix-window",
        "0",
        contains="--subpix-window",
    ),  # fmt: skip
    C("cal-workers-zero", *CALIB, "--square", "0.02", "--workers", "0", contains="--workers"),
    C("cal-pattern", *CALIB, "--square", "0.02", "--pattern", "dots", contains="--pattern"),
    C("cal-model-7", *CALIB, "--square", "0.02", "--model", "7", contains="--model"),
    C(
        "cal-out-is-image",
        "calibrate",
        "{CAL}/right01.jpg",
        "{CAL}/right02.jpg",
        "--board",
        "9x6",
        "--square",
        "0.02",
        "-o",
        "{CAL}/right01.jpg",
        contains="same file",
    ),  # fmt: skip
    C(
        "cal-report-is-out",
        *CALIB,
        "--square",
        "0.02",
        "--report",
        "out.yaml",
        contains="same file",
    ),  # fmt: skip
    C(
        "cal-input-missing",
        "calibrate",
        "nope/",
        "--board",
        "9x6",
        "--square",
        "0.02",
        "-o",
        "out.yaml",
        contains="not found",
    ),  # fmt: skip
    # --- build-model ----------------------------------------------------------------------
    C(
        "bm-spacing-nan",
        *BUILD,
        "--poses",
        "{KP}",
        "--spacing-deg",
        "nan",
        contains="--spacing-deg",
    ),  # fmt: skip
    C(
        "bm-spacing-low",
        *BUILD,
        "--poses",
        "{KP}",
        "--spacing-deg",
        "0.5",
        contains="--spacing-deg",
    ),  # fmt: skip
    C(
        "bm-spacing-high",
        *BUILD,
        "--poses",
        "{KP}",
        "--spacing-deg",
        "91",
        contains="--spacing-deg",
    ),  # fmt: skip
    C("bm-nfeatures", *BUILD, "--poses", "{KP}", "--nfeatures", "10", contains="--nfeatures"),
    C(
        "bm-reproj-nan",
        *BUILD,
        "--poses",
        "{KP}",
        "--max-reproj-px",
        "nan",
        contains="--max-reproj-px",
    ),  # fmt: skip
    C(
        "bm-angle-inf",
        *BUILD,
        "--poses",
        "{KP}",
        "--min-angle-deg",
        "inf",
        contains="--min-angle-deg",
    ),  # fmt: skip
    C(
        "bm-angle-neg",
        *BUILD,
        "--poses",
        "{KP}",
        "--min-angle-deg",
        "-1",
        contains="--min-angle-deg",
    ),  # fmt: skip
    C("bm-roi-nan", *BUILD, "--poses", "{KP}", "--roi", "1,nan,2", contains="--roi"),
    C("bm-roi-short", *BUILD, "--poses", "{KP}", "--roi", "1,2", contains="--roi"),
    C("bm-detector", *BUILD, "--poses", "{KP}", "--detector", "bogus", contains="--detector"),
    C(
        "bm-out-is-poses",
        "build-model",
        "{KF}",
        "--camera",
        "{CAM}",
        "--poses",
        "kp.csv",
        "-o",
        "kp.csv",
        needs=["kp_copy"],
        contains="same file",
    ),  # fmt: skip
    C(
        "bm-out-is-camera",
        "build-model",
        "{KF}",
        "--camera",
        "{CAM}",
        "--poses",
        "{KP}",
        "-o",
        "{CAM}",
        contains="same file",
    ),  # fmt: skip
    C("bm-poses-dup", *BUILD, "--poses", "dup.csv", contains="repeats the frame of row 3"),
    C("bm-poses-dup-float", *BUILD, "--poses", "dup_float.csv", contains="repeats"),
    C("bm-poses-inf", *BUILD, "--poses", "inf.csv", contains="column 'x_m' row 4"),
    C("bm-poses-ninf", *BUILD, "--poses", "ninf.csv", contains="column 'y_m' row 4"),
    C("bm-poses-tinf", *BUILD, "--poses", "tinf.csv", contains="column 'time_s' row 2"),
    C("bm-poses-nan", *BUILD, "--poses", "nan.csv", contains="column 'y_m' row 4"),
    C("bm-poses-q2", *BUILD, "--poses", "q2.csv", contains="unit quaternion"),
    C("bm-poses-q0", *BUILD, "--poses", "q0.csv", contains="zero quaternion"),
    C("bm-poses-qhalf", *BUILD, "--poses", "qhalf.csv", contains="norm 0.7071"),
    C("bm-poses-empty", *BUILD, "--poses", "empty.csv", contains="empty"),
    C("bm-poses-header", *BUILD, "--poses", "header.csv", contains="no rows"),
    C("bm-poses-nocol", *BUILD, "--poses", "nocol.csv", contains="qz"),
    C("bm-poses-binary", *BUILD, "--poses", "text.csv", contains="text.csv"),
    C(
        "bm-poses-and-board",
        *BUILD,
        "--poses",
        "{KP}",
        "--board",
        "bad.yaml",
        contains="exactly one",
    ),  # fmt: skip
    C("bm-no-poses", *BUILD, contains="exactly one"),
    C(
        "bm-camera-missing",
        "build-model",
        "{KF}",
        "--camera",
        "nope.yaml",
        "--poses",
        "{KP}",
        "-o",
        "out.mirage",
        contains="not found",
    ),  # fmt: skip
    # --- inspect -------------------------------------------------------------------------
    C("inspect-plot-is-model", "inspect", "{M}", "--plot", "{M}", contains="same file"),
    C("inspect-missing", "inspect", "nope.mirage", contains="not found"),
    C("inspect-not-zip", "inspect", "notzip.mirage", "--plot", "out.png", contains="model"),
    C("inspect-plot-dir", "inspect", "{M}", "--plot", "no/dir.png", contains="does not exist"),
    # --- report --------------------------------------------------------------------------
    C(
        "report-out-is-poses",
        "report",
        "{TRUTH}",
        "--path",
        "{PATH}",
        "-o",
        "{TRUTH}",
        contains="same file",
    ),  # fmt: skip
    C("report-summary-is-poses", *REPORT, "--summary", "{TRUTH}", contains="same file"),
    C("report-plot-is-path", *REPORT, "--plot", "{PATH}", contains="same file"),
    C("report-out-is-summary", *REPORT, "--summary", "out.csv", contains="same file"),
    # a hard link of an input is the same file under another name (same inode)
    C("report-out-is-hard-link", "report", "kp.csv", "--path", "{PATH}", "-o", "kp_link.csv",
      needs=["kp_copy", "hard_link"], contains="same file"),  # fmt: skip
    C("track-overlay-is-hard-link", *TRACK, "--overlay", "v_link.mp4", needs=["v_link"],
      contains="same file"),  # fmt: skip
    C(
        "report-poses-dup",
        "report",
        "dup.csv",
        "--path",
        "{PATH}",
        "-o",
        "out.csv",
        contains="repeats",
    ),  # fmt: skip
    C("report-truth-dup", *REPORT, "--truth", "dup.csv", contains="repeats"),
    C("report-truth-dup-float", *REPORT, "--truth", "dup_float.csv", contains="repeats"),
    C(
        "report-poses-inf",
        "report",
        "inf.csv",
        "--path",
        "{PATH}",
        "-o",
        "out.csv",
        contains="finite",
    ),  # fmt: skip
    C("report-truth-q2", *REPORT, "--truth", "q2.csv", contains="unit quaternion"),
    C("report-truth-tum-zero-q", *REPORT, "--truth", "zero_q.tum", contains="data row 2"),
    C("report-truth-tum-big-q", *REPORT, "--truth", "big_q.tum", contains="unit quaternion"),
    C("report-truth-tum-dup-time", *REPORT, "--truth", "dup_t.tum", contains="same timestamp"),
    C("report-truth-tum-nan", *REPORT, "--truth", "nan.tum", contains="finite"),
    C("report-truth-kitti-scaled", *REPORT, "--truth", "scaled_r.kitti", contains="rotation"),
    C("report-truth-kitti-mirror", *REPORT, "--truth", "mirror_r.kitti", contains="rotation"),
    C(
        "report-poses-empty",
        "report",
        "empty.csv",
        "--path",
        "{PATH}",
        "-o",
        "out.csv",
        contains="empty",
    ),  # fmt: skip
    C(
        "report-path-missing",
        "report",
        "{TRUTH}",
        "--path",
        "nope.yaml",
        "-o",
        "out.csv",
        contains="not found",
    ),  # fmt: skip
    C(
        "report-path-bad-yaml",
        "report",
        "{TRUTH}",
        "--path",
        "bad.yaml",
        "-o",
        "out.csv",
        contains="bad.yaml",
    ),  # fmt: skip
    # --- synth ---------------------------------------------------------------------------
    C("synth-noise-nan", *SYNTH, "--noise", "nan", contains="--noise"),
    C("synth-duration-inf", *SYNTH, "--duration", "inf", contains="--duration"),
    C("synth-fps-zero", *SYNTH, "--fps", "0", contains="--fps"),
    C("synth-fps-nan", *SYNTH, "--fps", "nan", contains="--fps"),
    C("synth-radius-nan", *SYNTH, "--radius", "nan", contains="--radius"),
    C("synth-step-nan", *SYNTH, "--keyframe-step", "nan", contains="--keyframe-step"),
    C("synth-heights-nan", *SYNTH, "--heights", "0.5,nan", contains="--heights"),
    C("synth-heights-inf", *SYNTH, "--heights", "inf", contains="--heights"),
    C("synth-heights-text", *SYNTH, "--heights", "low", contains="--heights"),
    C("synth-seed-neg", *SYNTH, "--seed", "-1", contains="--seed"),
    C("synth-seed-frac", *SYNTH, "--seed", "1.5", contains="--seed"),
    C("synth-width-small", *SYNTH, "--width", "8", contains="--width"),
    C("synth-quality", *SYNTH, "--jpeg-quality", "101", contains="--jpeg-quality"),
    C("synth-jobs-zero", *SYNTH, "--jobs", "0", contains="--jobs"),
    C("synth-square-inf", *SYNTH, "--square", "inf", contains="--square"),
    C("synth-views-zero", *SYNTH, "--calib-views", "0", contains="--calib-views"),
    C("synth-blur-zero", *SYNTH, "--motion-blur", "0", contains="--motion-blur"),
    C("synth-only-bogus", *SYNTH, "--only", "bogus", contains="bogus"),
    C(
        "synth-camera-is-output",
        "synth",
        "so",
        "--camera",
        "so/camera_truth.yaml",
        needs=["synth_cam"],
        contains="same file",
    ),  # fmt: skip
    # --- demo ----------------------------------------------------------------------------
    C("demo-out-is-sample", "demo", "--out", "{SAMPLE}", "--sample-data", "{SAMPLE}",
      contains="sample data"),  # fmt: skip
    C("demo-sample-missing", "demo", "--sample-data", "nope", contains="not found"),
]


# --- issue 30: outputs that hide inside inputs (folders, globs, other options, batch) -------
FR = ["track", "frames", "--model", "{M}"]
CAL_GLOB = ["calibrate", "frames/*.jpg", "--board", "9x6", "--square", "0.025"]
CASES += [
    C("track-out-is-image-in-folder", *FR, "-o", "frames/right02.jpg", needs=["frames"],
      contains="same file as VIDEO frames"),
    C("track-out-inside-image-folder", *FR, "-o", "frames/poses.csv", needs=["frames"],
      contains="inside VIDEO frames"),
    C("track-tum-inside-folder-via-dotdot", *FR, "--tum", "frames/../frames/p.tum",
      needs=["frames"], contains="inside VIDEO"),
    C("track-out-is-hard-link-to-image", *FR, "-o", "hard.jpg", needs=["frames", "hardlink"],
      contains="same file"),
    C("track-out-inside-bag", "track", "bag", "--model", "{M}", "-o", "bag/poses.csv",
      needs=["bag"], contains="inside VIDEO bag"),
    C("track-out-in-symlinked-folder", *FR, "-o", "frames_link/poses.csv",
      needs=["frames", "symlink"], contains="inside VIDEO frames"),
    C("cal-report-is-glob-member", *CAL_GLOB, "--report", "frames/right01.jpg",
      needs=["frames"], contains="same file"),
    C("cal-report-matches-glob", *CAL_GLOB, "--report", "frames/calib_000.jpg",
      needs=["frames"], contains="matches INPUT frames/*.jpg"),
    C("cal-out-inside-folder", "calibrate", "frames", "--board", "9x6", "--square", "0.025",
      "-o", "frames/camera.yaml", needs=["frames"], contains="inside INPUT frames"),
    C("bm-out-inside-keyframes", "build-model", "frames", "--camera", "{CAM}", "--poses",
      "{KP}", "-o", "frames/m.mirage", needs=["frames"], contains="inside INPUT frames"),
    C("report-out-is-transform-file", *REPORT[:-1], "tt.txt", "--truth", "{TRUTH}",
      "--truth-transform", "tt.txt", needs=["transform"], contains="--truth-transform"),
    C("report-summary-is-transform-file", *REPORT, "--truth", "{TRUTH}",
      "--truth-transform", "tt.txt", "--summary", "tt.txt", needs=["transform"],
      contains="same file"),
    C("report-out-is-config", "--config", "cfg.yaml", *REPORT[:-1], "cfg.yaml",
      needs=["cfg"], contains="--config"),
    C("synth-width-absurd", *SYNTH, "--width", "1000000000", contains="--width"),
    C("synth-height-makes-width-absurd", *SYNTH, "--height", "8000", contains="10667x8000"),
    C("demo-out-inside-sample", "demo", "--sample-data", "sample", "--out", "sample/d",
      needs=["sample_copy"], contains="inside --sample-data"),
    # --- issue 30: the last silent inputs, and messages that say what to fix -------------
    C("config-two-track-sections", *REPORT, needs=["cfg_dup"], contains="'track' appears twice"),
    C("report-path-unknown-key", *REPORT[:3], "look.yaml", "-o", "out.csv", needs=["paths"],
      contains="did you mean 'look_at_m'"),
    C("report-path-radius-1e308", *REPORT[:3], "huge.yaml", "-o", "out.csv", needs=["paths"],
      contains="radius_m 1e+308 is beyond"),
    C("report-poses-status-unknown", "report", "status.csv", "--path", "{PATH}", "-o",
      "out.csv", needs=["paths"], contains="'good'; expected one of ok, lost"),
    C("report-truth-transform-missing-file", *REPORT, "--truth", "{TRUTH}",
      "--truth-transform", "mocap/t_body_cam.txt", contains="file mocap/t_body_cam.txt not found"),
    C("synth-video-radius-nan", *SYNTH, "--video-radius", "nan", contains="--video-radius"),
    C("bm-nfeatures-huge", *BUILD, "--poses", "{KP}", "--nfeatures", "100000000000",
      contains="--nfeatures"),
    C("track-camera-width-zero", *TRACK, "--camera", "zero_w.yaml", needs=["paths"],
      contains="must be positive"),
    C("batch-empty-range-frames-and-seconds", "batch", "camp3.yaml", needs=["campaign"],
      contains="'end' 30 (frame 30) must come after 'start' 2s (frame 60)"),
    # --- issue 30: the small things -------------------------------------------------------
    C("track-global-option-after-command", *TRACK, "-q",
      contains="-q is a global option: it goes before the command, 'mirage -q track ...'"),
    C("cal-board-counts-squares", "calibrate", "frames", "--board", "10x7", "--square",
      "0.025", "-o", "out.yaml", needs=["frames"], contains="try --board 9x6"),
    C("track-plumb-bob-8-coefficients", *TRACK, "--camera", "plumb8.yaml", "--end", "0s",
      needs=["paths"], contains="--end"),
    C("track-min-inliers-absurd", *TRACK, "--min-inliers", "100000000000",
      contains="--min-inliers"),
    C("cal-subpix-window-absurd", *CALIB, "--square", "0.02", "--subpix-window",
      "100000000000", contains="--subpix-window"),
    C("synth-calib-views-absurd", *SYNTH, "--calib-views", "100000000",
      contains="--calib-views"),
    C("batch-out-is-flight-truth", "batch", "camp.yaml", needs=["campaign"],
      contains="is the same file as flight 'fl' truth"),
    C("batch-out-inside-flight-frames", "batch", "camp2.yaml", needs=["frames", "campaign"],
      contains="inside flight 'frames' video"),
]  # fmt: skip


def _setup(needs: list, world: dict) -> None:
    """The extra files some cases need, all in the case's own folder."""
    tmp = world["TMP"]
    if "frames" in needs:  # an image folder: a copy, never the repository's own files
        (tmp / "frames").mkdir()
        for f in sorted(CAL.glob("*.jpg"))[:3]:
            shutil.copyfile(f, tmp / "frames" / f.name)
    if "hardlink" in needs:
        os.link(tmp / "frames" / "right02.jpg", tmp / "hard.jpg")
    if "symlink" in needs:
        (tmp / "frames_link").symlink_to(tmp / "frames")
    if "bag" in needs:  # a ROS 2 bag is a folder holding metadata.yaml
        (tmp / "bag").mkdir()
        (tmp / "bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    if "sample_copy" in needs:  # the sample data's small files, in the case's folder
        (tmp / "sample" / "keyframes").mkdir(parents=True)
        for name in ("desired_path.yaml", "orbit_truth.csv", "camera_truth.yaml"):
            shutil.copyfile(SAMPLE / name, tmp / "sample" / name)
        shutil.copyfile(world["KP"], tmp / "sample" / "keyframes" / "poses.csv")
        (tmp / "sample" / "orbit.mp4").write_bytes(b"")
        (tmp / "sample" / "calibration").mkdir()
    if "cfg_dup" in needs:
        (tmp / "mirage.yaml").write_text(
            "track:\n  every: 2\nreport:\n  t-max-diff: 0.02\ntrack:\n  max-rmse: 2\n"
        )
    if "paths" in needs:
        (tmp / "look.yaml").write_text("type: circle\nradius_m: 1.5\nlook_at: [0, 0, 0.2]\n")
        (tmp / "huge.yaml").write_text("type: circle\nradius_m: 1e308\n")
        (tmp / "status.csv").write_text(GOOD.replace("frame,", "frame,status,", 1)
                                        .replace("\n0,", "\n0,ok,").replace("\n1,", "\n1,good,"))
        cam = world["CAM"].read_text()
        (tmp / "plumb8.yaml").write_text(  # the sample's lens, as 8 coefficients (3 zero)
            cam.replace("cols: 5", "cols: 8").replace("0. ]", "0., 0., 0., 0. ]")
            + 'distortion_model: "plumb_bob"\n'
        )
        (tmp / "zero_w.yaml").write_text(cam.replace("image_width: 640", "image_width: 0"))
    if "transform" in needs:
        (tmp / "tt.txt").write_text("0 0 0 1 0 0 0\n")
    if "cfg" in needs:
        (tmp / "cfg.yaml").write_text("report:\n  t-max-diff: 0.02\n")
    if "campaign" in needs:
        (tmp / "camp_out" / "fl").mkdir(parents=True)
        shutil.copyfile(world["TRUTH"], tmp / "camp_out" / "fl" / "poses.csv")
        (tmp / "camp.yaml").write_text(
            f"defaults: {{model: {world['M']}, path: {world['PATH']}, output: camp_out}}\n"
            f"flights:\n  - {{video: {world['V']}, name: fl, truth: camp_out/fl/poses.csv}}\n"
        )
        (tmp / "camp3.yaml").write_text(
            f"defaults: {{model: {world['M']}, path: {world['PATH']}, output: camp3_out}}\n"
            f"flights:\n  - {{video: {world['V']}, start: 2s, end: 30}}\n"
        )
        (tmp / "camp2.yaml").write_text(
            f"defaults: {{model: {world['M']}, path: {world['PATH']}, output: frames}}\n"
            "flights:\n  - {video: frames}\n"
        )


def _fill(args: list, p: dict) -> list[str]:
    return [str(a).format(**p) for a in args]


def _snapshot(paths) -> dict:
    out = {}
    for p in paths:
        p = Path(p)
        files = [f for f in p.rglob("*") if f.is_file()] if p.is_dir() else [p]
        for f in files:
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


def _hidden(folder: Path) -> list[str]:
    return sorted(str(f) for f in folder.rglob(".*"))


@pytest.fixture
def world(tmp_path, sample_model):
    for name, text in {**BAD_FILES, **PROTECTED}.items():
        (tmp_path / name).write_text(text)
    return {
        "V": SAMPLE / "orbit.mp4",
        "M": sample_model,
        "CAM": SAMPLE / "camera_truth.yaml",
        "KF": SAMPLE / "keyframes",
        "KP": SAMPLE / "keyframes" / "poses.csv",
        "PATH": SAMPLE / "desired_path.yaml",
        "TRUTH": SAMPLE / "orbit_truth.csv",
        "CAL": CAL,
        "SAMPLE": SAMPLE,
        "TMP": tmp_path,
        "TMPNAME": tmp_path.name,
    }


def run_in_process(argv: list[str], capsys) -> tuple[int, str, list]:
    capsys.readouterr()
    with (
        own_signal_handlers(),
        warnings.catch_warnings(record=True) as caught,
        pytest.raises(SystemExit) as e,
    ):
        warnings.simplefilter("always")
        cli.main(argv)
    _, err = capsys.readouterr()
    return e.value.code, err, [str(w.message) for w in caught]


def assert_contract(code, err, want_code, contains="", prefix="mirage: error: "):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == want_code, (code, err)
    assert len(lines) == 1 and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith(prefix), lines[0]
    if contains:
        assert contains.lower() in lines[0].lower(), lines[0]
    return lines[0]


INPUTS = ("V", "M", "CAM", "KF", "KP", "PATH", "TRUTH", "CAL", "SAMPLE")


def _copies(args: list, world: dict) -> dict:
    """`world` with each input the case names replaced by a copy in tmp_path/in: a case
    that passes an input as an output then risks a copy if the output guard is broken,
    never the checkout (or the session's model, which later tests use)."""
    out = dict(world)
    for key in INPUTS:
        if any(f"{{{key}}}" in str(a) for a in args):
            src = Path(world[key])
            dest = world["TMP"] / "in" / key / src.name
            dest.parent.mkdir(parents=True)
            (shutil.copytree if src.is_dir() else shutil.copyfile)(src, dest)
            out[key] = dest
    return out


@pytest.mark.parametrize("case", CASES)
def test_catalogue(case: Case, world, capsys, monkeypatch):
    tmp = world["TMP"]
    monkeypatch.chdir(tmp)
    originals = world
    world = _copies(case.args, world)
    if "kp_copy" in case.needs:
        shutil.copyfile(world["KP"], tmp / "kp.csv")
    if "hard_link" in case.needs:
        os.link(tmp / "kp.csv", tmp / "kp_link.csv")
    if "v_link" in case.needs:  # (the video is a copy: the case names it)
        os.link(world["V"], tmp / "v_link.mp4")
    if "synth_cam" in case.needs:
        (tmp / "so").mkdir()
        shutil.copyfile(world["CAM"], tmp / "so" / "camera_truth.yaml")
    _setup(case.needs, world)
    if "config" in case.needs:
        (tmp / "mirage.yaml").write_text(f"track:\n  model: {world['M']}\n  max-rmse: .nan\n")
    # the copies (inside tmp) and the originals they were made from
    watched = [tmp, originals["M"], originals["CAM"], originals["KP"], originals["TRUTH"]]
    watched += [originals["PATH"], originals["V"], CAL / "right01.jpg"]
    before = _snapshot(watched)
    code, err, warned = run_in_process(_fill(case.args, world), capsys)
    assert_contract(code, err, case.code, case.contains)
    assert not warned, warned
    assert _snapshot(watched) == before, "an existing file changed"
    assert not _hidden(tmp), _hidden(tmp)
    assert not (tmp / "synth_out").exists()  # nothing started before the check


def test_catalogue_size():
    assert len(CASES) >= 80


# --- a full disk ------------------------------------------------------------------------
@pytest.fixture
def full_disk(tmp_path):
    """A 256 KiB tmpfs filled to the last byte, holding good outputs from before."""
    with small_tmpfs(tmp_path / "full") as mnt:
        for name, text in PROTECTED.items():
            (mnt / name).write_text(text)
        with contextlib.suppress(OSError), open(mnt / "filler", "wb", buffering=0) as f:
            while True:
                f.write(b"\0" * 4096)
        with contextlib.suppress(OSError), open(mnt / "filler", "ab", buffering=0) as f:
            while True:  # the last partial block
                f.write(b"\0")
        yield mnt


FULL_DISK = [
    ("calibrate", [*CALIB[:-1], "{FULL}/out.yaml", "--square", "0.025"]),
    ("report", [*REPORT[:-1], "{FULL}/out.csv"]),
    ("report-summary", [*REPORT[:-1], "new.csv", "--summary", "{FULL}/out.yaml"]),
    ("track", [*TRACK[:-1], "{FULL}/out.csv", "--end", "2"]),
    ("track-tum", [*TRACK[:-1], "new.csv", "--end", "2", "--tum", "{FULL}/out.tum"]),
    ("inspect-plot", ["inspect", "{M}", "--plot", "{FULL}/out.png"]),
    ("track-overlay", [*TRACK[:-1], "new.csv", "--end", "2", "--overlay", "{FULL}/out.mp4"]),
    ("synth-camera", ["synth", "{FULL}/s", "--only", "calibration", "--calib-views", "1"]),
]


@pytest.mark.parametrize("args", [a for _, a in FULL_DISK], ids=[n for n, _ in FULL_DISK])
def test_full_disk(args, world, full_disk, capsys, monkeypatch):
    monkeypatch.chdir(world["TMP"])
    if args[0] == "calibrate":  # five views are enough to reach the write
        views = world["TMP"] / "views"
        views.mkdir()
        for f in sorted(CAL.glob("*.jpg"))[:5]:
            shutil.copyfile(f, views / f.name)
        args = ["calibrate", str(views), *args[2:]]
    before = _snapshot([full_disk, world["TMP"]])
    code, err, _ = run_in_process(_fill(args, {**world, "FULL": full_disk}), capsys)
    line = assert_contract(code, err, 1, "cannot write")
    assert str(full_disk) in line, line
    assert "no space left" in line.lower() or "disk full" in line, line
    after = _snapshot([full_disk, world["TMP"]])
    assert {k: v for k, v in after.items() if k in before} == before
    assert not _hidden(full_disk) and not _hidden(world["TMP"])


# --- real processes: stdout, signals ----------------------------------------------------
def _popen(args, cwd, **kw):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-m", "mirage_cli", *map(str, args)],
        cwd=cwd,
        env=env,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


@pytest.mark.parametrize("how", ["closed", "full"])
def test_stdout_failure_is_one_line(how, world):
    tmp = world["TMP"]
    args = _fill(REPORT, world)
    if how == "closed":  # `mirage ... >&-`
        p = _popen(args, tmp, stdout=subprocess.DEVNULL, preexec_fn=lambda: os.close(1))
    else:
        p = _popen(args, tmp, stdout=open("/dev/full", "w"))  # noqa: SIM115
    _, err = p.communicate(timeout=120)
    assert_contract(p.returncode, err, 1, "standard output")
    if how == "closed":  # refused before any work
        assert (tmp / "out.csv").read_text() == PROTECTED["out.csv"]
    assert not _hidden(tmp)


def _rows(path: Path) -> int:
    return len(path.read_text().splitlines()) - 1


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_mid_track_keeps_finished_frames(sig, code, world):
    tmp = world["TMP"]
    args = ["track", world["V"], "--model", world["M"], "-o", "poses.csv", "--tum", "p.tum"]
    p = _popen([*args, "--overlay", "ov.mp4"], tmp, stdout=subprocess.DEVNULL)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120:  # some rows in the hidden partial file
        parts = list(tmp.glob(".poses.csv.*.partial"))
        if parts and _rows(parts[0]) >= 3:
            break
        assert p.poll() is None, p.stderr.read()
        time.sleep(0.05)
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    name = signal.Signals(sig).name
    line = assert_contract(p.returncode, err, code, prefix=f"mirage: interrupted ({name}); ")
    kept = int(re.search(r"kept (\d+) frames in poses.csv", line).group(1))
    assert kept >= 3 and _rows(tmp / "poses.csv") == kept
    assert (tmp / "p.tum").exists() and (tmp / "ov.mp4").stat().st_size > 0
    from mirage_cli.fileio import video_frames_written  # a frame each row, none fewer

    assert video_frames_written(tmp / "ov.mp4") == kept
    assert not _hidden(tmp), _hidden(tmp)


def _loaded(pid: int, lib: str) -> bool:
    with contextlib.suppress(OSError):
        return lib in Path(f"/proc/{pid}/maps").read_text()
    return False


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_during_start_up(sig, code, world):
    """While OpenCV and numba load: one line, the signal's exit code, no traceback."""
    tmp = world["TMP"]
    p = _popen([*_fill(TRACK, world)], tmp, stdout=subprocess.DEVNULL)
    t0 = time.monotonic()
    while not _loaded(p.pid, "cv2") and time.monotonic() - t0 < 60 and p.poll() is None:
        time.sleep(0.005)
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    name = signal.Signals(sig).name
    assert_contract(p.returncode, err, code, prefix=f"mirage: interrupted ({name})")
    assert (tmp / "out.csv").read_text() == PROTECTED["out.csv"]
    assert not _hidden(tmp)


# `python -m mirage_cli` whose model entries each take 0.2 s more to write, so that a signal
# sent once the model's temporary file exists surely lands while the model is written
WRITE_SLOWLY = """
import sys, time, zipfile
from mirage_cli import signals
signals.install()
_writestr = zipfile.ZipFile.writestr
def writestr(self, *a, **k):
    _writestr(self, *a, **k)
    time.sleep(0.2)
zipfile.ZipFile.writestr = writestr
from mirage_cli.cli import main
main(sys.argv[1:])
"""


def test_sigterm_while_writing_the_model_leaves_no_temp_file(world):
    """SIGTERM while build-model writes its (multi-MB) model: the temporary file goes, the
    previous model stays as it was, exit 143. The model's entries are written slowly (0.2 s
    each), so the signal always lands mid-write."""
    tmp = world["TMP"]
    args = [*_fill(BUILD, world), "--poses", world["KP"], "--spacing-deg", "40"]
    p = subprocess.Popen(
        [sys.executable, "-c", WRITE_SLOWLY, *map(str, args)], cwd=tmp,
        env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    t0, seen = time.monotonic(), False
    while p.poll() is None and time.monotonic() - t0 < 300:
        if list(tmp.glob(".out.mirage.*")):  # the model is being written
            seen = True
            p.send_signal(signal.SIGTERM)
            break
        time.sleep(0.002)
    _, err = p.communicate(timeout=120)
    assert seen, (p.returncode, err)
    assert_contract(p.returncode, err, 143, prefix="mirage: interrupted (SIGTERM)")
    assert (tmp / "out.mirage").read_text() == PROTECTED["out.mirage"]
    assert not _hidden(tmp), _hidden(tmp)


def test_interrupt_inside_compiled_code_is_the_interrupt():
    """numba reports a signal that lands in compiled code as SystemError with the
    KeyboardInterrupt as its context; the tracking loop must see the interrupt itself."""
    from mirage_cli.signals import Terminated, through_compiled_code

    def compiled_call_interrupted():
        try:
            raise Terminated()
        except Terminated:
            raise SystemError("returned a result with an exception set")  # noqa: B904

    with pytest.raises(Terminated):
        with through_compiled_code():
            compiled_call_interrupted()

    def chained(depth):  # the signal inside numba's unpickling: SystemErrors chained (4 seen)
        if depth == 0:
            compiled_call_interrupted()
        try:
            chained(depth - 1)
        except SystemError:
            raise SystemError("returned a result with an exception set")  # noqa: B904

    with pytest.raises(Terminated):
        with through_compiled_code():
            chained(4)
    with pytest.raises(SystemError):  # any other SystemError is left alone
        with through_compiled_code():
            raise SystemError("a real one")


def test_sigterm_as_a_zip_entry_opens_is_the_interrupt_not_a_zip_error(world, monkeypatch):
    """The race the SIGTERM test above catches only sometimes, made certain: the signal lands
    just after zipfile opened an entry's write handle. The save must end as the interrupt
    (not ZipFile's "open writing handle" ValueError), the old model untouched, no temp file."""
    import zipfile

    from mirage_cli import signals
    from mirage_cli.model import LandmarkModel

    model = LandmarkModel.load(world["M"])
    real_open, calls = zipfile.ZipFile.open, []

    def open_then_signal(self, *a, **k):
        handle = real_open(self, *a, **k)
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return handle

    monkeypatch.setattr(zipfile.ZipFile, "open", open_then_signal)
    out = world["TMP"] / "out.mirage"
    with own_signal_handlers():
        signals.install()
        with pytest.raises(signals.Terminated):
            model.save(out)
    assert len(calls) == 3
    assert out.read_text() == PROTECTED["out.mirage"]
    assert not _hidden(world["TMP"]), _hidden(world["TMP"])


# --- issue 30: outputs that are not regular files are written through, never replaced -----
def _null_node(path: Path) -> Path:
    """A private character device like /dev/null (major 1, minor 3) in the test's folder: a
    regression replaces this node, never the machine's /dev/null."""
    import stat

    try:
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except OSError as e:
        pytest.skip(f"creating a device node needs root (CAP_MKNOD): {e.strerror}")
    return path


def _is_null_device(path: Path) -> bool:
    import stat

    st = os.lstat(path)
    return stat.S_ISCHR(st.st_mode) and st.st_rdev == os.makedev(1, 3)


def _fifo_reader(path: Path):
    """Open a FIFO for reading in a thread (a writer's open blocks until then); returns a
    function giving everything read."""
    import threading

    os.mkfifo(path)
    got: list[bytes] = []

    def read():
        with open(path, "rb") as f:
            got.append(f.read())

    t = threading.Thread(target=read, daemon=True)
    t.start()

    def result() -> bytes:
        t.join(60)
        return b"".join(got)

    return result


def test_report_writes_through_a_device_and_a_fifo(world, capsys, monkeypatch):
    tmp = world["TMP"]
    monkeypatch.chdir(tmp)
    nul = _null_node(tmp / "nul")
    fifo = _fifo_reader(tmp / "report.fifo")
    args = _fill(REPORT[:-1], world) + ["report.fifo", "--summary", "nul", "--plot", "nul"]
    code, err, warned = run_in_process(args, capsys)
    assert code == 0, err
    assert fifo().startswith(b"frame,"), "the FIFO's reader got the report"
    assert _is_null_device(nul), "the device node was replaced"
    assert Path(tmp / "report.fifo").is_fifo()
    assert not _hidden(tmp) and not warned, warned


def test_track_writes_through_a_device_and_a_fifo(world, capsys, monkeypatch):
    """The row-by-row pose writer and the overlay video (no suffix: an .mp4 is made and
    copied through) write into the special files; nothing replaces them."""
    tmp = world["TMP"]
    monkeypatch.chdir(tmp)
    nul = _null_node(tmp / "nul")
    fifo = _fifo_reader(tmp / "poses.fifo")
    args = [*_fill(TRACK[:-1], world), "nul", "--end", "3", "--tum", "poses.fifo"]
    code, err, _ = run_in_process([*args, "--overlay", "nul"], capsys)
    assert code == 0, err
    rows = [ln for ln in fifo().decode().splitlines() if not ln.startswith("#")]
    assert len(rows) == 3, "three TUM rows through the FIFO"
    assert _is_null_device(nul) and Path(tmp / "poses.fifo").is_fifo()
    assert not _hidden(tmp)


def test_stdout_link_output_writes_standard_output(world):
    """`-o /dev/stdout` (here a private link to /proc/self/fd/1, the same thing): the CSV
    goes to standard output and the link stays a link."""
    tmp = world["TMP"]
    (tmp / "stdout").symlink_to("/proc/self/fd/1")
    p = _popen(["-q", *_fill(REPORT[:-1], world), "stdout"], tmp, stdout=subprocess.PIPE)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    assert out.startswith("frame,") and len(out.splitlines()) > 100
    assert (tmp / "stdout").is_symlink()
    assert not _hidden(tmp)


def test_symlink_output_writes_its_target(world, capsys, monkeypatch):
    """A symlinked output replaces the file it points to (atomically, in the target's
    folder); the link stays a link."""
    tmp = world["TMP"]
    monkeypatch.chdir(tmp)
    (tmp / "elsewhere").mkdir()
    (tmp / "elsewhere" / "r.csv").write_text("old\n")
    (tmp / "link.csv").symlink_to(tmp / "elsewhere" / "r.csv")
    code, err, _ = run_in_process([*_fill(REPORT[:-1], world), "link.csv"], capsys)
    assert code == 0, err
    assert (tmp / "link.csv").is_symlink()
    assert (tmp / "elsewhere" / "r.csv").read_text().startswith("frame,")
    assert not _hidden(tmp) and not _hidden(tmp / "elsewhere")


# --- issue 30: signals from the first instruction, never swallowed ------------------------
def _catches_sigterm(pid: int) -> bool:
    """Whether the process has its own SIGTERM handler yet (/proc's caught-signal mask)."""
    with contextlib.suppress(OSError, StopIteration, ValueError):
        status = Path(f"/proc/{pid}/status").read_text().splitlines()
        mask = int(next(ln for ln in status if ln.startswith("SigCgt:")).split()[1], 16)
        return bool(mask & (1 << (signal.SIGTERM - 1)))
    return False


def test_start_up_signals_are_never_swallowed(world):
    """50 runs of the console script's entry point, each sent SIGINT or SIGTERM at a random
    moment from the handlers' installation (before click, OpenCV and numba load) through
    the compiled solver's cache load and the first frames: every one ends with its
    signal's exit code and one line, and the previous output stays. The run is 300 frames
    so that it is still tracking 1.2 s after start-up (since the model file holds its
    tables, 30 frames could end first, and a signal during the interpreter's shutdown
    meets the default handlers: 2 runs of 50 ended -15 / -2 without a word; on a quiet
    host 150 frames ended first once in 50)."""
    import random

    tmp = world["TMP"]
    rng = random.Random(30)
    entry = "from mirage_cli.__main__ import run; run()"  # what the `mirage` script runs
    outcomes = []
    for i in range(50):
        sig = (signal.SIGINT, signal.SIGTERM)[i % 2]
        p = subprocess.Popen(
            [sys.executable, "-c", entry, *_fill(TRACK, world), "--end", "300"],
            cwd=tmp,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        t0 = time.monotonic()
        while not _catches_sigterm(p.pid) and time.monotonic() - t0 < 30 and p.poll() is None:
            time.sleep(0.001)
        time.sleep(rng.uniform(0, 1.2))
        assert p.poll() is None, "the run ended before its signal"
        p.send_signal(sig)
        _, err = p.communicate(timeout=120)
        outcomes.append((sig, p.returncode, err))
    swallowed = [(s, c, e) for s, c, e in outcomes if c != signals_code(s)]
    assert not swallowed, swallowed[:3]
    for sig, code, err in outcomes:
        name = signal.Signals(sig).name
        assert_contract(code, err, signals_code(sig), prefix=f"mirage: interrupted ({name})")
    # the previous output stays, unless a run was already tracking when its signal came:
    # then it holds the finished frames, whole rows under the pose header (the brief: an
    # interrupted track keeps every frame done so far); seen on a loaded machine
    out = (tmp / "out.csv").read_text()
    if out != PROTECTED["out.csv"]:
        rows = out.splitlines()
        assert rows[0].startswith("frame,time_s,status") and out.endswith("\n"), out[:200]
        assert all(r.count(",") == rows[0].count(",") for r in rows), out[:200]
    assert not _hidden(tmp), _hidden(tmp)


def signals_code(sig) -> int:
    return {signal.SIGINT: 130, signal.SIGTERM: 143}[sig]


def test_an_interrupted_run_ends_though_a_thread_never_does():
    """After its interrupt line, a run whose exit would wait on a thread that never ends
    (a library's worker stuck in a job) still ends, with the signal's code, once the
    grace period is over; without the grace it hangs until the test kills it. Only the
    process's own entry point does this: `main` called in-process (tests, scripts) never
    ends its caller's process."""
    code = (
        "import threading, sys; from mirage_cli import cli\n"
        "threading.Thread(target=threading.Event().wait).start()\n"
        "cli.EXIT_GRACE_S = {grace}\n"
        "def stop(argv): raise KeyboardInterrupt\n"
        "cli._invoke = stop\n"
        "sys.argv = ['mirage', 'track']\n"
        "from mirage_cli.__main__ import run; run()\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", code.format(grace=0.5)], env=env,
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert (p.returncode, p.stderr.strip()) == (130, "mirage: interrupted (SIGINT)")
    assert time.monotonic() - t0 < 30
    with pytest.raises(subprocess.TimeoutExpired):  # the grace is what ends it
        subprocess.run([sys.executable, "-c", code.format(grace=1e6)], env=env,
                       capture_output=True, timeout=8)  # fmt: skip


def test_the_process_exit_skips_only_the_teardown(tmp_path):
    """`mirage` ends without freeing every module's objects (0.3 s after a track), but as
    Python's exit otherwise would: its threads finish, atexit callbacks run, what it
    printed is flushed, and its code is kept. A module object's destructor is what is
    skipped (run by a plain `sys.exit`, the control)."""
    code = (
        "import atexit, sys, threading, time\n"
        "out = sys.argv.pop(1)\n"
        "def late():\n"
        "    time.sleep(0.3); open(out + '.thread', 'w').write('done')\n"
        "threading.Thread(target=late).start()\n"
        "atexit.register(lambda: open(out + '.atexit', 'w').write('done'))\n"
        "class Teardown:\n"
        "    def __del__(self, open=open, out=out): open(out + '.teardown', 'w').write('ran')\n"
        "keep = Teardown()\n"
        "if sys.argv[1] == 'plain': sys.exit(3)\n"
        "from mirage_cli.__main__ import run; run()\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def mirage(name: str, *argv: str) -> tuple[subprocess.CompletedProcess, set[str]]:
        out = tmp_path / name
        p = subprocess.run([sys.executable, "-c", code, str(out), *argv], env=env,
                           capture_output=True, text=True, timeout=120)  # fmt: skip
        return p, {f.suffix for f in tmp_path.glob(f"{name}.*")}

    p, ran = mirage("version", "--version")
    assert (p.returncode, p.stdout.strip()) == (0, f"mirage, version {__version__}")
    assert ran == {".thread", ".atexit"}
    p, ran = mirage("error", "track", str(tmp_path / "missing.mp4"), "--model", "m.mirage")
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "not found" in p.stderr
    assert ran == {".thread", ".atexit"}
    p, ran = mirage("plain", "plain")
    assert p.returncode == 3 and ran == {".thread", ".atexit", ".teardown"}


def test_a_profiled_run_still_writes_its_profile(tmp_path):
    """Under a profiler the exit is Python's own: cProfile writes its results after the
    program returns, which the exit without teardown would skip."""
    out = tmp_path / "mirage.prof"
    p = subprocess.run(
        [sys.executable, "-m", "cProfile", "-o", str(out), "-m", "mirage_cli", "--version"],
        env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert p.returncode == 0 and __version__ in p.stdout
    assert out.stat().st_size > 0


def test_an_interrupt_in_process_leaves_the_callers_process_alone(monkeypatch):
    """`main` called in-process (a test, a script) and interrupted exits 130 to its caller
    and starts nothing that would end the caller's process later (a 20 s timer that
    did so killed the test suite mid-run)."""

    def stop(argv):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_invoke", stop)
    before = set(threading.enumerate())
    with own_signal_handlers(), pytest.raises(SystemExit) as e:
        cli.main(["track"])
    assert e.value.code == 130
    assert set(threading.enumerate()) <= before


def test_a_swallowed_signal_still_interrupts(monkeypatch):
    """A signal whose exception a compiled-code callback dropped is raised at the next
    check (before the next frame, after the kernels load, before `main` says 0)."""
    from mirage_cli import signals

    with own_signal_handlers():
        signals.install()
        try:
            os.kill(os.getpid(), signal.SIGTERM)
        except signals.Terminated:
            pass  # what the callback does: print it, drop it
        with pytest.raises(signals.Terminated):
            signals.check()
        signals.check()  # raised once only


def test_a_signal_during_an_import_is_raised_once_the_import_is_over(tmp_path, monkeypatch):
    """A signal that lands inside an import is held (C code that started the import could
    print the exception and drop it: one interrupted start-up in 50 printed a traceback)
    and raised by the same signal sent again 20 ms later, once the import is over: the
    module is whole, the interrupt still comes, once."""
    from mirage_cli import signals

    (tmp_path / "slow_mod_under_signal.py").write_text(
        "import os, signal, time\n"
        "os.kill(os.getpid(), signal.SIGTERM)\n"
        "time.sleep(0.2)\n"
        "WHOLE = True\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    with own_signal_handlers():
        signals.install()
        with pytest.raises(signals.Terminated):
            import slow_mod_under_signal  # noqa: F401

            time.sleep(2.0)  # the signal again, outside the import
        assert sys.modules["slow_mod_under_signal"].WHOLE
        signals.seen()  # as the CLI's top level, having reported it
        time.sleep(0.1)
        signals.check()  # raised once only: no third signal came


def test_console_script_installs_the_handlers_before_importing_the_program():
    """The `mirage` script's entry point is the light __main__.run (signals first), not
    cli.main (whose module imports click and the config reader before any handler)."""
    text = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^mirage = "mirage_cli\.__main__:run"$', text, re.M), "entry point"
    code = "import sys, mirage_cli.__main__; print(sorted(m for m in sys.modules if m.startswith(('click', 'cv2', 'numba', 'numpy'))))"  # noqa: E501
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.stdout.strip() == "[]", out.stdout


def test_bad_mplbackend_is_a_warning_not_an_unexpected_error(world):
    """matplotlib refuses an unknown $MPLBACKEND on import; mirage draws with Agg and
    never uses a backend: one warning, the plot written, exit 0."""
    tmp = world["TMP"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "bogus"}
    args = [*_fill(REPORT[:-1], world), "new.csv", "--plot", "new.png"]
    p = subprocess.run([sys.executable, "-m", "mirage_cli", *args], cwd=tmp, env=env,
                       capture_output=True, text=True, timeout=300)  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert p.stderr.strip().startswith("mirage: warning: MPLBACKEND='bogus'"), p.stderr
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert (tmp / "new.png").stat().st_size > 0


def test_out_of_memory_is_one_line_exit_1(capsys, monkeypatch):
    from mirage_cli.cli import synth as synth_cli

    def no_memory(*a, **k):
        raise MemoryError()

    monkeypatch.setattr(synth_cli.synth, "default_camera", no_memory)
    code, err, _ = run_in_process(["synth", "x"], capsys)
    assert_contract(code, err, 1, "out of memory")


def test_image_names_giving_one_time_warn(tmp_path, caplog):
    """100.5.png and 100.50.png are one time: a warning naming both (time_s stays empty)."""
    from mirage_cli.frames import FrameSource

    for name in ("100.5.png", "100.50.png", "100.6.png"):
        shutil.copyfile(CAL / "right01.jpg", tmp_path / name)
    with caplog.at_level("WARNING", logger="mirage"):
        src = FrameSource([tmp_path])
    assert src.times is None
    assert "100.5.png and 100.50.png have names giving the same time (100.5 s)" in caplog.text


def test_camera_info_with_a_nan_focal_length_is_refused():
    """A NaN in a bag's camera_info K was read as 'uncalibrated' (None) without a word."""
    from types import SimpleNamespace

    from mirage_cli.bags import camera_from_info
    from mirage_cli.errors import InputError

    k = [float("nan"), 0, 320, 0, 500, 240, 0, 0, 1]
    msg = SimpleNamespace(k=k, d=[0.0] * 5, distortion_model="plumb_bob", width=640, height=480)
    with pytest.raises(InputError, match="NaN"):
        camera_from_info(msg, "/cam/camera_info in x.bag")
    msg.k = [0.0] * 9  # all zero: uncalibrated, as before
    assert camera_from_info(msg, "x") is None


def test_model_box_with_nan_projections_is_the_whole_frame_without_a_warning(sample_model):
    """A projection the lens model cannot place (NaN) made numpy warn 'invalid value
    encountered in cast' and the box came out empty, i.e. the whole frame: the same result
    now, said without the warning."""
    import numpy as np

    from mirage_cli.model import LandmarkModel
    from mirage_cli.pose import Pose
    from mirage_cli.tracking import Tracker, TrackSettings

    model = LandmarkModel.load(sample_model)
    tracker = Tracker(model, model.camera, TrackSettings())
    pose = model.keyframes[0].pose
    real = tracker.camera.project

    def with_nan(X, p):
        uv = real(X, p)
        uv[0] = np.nan
        return uv

    tracker.camera.project = with_nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert tracker._model_box(pose, (480, 640)) is None
    tracker.camera.project = real
    assert isinstance(pose, Pose)


@pytest.mark.parametrize("command", sorted(cli.COMMANDS))
def test_help_shows_no_none_bound_and_no_doubled_percent(command, capsys):
    with own_signal_handlers(), pytest.raises(SystemExit) as e:
        cli.main([command, "--help"])
    out = capsys.readouterr().out
    assert e.value.code == 0
    assert "None]" not in out and "None;" not in out and "%%" not in out, out


def test_square_in_millimetres_warns(world, capsys, monkeypatch):
    """--square 25 is a 25 m square: calibrated (the data are usable), with a warning."""
    tmp = world["TMP"]
    monkeypatch.chdir(tmp)
    _setup(["frames"], world)
    args = ["calibrate", "frames", "--board", "9x6", "--square", "25", "-o", "cam.yaml"]
    code, err, _ = run_in_process(args, capsys)
    assert code == 0, err
    assert "mirage: warning: --square 25 is in metres" in err and "--square 0.025" in err


def test_verbose_prints_stages_frames_and_refusals(world, capsys, monkeypatch):
    """-v: each stage's time and, after tracking, the refused frames by reason and the
    keyframes used; -vv: a line per frame. Without -v none of it."""
    monkeypatch.chdir(world["TMP"])
    code, err, _ = run_in_process(["-v", *_fill(REPORT, world)], capsys)
    assert code == 0 and "stage compute the errors:" in err and "poses: 540 frames" in err
    code, err, _ = run_in_process(_fill(REPORT, world), capsys)
    assert code == 0 and "stage" not in err
    track = [*_fill(TRACK[:-1], world), "new.csv", "--start", "425", "--end", "432"]
    code, err, warned = run_in_process(["-vv", *track], capsys)
    assert code == 0, err
    assert not warned, warned  # no Python warning (numpy's cast warning of _model_box)
    assert "stage load the compiled solver:" in err and "stage tracking:" in err
    assert re.search(r"^frame 425: \w+", err, re.M), err
    assert re.search(r"^refused \d+ frame\(s\) as lost", err, re.M), err
    # why frames were detected rather than flowed: per frame (-vv), and counted (-v)
    detected = re.findall(r"^frame \d+: \w+ \((?:detect|relocalise): (\w+)\)", err, re.M)
    why = re.search(r"^detected rather than flowed, why: (.+)$", err, re.M)
    assert detected and why, err
    counted = dict((c, int(n)) for c, n in (part.split() for part in why[1].split(", ")))
    assert counted == {c: detected.count(c) for c in set(detected)}


def test_an_interrupt_in_a_callback_is_not_printed_but_raised_later(capsys):
    """A signal landing in a callback Python cannot propagate from (ctypes, a finaliser)
    went to 'Exception ignored in ...' on stderr (a traceback beside the one line):
    it is silent there and `check` raises it."""
    import ctypes

    from mirage_cli import signals

    saved = sys.unraisablehook
    try:
        sys.unraisablehook = sys.__unraisablehook__
        with own_signal_handlers():
            signals.install()

            @ctypes.CFUNCTYPE(None)
            def callback():
                os.kill(os.getpid(), signal.SIGTERM)  # the handler raises in here

            callback()
            assert "Exception ignored" not in capsys.readouterr().err
            with pytest.raises(signals.Terminated):
                signals.check()
    finally:
        sys.unraisablehook = saved


def test_an_interrupt_a_library_turned_into_its_own_error_is_still_the_interrupt():
    """A SIGINT inside numba's import surfaced as ImportError('numba._devicearray failed to
    import') with the interrupt as its context: exit 130, not 'unexpected ImportError' 1
    (1 of 50 start-up signals under load)."""
    try:
        try:
            raise KeyboardInterrupt()
        except BaseException:
            raise ImportError("numba._devicearray failed to import") from None  # noqa: B904
    except ImportError as e:
        e.__context__ = KeyboardInterrupt()  # `from None` hides it from display only
        assert cli._report(e) == 130
    assert cli._report(ImportError("no module")) == 1
