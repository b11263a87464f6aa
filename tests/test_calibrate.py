"""`mirage calibrate` on real photos, synthetic renders with known truth, and bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import run_mirage as mirage

from mirage_cli.boards import Board
from mirage_cli.calibrate import (
    CalibOptions,
    Detections,
    View,
    calibrate,
    detect_images,
    detect_video,
    find_corners,
    weak_data_warnings,
)
from mirage_cli.camera import Camera
from mirage_cli.errors import InputError
from mirage_cli.frames import FrameSource, read_image, resolve_inputs

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "tests" / "data" / "chessboard-right"
SYNTH = ROOT / "sample_data" / "calibration"
TRUTH = ROOT / "sample_data" / "camera_truth.yaml"

# Table in tests/data/chessboard-right/README.md: OpenCV's sample pipeline (cornerSubPix
# with an 11 px half-window = 23x23 px, no outlier rejection).
REFERENCE = {"fx": 542.35, "fy": 541.62, "cx": 328.32, "cy": 246.95, "rms": 0.459}
# On these 640x480 photos the corner spacing is 21-35 px, so that window reaches
# across squares and moves some corners by 2-5 px (right02: 1.2 px view RMS). Our default
# (1/4 the spacing) is checked against the same photos calibrated by plain OpenCV with a
# 5 px half-window (`opencv_truth`, no code of ours): measured 0.01 / 0.02 px apart on fx /
# fy and 0.29 / 0.07 px on cx / cy; a 3 px half-window moves plain OpenCV's focal lengths
# by 0.65 px. On synthetic renders the truth is the generator's (camera_truth.yaml).
FOCAL_TOL_PX, CENTRE_TOL_PX = 0.3, 0.6


def opencv_truth() -> dict:
    """fx fy cx cy of the real photos by OpenCV alone: findChessboardCorners, cornerSubPix
    (5 px half-window), calibrateCamera with its default 5-coefficient model."""
    obj = np.zeros((54, 3), np.float32)
    obj[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 0.025
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    objs, corners = [], []
    for f in sorted(REAL.glob("*.jpg")):
        gray = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        found, c = cv2.findChessboardCorners(gray, (9, 6))
        if found:
            objs.append(obj)
            corners.append(cv2.cornerSubPix(gray, c, (5, 5), (-1, -1), crit))
    _, K, _, _, _ = cv2.calibrateCamera(objs, corners, gray.shape[::-1], None, None)
    return {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}


def assert_one_line_error(r, *words):
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mirage: error: "), r.stderr
    assert "Traceback" not in r.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])


@pytest.fixture(scope="module")
def real_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("calib")
    r = mirage(
        "calibrate",
        REAL,
        "--board",
        "9x6",
        "--square",
        "0.025",
        "-o",
        out / "camera.yaml",
        "--report",
        out / "calib.png",
    )
    assert r.returncode == 0, r.stderr
    return r, out


# --- real photos --------------------------------------------------------------------------
def test_real_photos_default(real_run):
    r, out = real_run
    cam = Camera.load(out / "camera.yaml")
    got = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}
    for k, v in opencv_truth().items():
        tol = FOCAL_TOL_PX if k in ("fx", "fy") else CENTRE_TOL_PX
        assert abs(got[k] - v) < tol, (k, got[k], v)
    assert cam.rms_px < 0.3  # reference pipeline: 0.459
    assert "RMS reprojection error" in r.stdout and "fx 537" in r.stdout


def test_real_photos_reproduce_reference_table(tmp_path):
    """With the reference's refinement window and no rejection we land on its table."""
    r = mirage(
        "calibrate",
        REAL,
        "--board",
        "9x6",
        "--square",
        "0.025",
        "-o",
        tmp_path / "c.yaml",
        "--subpix-window",
        "11",
        "--max-view-error",
        "100",
    )
    assert r.returncode == 0, r.stderr
    cam = Camera.load(tmp_path / "c.yaml")
    for k in ("fx", "fy", "cx", "cy"):
        assert abs(getattr(cam, k) - REFERENCE[k]) < 1.5, (k, getattr(cam, k))
    assert cam.rms_px < 0.6


