"""plotting.py: each figure is a PNG of the expected size, the overlay draws what it says,
report.py stays pure (no plotting, no files) and start-up does not load matplotlib."""

from __future__ import annotations

import ast
import builtins
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from conftest import SAMPLE

from mirage_cli import report as report_module
from mirage_cli.boards import Board
from mirage_cli.calibrate import Detections, View, calibrate
from mirage_cli.model import LandmarkModel
from mirage_cli.path import load_path
from mirage_cli.plotting import (
    CALIBRATION_DPI,
    REPORT_DPI,
    TOP_VIEW_DPI,
    calibration_figure,
    draw_overlay,
    report_figure,
    save_png,
    top_view_figure,
)
from mirage_cli.pose import look_at
from mirage_cli.report import make_report
from mirage_cli.synth import default_camera
from mirage_cli.trajectory import read_pose_csv


def _png_size(path: Path) -> tuple[int, int]:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None and path.stat().st_size > 10_000
    return img.shape[1], img.shape[0]


@pytest.fixture(scope="module")
def sample_report():
    """The true orbit as the estimate, with a stretch of lost frames."""
    poses = read_pose_csv(SAMPLE / "orbit_truth.csv")
    lost = poses.index[100:130]
    poses.loc[lost, "status"] = "lost"
    poses.loc[lost, ["x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"]] = np.nan
    path = load_path(SAMPLE / "desired_path.yaml")
    return make_report(poses, path, read_pose_csv(SAMPLE / "orbit_truth.csv")), path


def test_report_figure_png(sample_report, tmp_path):
    rep, path = sample_report
    fig = report_figure(rep, path)
    n_err = len(fig.axes) - 1  # the top view plus one axis per error column
    assert n_err == 5  # cross-track, height, heading (an untimed path), position, rotation
    save_png(fig, tmp_path / "r.png", REPORT_DPI)
    assert _png_size(tmp_path / "r.png") == (1300, round(max(6.0, 1.9 * n_err) * REPORT_DPI))
    assert list(tmp_path.iterdir()) == [tmp_path / "r.png"]  # no temporary left behind


def test_calibration_figure_png(tmp_path):
    board = Board(9, 6, 0.025)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    rng = np.random.default_rng(1)
    views = []
    for i in range(8):
        rvec = np.r_[rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.3, 0.3)]
        R, _ = cv2.Rodrigues(rvec)
        t = np.r_[rng.uniform(-0.05, 0.05, 2), 0.35] - R @ np.array([0.1, 0.0625, 0])
        uv, _ = cv2.projectPoints(board.object_points, rvec, t, K, None)
        uv = uv.reshape(-1, 2) + rng.normal(0, 0.05 if i else 3.0, (54, 2))  # view 0: outlier
        views.append(View(f"v{i}", uv.astype(np.float32), np.arange(54), "sb"))
    calib = calibrate(Detections(views, (640, 480), 8), board)
    assert [v.name for v, _ in calib.rejected] == ["v0"]  # the plot shows a rejected view
    save_png(calibration_figure(calib), tmp_path / "c.png", CALIBRATION_DPI)
    assert _png_size(tmp_path / "c.png") == (12 * CALIBRATION_DPI, round(4.5 * CALIBRATION_DPI))


def test_top_view_figure_png(sample_model, tmp_path):
    model = LandmarkModel.load(sample_model)
    save_png(top_view_figure(model), tmp_path / "t.png", TOP_VIEW_DPI, bbox_inches="tight")
    w, h = _png_size(tmp_path / "t.png")  # a 7 x 7 in figure, cropped to what is drawn
    assert 0.6 * 7 * TOP_VIEW_DPI < w <= 7 * TOP_VIEW_DPI + 40
    assert 0.6 * 7 * TOP_VIEW_DPI < h <= 7 * TOP_VIEW_DPI + 40


