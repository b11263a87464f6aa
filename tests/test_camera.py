import cv2
import numpy as np
import pytest
from conftest import SAMPLE

from mirage_cli.camera import Camera
from mirage_cli.errors import InputError
from mirage_cli.pose import Pose


def make_camera():
    K = np.array([[520.0, 0, 321.0], [0, 518.0, 239.5], [0, 0, 1]])
    return Camera(
        K,
        [-0.2, 0.07, 0.001, -0.0005, 0.01],
        640,
        480,
        rms_px=0.31,
        meta={"board": "9x6", "views_used": 17},
    )


def test_yaml_round_trip_and_opencv_readable(tmp_path):
    cam = make_camera()
    path = tmp_path / "cam.yaml"
    cam.save(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert np.allclose(fs.getNode("camera_matrix").mat(), cam.K)
    assert fs.getNode("image_width").real() == 640
    fs.release()
    back = Camera.load(path)
    assert np.allclose(back.K, cam.K) and np.allclose(back.dist, cam.dist)
    assert back.size == (640, 480) and back.rms_px == pytest.approx(0.31)
    assert back.meta["board"] == "9x6"


def test_sample_camera_is_opencv_readable():
    fs = cv2.FileStorage(str(SAMPLE / "camera_truth.yaml"), 0)
    K = fs.getNode("camera_matrix").mat()
    assert K.shape == (3, 3) and K[0, 0] > 100


def test_reads_ros_camera_info(tmp_path):
    p = tmp_path / "ros.yaml"
    p.write_text(
        "image_width: 640\nimage_height: 480\ncamera_name: webcam\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [500, 0, 320, 0, 501, 240, 0, 0, 1]\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.1, 0.01, 0, 0, 0]\n"
    )
    cam = Camera.load(p)
    assert cam.fx == 500 and cam.fy == 501 and cam.cx == 320 and cam.dist[0] == -0.1


@pytest.mark.parametrize(
    "text, msg",
    [
        ("", "mapping"),
        ("image_width: 640\n", "camera_matrix"),
        ("%YAML:1.0\n---\nimage_width: 640\n", "camera_matrix"),
        ("camera_matrix: [1, 2\n", "not valid YAML"),
    ],
)
def test_bad_camera_files(tmp_path, text, msg):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=msg):
        Camera.load(p)


def test_missing_camera_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        Camera.load(tmp_path / "nope.yaml")


def test_project_undistort_inverse():
    cam = make_camera()
    rng = np.random.default_rng(1)
    X = np.column_stack(
        [rng.uniform(-0.8, 0.8, 200), rng.uniform(-0.6, 0.6, 200), rng.uniform(1, 3, 200)]
    )
    uv = cam.project(X, Pose.identity())
    xy = cam.undistort_points(uv)
    assert np.allclose(xy, X[:, :2] / X[:, 2:], atol=1e-9)
    rays = cam.pixel_rays(uv)
    assert np.allclose(rays, X / np.linalg.norm(X, axis=1, keepdims=True), atol=1e-9)


def test_scaled_camera_keeps_rays():
    cam = make_camera()
    half = cam.scaled(320, 240)
    X = np.array([[0.3, -0.2, 2.0], [-0.5, 0.4, 1.5]])
    uv, uv2 = cam.project(X, Pose.identity()), half.project(X, Pose.identity())
    assert np.allclose((uv2 + 0.5) * 2 - 0.5, uv, atol=1e-9)
