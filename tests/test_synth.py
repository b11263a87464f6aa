"""The synthetic scene generator: exact geometry, determinism, and the committed sample data."""

import cv2
import numpy as np
import pandas as pd
import pytest
from conftest import SAMPLE, assert_one_line_error

from mirage_cli.camera import Camera
from mirage_cli.pose import look_at
from mirage_cli.render import Renderer
from mirage_cli.synth import (
    LANDMARK_BOUNDS,
    OrbitPath,
    default_camera,
    landmark_scene,
    landmark_surface_distance,
    landmark_surface_samples,
)
from mirage_cli.trajectory import POSE_COLUMNS, read_pose_csv


@pytest.fixture(scope="module")
def scene():
    return landmark_scene(0)


def test_renderer_projection_accuracy(scene):
    """Texture markers (X-junctions at known 3D points) appear where the distorted camera
    projects them: sub-pixel corner detection agrees within 0.5 px."""
    cam = default_camera()
    assert abs(cam.dist[0]) > 0.1  # distortion is on
    r = Renderer(scene, cam)
    errors = []
    for az in (20, 110, 200, 290):
        a = np.radians(az)
        pose = look_at([0.9 * np.cos(a), 0.9 * np.sin(a), 0.45], [0.05, 0.02, 0.25])
        img = cv2.cvtColor(r.render(pose, noise_sigma=0.0), cv2.COLOR_BGR2GRAY)
        M, N = scene.markers, scene.marker_normals
        facing = (
            np.einsum("ij,ij->i", N, pose.center - M) / np.linalg.norm(pose.center - M, axis=1)
            > 0.5
        )
        uv = cam.project(M, pose)
        inside = ((uv > 15) & (uv < np.array([cam.width, cam.height]) - 15)).all(axis=1)
        use = facing & inside & r.visible(pose, M)
        if not use.any():
            continue
        start = (uv[use] + np.array([1.2, -1.0])).astype(np.float32).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
        found = cv2.cornerSubPix(img, start, (4, 4), (-1, -1), crit).reshape(-1, 2)
        errors.append(np.linalg.norm(found - uv[use], axis=1))
        # markers far from the centre are where distortion matters
    err = np.concatenate(errors)
    assert len(err) >= 8
    assert np.max(err) <= 0.5, err


def test_surface_distance(scene):
    pts = landmark_surface_samples(0.05)
    assert np.max(landmark_surface_distance(pts)) < 1e-9
    assert np.allclose(landmark_surface_distance([[0, 0, 1.0]]), 1.0 - 0.62 + 0.0, atol=0.2)
    assert np.isclose(landmark_surface_distance([[1.30, 0, 0.1]])[0], 1.0)
    assert len(scene.markers) >= 20


def test_orbit_path_goes_around_and_looks_away():
    path = OrbitPath()
    t = np.arange(0, path.duration_s, 1 / 30)
    az = np.unwrap([np.arctan2(*path.pose(x).center[[1, 0]]) for x in t])
    assert np.degrees(az[-1] - az[0]) >= 360
    d = np.array([np.linalg.norm(path.pose(x).center) for x in t])
    assert 1.0 <= d.min() and d.max() <= 2.5


def test_same_seed_is_byte_identical(mirage, tmp_path):
    args = [
        "--width",
        "160",
        "--only",
        "calibration,keyframes",
        "--calib-views",
        "2",
        "--keyframe-step",
        "120",
        "--jobs",
        "1",
    ]
    a, b = tmp_path / "a", tmp_path / "b"
    assert mirage("synth", a, "--seed", "7", *args).returncode == 0
    assert mirage("synth", b, "--seed", "7", *args).returncode == 0
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) >= 7
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    c = tmp_path / "c"
    assert mirage("synth", c, "--seed", "8", *args).returncode == 0
    assert (a / "keyframes/kf_000.jpg").read_bytes() != (c / "keyframes/kf_000.jpg").read_bytes()


def test_bad_input(mirage, tmp_path):
    assert_one_line_error(mirage("synth", tmp_path / "o", "--width", "-5"), 2, "--width")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    import os

    if os.geteuid() != 0:  # root may write anywhere; use an impossible path instead
        assert_one_line_error(mirage("synth", ro / "x"), 2, "cannot")
    assert_one_line_error(mirage("synth", "/proc/mirage/x", "--only", "keyframes"), 2, "cannot")
    assert_one_line_error(mirage("synth", tmp_path / "o", "--only", "bogus"), 2, "bogus")
    assert_one_line_error(mirage("synth", tmp_path / "o", "--board", "9"), 2, "COLSxROWS")


# --- the committed sample data ---------------------------------------------------------
def test_sample_data_files():
    cam = Camera.load(SAMPLE / "camera_truth.yaml")
    assert cam.size == (640, 480)
    assert len(list((SAMPLE / "calibration").glob("*.jpg"))) >= 15
    kf = read_pose_csv(SAMPLE / "keyframes" / "poses.csv")
    assert len(kf) == 36
    assert all((SAMPLE / "keyframes" / f).is_file() for f in kf["frame"])
    az = np.sort(kf["azimuth_deg"].to_numpy())
    assert np.allclose(np.diff(az), 10, atol=1e-6)
    size = sum(p.stat().st_size for p in SAMPLE.rglob("*") if p.is_file())
    assert size < 20e6


def test_orbit_video_and_truth():
    cap = cv2.VideoCapture(str(SAMPLE / "orbit.mp4"))
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        assert frame.shape == (480, 640, 3)
        n += 1
    assert n >= 450
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(30)
    raw = pd.read_csv(SAMPLE / "orbit_truth.csv")
    assert list(raw.columns[: len(POSE_COLUMNS)]) == POSE_COLUMNS
    assert len(raw) == n and raw["frame"].tolist() == list(range(n))
    truth = read_pose_csv(SAMPLE / "orbit_truth.csv")
    cam = Camera.load(SAMPLE / "camera_truth.yaml")
    away = truth[truth["landmark_visible"] == 0]
    assert len(away) >= 30  # at least 1 s out of view
    # in those frames the landmark's projected bounding box misses the image
    lo, hi = LANDMARK_BOUNDS
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    from mirage_cli.trajectory import row_pose

    for _, row in away.iterrows():
        pose = row_pose(row)
        Xc = pose.transform(corners)
        if (Xc[:, 2] <= 0).any():
            continue  # partly behind the camera: certainly not in the image
        uv = cam.project(corners, pose)
        assert (
            uv[:, 0].max() < 0 or uv[:, 0].min() > 639 or uv[:, 1].max() < 0 or uv[:, 1].min() > 479
        )