def test_camera_yaml_round_trip(real_run):
    _, out = real_run
    path = out / "camera.yaml"
    cam = Camera.load(path)
    assert cam.size == (640, 480)
    assert cam.meta["board"] == "9x6" and cam.meta["pattern"] == "chessboard"
    assert cam.meta["square_m"] == pytest.approx(0.025)
    assert cam.meta["views_used"] == 13
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    errs = fs.getNode("per_view_errors_px").mat().ravel()
    std = fs.getNode("std_intrinsics").mat().ravel()
    fs.release()
    assert len(errs) == 13 and np.all(errs < 0.5)
    assert len(std) == 4 and np.all((std > 0) & (std < 2))
    again = out / "again.yaml"
    cam.save(again)
    assert Camera.load(again).same_as(cam, tol_px=1e-9)
    assert (out / "calib.png").read_bytes()[:4] == b"\x89PNG"


# --- synthetic renders with known truth ---------------------------------------------------
def test_synthetic_against_truth(tmp_path):
    """Against the generator's camera (camera_truth.yaml). Measured at dc25f7f: fx +0.05,
    fy +0.07, cx -0.29, cy -0.20 px, k1 -0.0005, k2 +0.0025, RMS 0.041 px; limits about
    3x the focal and 2x the centre errors (not 1% = 5 px)."""
    r = mirage("calibrate", SYNTH, "--board", "9x6", "--square", "0.025", "-o", tmp_path / "c.yaml")
    assert r.returncode == 0, r.stderr
    cam, truth = Camera.load(tmp_path / "c.yaml"), Camera.load(TRUTH)
    assert len(list(SYNTH.glob("*.jpg"))) >= 15
    for k in ("fx", "fy"):
        assert abs(getattr(cam, k) - getattr(truth, k)) < 0.2, (k, getattr(cam, k))
    for k in ("cx", "cy"):
        assert abs(getattr(cam, k) - getattr(truth, k)) < 0.5, (k, getattr(cam, k))
    k_err = np.abs(cam.dist.ravel()[:2] - truth.dist.ravel()[:2])
    assert k_err[0] < 0.003 and k_err[1] < 0.01, k_err
    assert cam.rms_px < 0.1


def test_charuco_rendered_views():
    """ChArUco detection + calibration on pinhole renders (exact homographies)."""
    board = Board(7, 5, 0.04, "charuco", 0.03, "DICT_5X5_100")
    tex = board.cv_board().generateImage((7 * 80, 5 * 80), marginSize=0)  # 80 px / square
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    S = np.diag([0.04 / 80, 0.04 / 80, 1.0])  # texture px -> metres
    rng = np.random.default_rng(3)
    views = []
    for i in range(8):
        rvec = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.2, 0.2)])
        R, _ = cv2.Rodrigues(rvec)
        t = np.array([0, 0, 0.55]) - R @ np.array([0.14, 0.10, 0])
        H = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ S
        img = cv2.warpPerspective(tex, H, (640, 480), flags=cv2.INTER_AREA, borderValue=255)
        found = find_corners(cv2.GaussianBlur(img, (3, 3), 0.6), board)
        assert found is not None, i
        views.append(View(f"v{i}", *found))
    calib = calibrate(Detections(views, (640, 480), 8), board, CalibOptions(zero_tangent=True))
    assert abs(calib.K[0, 0] - 600) < 6 and abs(calib.K[1, 1] - 600) < 6
    assert calib.rms_px < 0.5


# --- media and video ----------------------------------------------------------------------
def test_resolve_inputs_files_folders_globs(tmp_path):
    for name in ("b10.JPG", "b2.png", "notes.txt", "b1.jpeg"):
        (tmp_path / name).write_bytes(b"x")
    names = [p.name for p in resolve_inputs([tmp_path]).images]
    assert names == ["b1.jpeg", "b2.png", "b10.JPG"]  # natural order, any case
    assert [p.name for p in resolve_inputs([str(tmp_path / "b1*")]).images] == [
        "b1.jpeg",
        "b10.JPG",
    ]
    with pytest.raises(InputError, match="no images found"):
        resolve_inputs([str(tmp_path / "*.tif")])
    with pytest.raises(InputError, match="cannot decode"):
        read_image(tmp_path / "b2.png")


def test_video_sampling_and_duplicates(tmp_path):
    """Each photo held for 3 frames: every=1 finds 39 views, keeps 13 distinct ones."""
    video = tmp_path / "calib.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480))
    photos = sorted(REAL.glob("*.jpg"))[:6]
    for p in photos:
        for _ in range(3):
            w.write(cv2.imread(str(p)))
    w.release()
    assert resolve_inputs([video]).is_video
    frames = list(FrameSource([video]).frames(every=2))
    assert [f.index for f in frames] == list(range(0, 18, 2))
    assert frames[1].time_s == pytest.approx(0.2)
    det = detect_video(video, Board(9, 6, 0.025), every=1)
    assert det.examined == 18 and len(det.views) == 6 and det.duplicates == 12