def test_draw_overlay():
    cam = default_camera()
    pose = look_at([1.5, 0.3, 0.6], [0.0, 0.0, 0.28])
    img = np.full((cam.height, cam.width, 3), 128, np.uint8)
    px = np.array([[100.2, 200.7], [400.0, 300.0], [639.4, 479.2]])  # the last at the corner
    res = SimpleNamespace(
        status="ok", pose=pose, inlier_px=px, inliers=3, rmse_px=0.42, keyframe="kf_007"
    )
    out = draw_overlay(img, res, cam, axis_m=0.2)
    assert out.shape == img.shape and (img == 128).all()  # drawn on a copy
    green = np.all(out == (0, 255, 0), axis=2)
    for x, y in np.rint(px).astype(int):
        ys, xs = slice(max(y - 1, 0), y + 2), slice(max(x - 1, 0), x + 2)
        assert green[ys, xs].all()
    o, tip_x = cam.project(np.array([[0, 0, 0], [0.1, 0, 0]], float), pose).round().astype(int)
    assert out[o[1], o[0]].tolist() != [128, 128, 128]  # the axes start at W's origin
    assert out[tip_x[1], tip_x[0], 2] > 200  # x axis red (BGR)
    assert (out[6:12, 6:12] == 0).all()  # the status box
    assert out[:40, :400, 1].max() >= 200  # green "ok" text

    lost = draw_overlay(img, SimpleNamespace(status="lost"), cam, axis_m=0.2)
    drawn = np.any(lost != 128, axis=2)
    assert not drawn[40:].any() and not drawn[:, 200:].any()  # only the status box
    assert lost[drawn][:, 2].max() >= 200 and lost[drawn][:, 1].max() < 60  # red on black


def test_report_module_is_pure(sample_report, tmp_path, monkeypatch):
    """report.py imports no plotting or file helpers and computes a report without
    opening a file or importing matplotlib."""
    tree = ast.parse(Path(report_module.__file__).read_text())
    imported = {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)} | {
        a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names
    }
    assert not {m for m in imported if m.split(".")[0] in ("matplotlib", "cv2", "yaml")}
    assert not {m for m in imported if m.lstrip(".") in ("fileio", "plotting", "ui")}
    poses = read_pose_csv(SAMPLE / "orbit_truth.csv")
    path = load_path(SAMPLE / "desired_path.yaml")

    def no_open(*a, **k):
        raise AssertionError(f"report opened a file: {a}")

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(builtins, "open", no_open)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # any import of it fails
    rep = make_report(poses, path, poses)
    assert rep.summary["tracked_pct"] == 100.0
    assert list(tmp_path.iterdir()) == []


def test_cli_start_up_does_not_import_matplotlib():
    code = "import sys, mirage_cli.cli; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_overlay_frames_carry_their_frame_number_and_time():
    """Bottom left: 'frame N  T s' (the pose CSV's frame and time_s), on every status."""
    cam = default_camera()
    img = np.full((cam.height, cam.width, 3), 128, np.uint8)
    rec = SimpleNamespace(status="lost", frame=42, time_s=1.4)
    out = draw_overlay(img, rec, cam, axis_m=0.2)
    bottom = np.any(out[-40:, :200] != 128, axis=2)
    assert bottom.any() and out[-40:, :200].max() == 255  # white text on black
    assert not np.any(out[40:-40] != 128)  # nothing else but the two boxes
    from mirage_cli.plotting import _frame_stamp

    assert _frame_stamp(rec) == "frame 42  1.400 s"
    none = draw_overlay(img, SimpleNamespace(status="lost"), cam, axis_m=0.2)
    assert not np.any(none[-40:] != 128)  # no frame known: no stamp


def test_report_plot_says_the_signs_and_labels_the_lost_band(sample_report):
    rep, path = sample_report
    fig = report_figure(rep, path)
    labels = [a.get_ylabel() for a in fig.axes[1:]]
    assert any("+ left of path" in s for s in labels), labels
    assert any("+ turned left" in s for s in labels) and any("+ above" in s for s in labels)
    legend = fig.axes[1].get_legend()
    assert legend is not None and "not tracked" in [t.get_text() for t in legend.get_texts()]
