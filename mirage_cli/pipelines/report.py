"""`mirage report`'s pipeline: a pose CSV against the desired path (and the truth) ->
the per-frame error table, the summary and the plot."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import yaml

from ..fileio import atomic_write
from ..path import load_path
from ..plotting import REPORT_DPI, report_figure, save_png
from ..report import Report, make_report
from ..trajectory import read_pose_csv
from ..truth import TruthSettings, load_truth
from .reporting import SILENT, Reporter


@dataclass
class ReportResult:
    report: Report  # .table (per frame) and .summary (the summary YAML's dict)
    desired: object  # the desired path (path.py), for the plot


def report(
    poses,
    path,
    truth=None,
    truth_settings: TruthSettings | None = None,
    reporter: Reporter = SILENT,
) -> ReportResult:
    """Read the desired path, the poses and (optionally) the truth; compute the errors."""
    with reporter.stage("read the path and the poses"):
        desired = load_path(path)
        table = read_pose_csv(poses)
    reporter.detail(f"path: {type(desired).__name__}, {desired.length_m:.3f} m long")
    reporter.detail(f"poses: {len(table)} frames, {(table['status'] == 'ok').sum()} ok")
    with reporter.stage("read the truth"):
        truth_df = load_truth(truth, table, truth_settings or TruthSettings()) if truth else None
    with reporter.stage("compute the errors"):
        rep = make_report(table, desired, truth_df)
    return ReportResult(rep, desired)


def write_report(rep: Report, output, summary_path=None, plot_path=None, path=None) -> None:
    """Write report.csv (+ summary YAML, + plot), each atomically."""
    table = rep.table.copy()
    t = table["time_s"].to_numpy(float)  # epoch stamps (bags) need their microseconds
    table["time_s"] = np.where(np.isfinite(t), np.char.mod("%.6f", np.nan_to_num(t)), "")
    with atomic_write(output, newline="") as f:
        table.to_csv(f, index=False, float_format="%.8g", lineterminator="\n")
    if summary_path:
        with atomic_write(summary_path) as f:
            yaml.safe_dump(rep.summary, f, sort_keys=False)
    if plot_path:
        save_png(report_figure(rep, path), plot_path, REPORT_DPI)


def nothing_tracked(rep: Report) -> bool:
    """No frame had a pose: every error is empty."""
    return not np.isfinite(rep.table["cross_track_m"].to_numpy(float)).any()