# --- bad input: one line on stderr, exit 2 ------------------------------------------------
def test_no_images_found(tmp_path):
    (tmp_path / "empty").mkdir()  # (an output inside the input folder is refused: issue 30)
    args = ["--board", "9x6", "--square", "0.025", "-o", tmp_path / "c.yaml"]
    assert_one_line_error(mirage("calibrate", tmp_path / "empty", *args), "no images found")


def test_wrong_board_size(tmp_path):
    imgs = sorted(REAL.glob("*.jpg"))[:4]
    r = mirage("calibrate", *imgs, "--board", "7x5", "--square", "0.025", "-o", tmp_path / "c.yaml")
    assert_one_line_error(r, "no 7x5 chessboard found", "--board 6x4")  # squares for corners
    assert not (tmp_path / "c.yaml").exists()


def test_noise_images(tmp_path):
    rng = np.random.default_rng(0)
    (tmp_path / "in").mkdir()
    for i in range(3):
        cv2.imwrite(str(tmp_path / "in" / f"n{i}.png"), rng.integers(0, 255, (240, 320), np.uint8))
    r = mirage(
        "calibrate",
        tmp_path / "in",
        "--board",
        "9x6",
        "--square",
        "0.025",
        "-o",
        tmp_path / "c.yaml",
    )
    assert_one_line_error(r, "no 9x6 chessboard found in any of the 3 images")


def test_too_few_views(tmp_path):
    imgs = sorted(REAL.glob("*.jpg"))[:2]
    r = mirage("calibrate", *imgs, "--board", "9x6", "--square", "0.025", "-o", tmp_path / "c.yaml")
    assert_one_line_error(r, "only 2 usable view", "at least 3")


def test_mixed_image_sizes(tmp_path):
    src = tmp_path / "in"  # the images; the camera goes beside, not among them
    src.mkdir()
    imgs = sorted(REAL.glob("*.jpg"))[:4]
    for p in imgs[:3]:
        shutil.copy(p, src)
    small = cv2.resize(cv2.imread(str(imgs[3])), (320, 240))
    cv2.imwrite(str(src / "small.jpg"), small)
    r = mirage("calibrate", src, "--board", "9x6", "--square", "0.025", "-o", tmp_path / "c.yaml")
    assert_one_line_error(r, "different sizes", "640x480", "320x240")


def test_corrupt_image_is_skipped(tmp_path):
    src = tmp_path / "in"  # the images; the camera goes beside, not among them
    src.mkdir()
    for p in sorted(REAL.glob("*.jpg")):
        shutil.copy(p, src)
    (src / "right99.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    r = mirage("calibrate", src, "--board", "9x6", "--square", "0.025", "-o", tmp_path / "c.yaml")
    assert r.returncode == 0, r.stderr
    assert "mirage: warning: skipped cannot decode image" in r.stderr
    assert "right99.jpg" in r.stderr and "Traceback" not in r.stderr
    assert "1 unreadable" in r.stdout
    assert Camera.load(tmp_path / "c.yaml").meta["views_used"] == 13


def test_only_corrupt_images(tmp_path):
    src = tmp_path / "in"  # the images; the camera goes beside, not among them
    src.mkdir()
    (src / "a.jpg").write_bytes(b"garbage")
    r = mirage("calibrate", src, "--board", "9x6", "--square", "0.025", "-o", tmp_path / "c.yaml")
    assert r.returncode == 2 and "mirage: error: none of the 1 images could be read" in r.stderr


@pytest.mark.parametrize("out", ["missing-dir/c.yaml", "."])
def test_unwritable_output_fails_before_work(tmp_path, out):
    r = mirage("calibrate", REAL, "--board", "9x6", "--square", "0.025", "-o", out, cwd=tmp_path)
    assert_one_line_error(r, "c.yaml" if "/" in out else "directory")


@pytest.mark.parametrize(
    "args, words",
    [
        (["--board", "9", "--square", "0.025"], ["--board", "COLSxROWS"]),
        (["--board", "1x6", "--square", "0.025"], ["--board", ">= 2"]),
        (["--board", "9x6", "--square", "-1"], ["--square", "must be > 0"]),
        (["--board", "9x6", "--square", "0.025", "--every", "0"], ["--every"]),
    ],
)
def test_bad_options(tmp_path, args, words):
    assert_one_line_error(mirage("calibrate", REAL, *args, "-o", tmp_path / "c.yaml"), *words)


def test_core_detection_counts():
    det = detect_images(sorted(REAL.glob("*.jpg")), Board(9, 6, 0.025), workers=2)
    assert len(det.views) == 13 and det.image_size == (640, 480)
    calib = calibrate(det, Board(9, 6, 0.025), CalibOptions(fix_aspect=True))
    assert calib.K[0, 0] == pytest.approx(calib.K[1, 1])
    assert not calib.rejected and calib.rms_px < 0.3


def test_the_same_corners_give_the_same_camera_to_the_bit():
    """calibrateCamera's parallel sums varied their order (K differed by ~4e-12 between two
    calls with 3 OpenCV threads); one thread inside it makes the camera reproducible, and
    the caller's thread count is restored."""
    det = detect_images(sorted(SYNTH.glob("*.jpg")), Board(9, 6, 0.025), workers=2)
    before = cv2.getNumThreads()
    cv2.setNumThreads(3)
    try:
        runs = [calibrate(det, Board(9, 6, 0.025)) for _ in range(4)]
        assert cv2.getNumThreads() == 3
    finally:
        cv2.setNumThreads(before)
    for c in runs[1:]:
        assert np.array_equal(c.K, runs[0].K) and np.array_equal(c.dist, runs[0].dist)
        assert c.rms_px == runs[0].rms_px


def _projected_views(tilt_max_rad: float, n: int = 12, seed: int = 0) -> list[View]:
    """Exact corner projections of a 9x6 board through a known camera."""
    board = Board(9, 6, 0.025)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    dist = np.array([-0.2, 0.05, 0, 0, 0])
    rng = np.random.default_rng(seed)
    views = []
    for i in range(n):
        rvec = np.r_[rng.uniform(-tilt_max_rad, tilt_max_rad, 2), rng.uniform(-0.3, 0.3)]
        R, _ = cv2.Rodrigues(rvec)
        t = np.r_[rng.uniform(-0.06, 0.06, 2), 0.35] - R @ np.array([0.1, 0.0625, 0])
        uv, _ = cv2.projectPoints(board.object_points.astype(float), rvec, t, K, dist)
        uv = uv.reshape(-1, 2) + rng.normal(0, 0.05, (54, 2))
        views.append(View(f"v{i}", uv.astype(np.float32), np.arange(54), "sb"))
    return views


def test_outlier_view_rejected_and_recalibrated():
    views = _projected_views(0.6)
    views[4].corners = views[4].corners + np.random.default_rng(1).normal(0, 2.0, (54, 2))
    calib = calibrate(Detections(views, (640, 480), 12), Board(9, 6, 0.025))
    assert [v.name for v, _ in calib.rejected] == ["v4"]
    assert len(calib.views) == 11 and calib.rms_px < 0.1
    assert abs(calib.K[0, 0] - 500) < 1 and abs(calib.K[0, 2] - 320) < 1


def test_weak_data_warnings():
    calib = calibrate(Detections(_projected_views(0.08, n=6), (640, 480), 6), Board(9, 6, 0.025))
    text = " ".join(calib.warnings)
    assert "only 6 views" in text
    assert "fronto-parallel" in text
    assert "image edge" in text
    good = calibrate(Detections(_projected_views(0.6), (640, 480), 12), Board(9, 6, 0.025))
    assert not any("fronto" in w or "only" in w or "folds" in w for w in good.warnings)
    # the same views with a strong barrel term at a short focal length: the polynomial
    # folds back 299 px out, inside the corners, and the warning says how much is lost
    good.K = np.array([[440.0, 0, 319.5], [0, 440.0, 239.5], [0, 0, 1]])
    good.dist = np.array([-0.3, -0.02, 0, 0, 0])
    fold = [w for w in weak_data_warnings(good) if "folds back 299 px" in w]
    assert len(fold) == 1 and "--model 8" in fold[0], weak_data_warnings(good)


def test_corrupt_video(tmp_path):
    junk = tmp_path / "calib.mp4"
    junk.write_bytes(b"not a video" * 200)
    r = mirage("calibrate", junk, "--board", "9x6", "--square", "0.025", "-o", tmp_path / "c.yaml")
    assert_one_line_error(r, "cannot open video")  # no FFmpeg noise on stderr
