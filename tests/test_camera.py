import cv2
import numpy as np
import pytest
from conftest import SAMPLE, assert_one_line_error

from mirage_cli.camera import Camera, beyond_fold, fold_radius
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


@pytest.mark.parametrize(
    "dist",
    [
        [-0.2, 0.07, 0.001, -0.0005],
        [-0.2, 0.07, 0.001, -0.0005, 0.01],
        [0.3, -0.1, 0.002, 0.001, 0.02, 0.5, -0.05, 0.01],  # rational
        [0.1, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.001, 0.0, -0.002, 0.0],  # thin prism
    ],
)
def test_project_is_opencvs_projection(dist):
    """The numpy projection of the common models is cv2.projectPoints' to the last bit
    (behind and at depth 0 included), from any pose."""
    cam = Camera(np.array([[520.0, 0, 321.0], [0, 518.0, 239.5], [0, 0, 1]]), dist, 640, 480)
    rng = np.random.default_rng(3)
    X = rng.uniform(-1, 1, (500, 3)) + [0, 0, 2.0]
    X[:20, 2] *= -1  # behind the camera
    X[20, 2] = 0.0
    pose = Pose.from_rvec_tvec(np.array([0.1, -0.3, 0.2]), np.array([0.05, -0.1, 0.3]))
    want, _ = cv2.projectPoints(X, pose.rvec, pose.t, cam.K, cam.dist)
    assert np.array_equal(cam.project(X, pose), want.reshape(-1, 2))


def test_scaled_camera_keeps_rays():
    cam = make_camera()
    half = cam.scaled(320, 240)
    X = np.array([[0.3, -0.2, 2.0], [-0.5, 0.4, 1.5]])
    uv, uv2 = cam.project(X, Pose.identity()), half.project(X, Pose.identity())
    assert np.allclose((uv2 + 0.5) * 2 - 0.5, uv, atol=1e-9)


# --- ROS camera_info in its common spellings ------------------------------------------------
ROS_CALIBRATION_YAML = """\
image_width: 1280
image_height: 720
camera_name: head_camera
camera_matrix:
  rows: 3
  cols: 3
  data: [912.3, 0, 641.2, 0, 910.8, 362.4, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.112, 0.0891, 0.00031, -0.00022, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [890.1, 0, 640.5, 0, 0, 895.3, 361.9, 0, 0, 0, 1, 0]
"""

ROS1_ECHO = """\
header:
  seq: 1523
  stamp:
    secs: 1700000000
    nsecs: 125000000
  frame_id: "head_camera"
height: 720
width: 1280
distortion_model: "plumb_bob"
D: [-0.112, 0.0891, 0.00031, -0.00022, 0.0]
K: [912.3, 0.0, 641.2, 0.0, 910.8, 362.4, 0.0, 0.0, 1.0]
R: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
P: [890.1, 0.0, 640.5, 0.0, 0.0, 895.3, 361.9, 0.0, 0.0, 0.0, 1.0, 0.0]
binning_x: 0
binning_y: 0
roi:
  x_offset: 0
  y_offset: 0
  height: 0
  width: 0
  do_rectify: False
---
"""

ROS2_ECHO = """\
header:
  stamp:
    sec: 1700000000
    nanosec: 125000000
  frame_id: head_camera
height: 720
width: 1280
distortion_model: plumb_bob
d:
- -0.112
- 0.0891
- 0.00031
- -0.00022
- 0.0
k:
- 912.3
- 0.0
- 641.2
- 0.0
- 910.8
- 362.4
- 0.0
- 0.0
- 1.0
r:
- 1.0
- 0.0
- 0.0
- 0.0
- 1.0
- 0.0
- 0.0
- 0.0
- 1.0
p:
- 890.1
- 0.0
- 640.5
- 0.0
- 0.0
- 895.3
- 361.9
- 0.0
- 0.0
- 0.0
- 1.0
- 0.0
binning_x: 0
binning_y: 0
roi:
  x_offset: 0
  y_offset: 0
  height: 0
  width: 0
  do_rectify: false
---
header:
  stamp:
    sec: 1700000000
    nanosec: 158000000
  frame_id: head_camera
height: 720
width: 1280
"""


@pytest.mark.parametrize(
    "text", [ROS_CALIBRATION_YAML, ROS1_ECHO, ROS2_ECHO], ids=["calibration", "ros1", "ros2"]
)
def test_reads_every_ros_camera_info_spelling(tmp_path, text):
    p = tmp_path / "camera_info.yaml"
    p.write_text(text)
    cam = Camera.load(p)
    assert cam.model == "pinhole" and cam.size == (1280, 720)
    assert np.allclose(cam.K, [[912.3, 0, 641.2], [0, 910.8, 362.4], [0, 0, 1]])
    assert np.allclose(cam.dist, [-0.112, 0.0891, 0.00031, -0.00022, 0])
    # the same lens as OpenCV sees it: projection agrees with cv2.projectPoints
    X = np.array([[0.4, -0.3, 2.0], [-0.7, 0.2, 1.5]])
    uv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.allclose(cam.project(X, Pose.identity()), uv.reshape(-1, 2), atol=1e-9)


def test_reads_rational_polynomial(tmp_path):
    p = tmp_path / "rational.yaml"
    text = ROS1_ECHO.replace('"plumb_bob"', "rational_polynomial").replace(
        "D: [-0.112, 0.0891, 0.00031, -0.00022, 0.0]",
        "D: [-0.112, 0.0891, 0.00031, -0.00022, 0.01, 0.2, -0.05, 0.03]",
    )
    p.write_text(text)
    cam = Camera.load(p)
    assert cam.model == "pinhole" and cam.dist.size == 8 and cam.dist[7] == 0.03


# --- the fisheye (equidistant) model ----------------------------------------------------------
FISHEYE_D = [0.021, -0.0083, 0.0042, -0.0011]
ROS_EQUIDISTANT = """\
image_width: 1280
image_height: 800
camera_name: fisheye_front
camera_matrix: {rows: 3, cols: 3, data: [420.5, 0, 639.8, 0, 421.2, 401.3, 0, 0, 1]}
distortion_model: equidistant
distortion_coefficients: {rows: 1, cols: 4, data: [0.021, -0.0083, 0.0042, -0.0011]}
rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}
projection_matrix: {rows: 3, cols: 4, data: [420.5, 0, 639.8, 0, 0, 421.2, 401.3, 0, 0, 0, 1, 0]}
"""


def _wide_points(rng, n=300, max_deg=80.0):
    """Points in front of the camera up to max_deg off the optical axis."""
    theta = np.radians(rng.uniform(0, max_deg, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    d = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    return d * rng.uniform(1.0, 4.0, (n, 1))


def test_ros_equidistant_is_read_as_opencv_fisheye(tmp_path):
    p = tmp_path / "fisheye.yaml"
    p.write_text(ROS_EQUIDISTANT)
    cam = Camera.load(p)
    assert cam.model == "fisheye" and np.allclose(cam.dist, FISHEYE_D)
    X = _wide_points(np.random.default_rng(3))
    uv = cam.project(X, Pose.identity())
    ref, _ = cv2.fisheye.projectPoints(
        X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist
    )
    assert np.allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    # read as plumb_bob, the same numbers would put points tens of pixels elsewhere
    wrong, _ = cv2.projectPoints(X[:50], np.zeros(3), np.zeros(3), cam.K, np.r_[FISHEYE_D, 0])
    assert np.median(np.linalg.norm(wrong.reshape(-1, 2) - uv[:50], axis=1)) > 20


def test_fisheye_project_undistort_round_trip():
    cam = Camera(
        [[420.5, 0, 639.8], [0, 421.2, 401.3], [0, 0, 1]], FISHEYE_D, 1280, 800, model="fisheye"
    )
    X = _wide_points(np.random.default_rng(4))
    uv = cam.project(X, Pose.identity())
    xy = cam.undistort_points(uv)
    assert np.abs(xy - X[:, :2] / X[:, 2:]).max() < 1e-6
    rays = cam.pixel_rays(uv)
    assert np.abs(rays - X / np.linalg.norm(X, axis=1, keepdims=True)).max() < 1e-6
    # ideal pixels: what the distortion-free pinhole with the same K sees
    ideal = cam.standard().project(X, Pose.identity())
    assert np.abs(cam.ideal_pixels(uv) - ideal).max() < 1e-4


def test_fisheye_with_zero_coefficients_is_not_a_pinhole():
    """Equidistant with k = 0 is r = f * theta: the solver's pinhole fast path must not
    take it for a lens without distortion."""
    from mirage_cli.solver import solve_pose

    cam = Camera(
        [[300.0, 0, 320], [0, 300, 240], [0, 0, 1]], [0, 0, 0, 0], 640, 480, model="fisheye"
    )
    rng = np.random.default_rng(5)
    X = np.column_stack(
        [rng.uniform(-1, 1, 40), rng.uniform(-1, 1, 40), rng.uniform(-0.5, 0.5, 40)]
    )
    truth = Pose.from_rvec_tvec(np.array([0.1, -0.2, 0.05]), np.array([0.1, -0.05, 1.6]))
    uv = cam.project(X, truth)
    est = solve_pose(X, uv, cam, reference_pose=None, method="mirage-s")
    assert est.success, est.reason
    assert est.pose.distance_to(truth) < 1e-6 and est.pose.angle_to(truth) < 1e-4


@pytest.mark.parametrize("method", ["mirage-s", "sqpnp", "epnp"])
def test_solve_pose_recovers_pose_from_fisheye_pixels(method):
    from mirage_cli.solver import RefineOptions, solve_pose

    cam = Camera(
        [[420.5, 0, 639.8], [0, 421.2, 401.3], [0, 0, 1]], FISHEYE_D, 1280, 800, model="fisheye"
    )
    rng = np.random.default_rng(6)
    X = np.column_stack([rng.uniform(-2, 2, 80), rng.uniform(-2, 2, 80), rng.uniform(-1, 1, 80)])
    truth = Pose.from_rvec_tvec(np.array([0.2, 0.1, -0.1]), np.array([0.0, 0.1, 2.2]))
    uv = cam.project(X, truth)
    ref = Pose.from_rvec_tvec(np.array([0.3, 0.0, -0.2]), np.array([0.1, 0.0, 2.4]))
    est = solve_pose(X, uv + rng.normal(0, 0.3, uv.shape), cam, reference_pose=ref, method=method)
    assert est.success, est.reason
    assert est.pose.distance_to(truth) < 0.01 and est.pose.angle_to(truth) < 0.3
    # read as plumb_bob the same pixels give no such pose
    pin = Camera(cam.K, np.r_[FISHEYE_D, 0], 1280, 800)
    bad = solve_pose(
        X, uv, pin, reference_pose=ref, method=method, refine=RefineOptions(max_rmse_px=2.0)
    )
    assert not bad.success or bad.pose.distance_to(truth) > 0.05


def test_fisheye_file_round_trip_keeps_the_model(tmp_path):
    cam = Camera(
        [[420.5, 0, 639.8], [0, 421.2, 401.3], [0, 0, 1]], FISHEYE_D, 1280, 800, model="fisheye"
    )
    path = tmp_path / "fisheye.yaml"
    cam.save(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("distortion_model").string() == "equidistant"
    fs.release()
    back = Camera.load(path)
    assert back.model == "fisheye" and np.allclose(back.dist, FISHEYE_D)
    assert back.same_as(cam) and not back.same_as(Camera(cam.K, np.r_[FISHEYE_D, 0], 1280, 800))
    half = back.scaled(640, 400)
    assert half.model == "fisheye"


# --- bad camera files: one line, exit 2, naming the file --------------------------------------
K_OK = "[500, 0, 320, 0, 500, 240, 0, 0, 1]"


@pytest.mark.parametrize(
    "text, contains",
    [
        (
            ROS1_ECHO.replace("0.0, 0.0, 1.0]\nR", "0.0, 0.0, 0.0]\nR"),
            "bottom row must be [0, 0, 1]",
        ),
        (ROS2_ECHO.replace("- 912.3", "- -912.3"), "positive focal lengths"),
        (ROS1_ECHO.replace("K: [912.3", "K: [.nan"), "finite"),
        (ROS1_ECHO.replace("K: [912.3, 0.0,", "K: [912.3,"), "must have 9 numbers, has 8"),
        (ROS1_ECHO.replace('"plumb_bob"', "double_sphere"), "distortion_model 'double_sphere'"),
        (
            ROS_EQUIDISTANT.replace("0.0042, -0.0011]", "0.0042, -0.0011, 0]").replace(
                "cols: 4", "cols: 5"
            ),
            "4 distortion coefficients, got 5",
        ),
        (ROS_CALIBRATION_YAML.replace("cols: 5", "cols: 4"), "says 1x4 but has 5 numbers"),
        (ROS_CALIBRATION_YAML.replace("image_height: 720", "image_height: [720]"), "image_height"),
        (ROS1_ECHO.replace("D: [", "D: [abc, "), "'D' is not a list of numbers"),
        ("image_width: 640\nimage_height: 480\nk: {a: 1}\n", "'k' has no 'data'"),
        (f"width: 0\nheight: 0\nK: {K_OK}\n", "0x0"),
        (
            "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
            "   rows: 3\n   cols: 3\n   dt: d\n   data: [ 520., 0., 323.5, 0., 51",
            "not valid OpenCV YAML",
        ),
        (
            "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
            "   rows: 3\n   cols: 3\n   dt: d\n"
            "   data: [ 520., 0., 323.5, 0., 518., 237.2, 0., 0., 0. ]\n",
            "bottom row",
        ),
    ],
)
def test_bad_camera_file_is_one_line_error(mirage, tmp_path, text, contains):
    p = tmp_path / "cam.yaml"
    p.write_text(text)
    proc = mirage("synth", tmp_path / "out", "--camera", p, "--only", "calibration")
    assert_one_line_error(proc, 2, contains)
    assert str(p) in proc.stderr


def test_truncated_sample_camera_is_one_line_error(mirage, tmp_path):
    """FileStorage raises SystemError or cv2.error on cut files: never 'unexpected'."""
    text = (SAMPLE / "camera_truth.yaml").read_text()
    for cut in range(40, len(text), 23):
        p = tmp_path / f"cut{cut}.yaml"
        p.write_text(text[:cut])
        try:
            Camera.load(p)
        except InputError as e:
            assert str(p) in str(e) and "\n" not in str(e)
    p = tmp_path / "cut.yaml"
    p.write_text(text[:200])
    assert_one_line_error(mirage("synth", tmp_path / "o", "--camera", p), 2, str(p))


def test_model_file_keeps_a_fisheye_camera(tmp_path):
    """A model built with a fisheye camera must not come back as plumb_bob."""
    from mirage_cli.features import DetectorSettings
    from mirage_cli.model import Keyframe, LandmarkModel

    cam = Camera(
        [[420.5, 0, 639.8], [0, 421.2, 401.3], [0, 0, 1]], FISHEYE_D, 1280, 800, model="fisheye"
    )
    pts = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.05]])
    pose = Pose.from_rvec_tvec(np.zeros(3), np.array([0.0, 0.0, 1.0]))
    kf = Keyframe(
        "kf_000",
        pose,
        cam.project(pts, pose).astype(np.float32),
        np.zeros((3, 128), np.float32),
        np.arange(3, dtype=np.int32),
        np.zeros((100, 160), np.uint8),
    )
    path = tmp_path / "m.mirage"
    LandmarkModel(cam, DetectorSettings(), [kf], pts).save(path)
    back = LandmarkModel.load(path).camera
    assert back.model == "fisheye" and back.same_as(cam)
    assert np.allclose(back.project(pts, pose), kf.keypoints, atol=1e-3)


def _folding_camera() -> Camera:
    """A strong barrel term at a short focal length (a random scene family's camera at
    the edge of its range): the polynomial folds back 299 px from the centre (r_d = 0.68
    at r = 1), inside a 640x480 image's corners (400 px)."""
    K = np.array([[440.0, 0, 319.5], [0, 440.0, 239.5], [0, 0, 1]])
    return Camera(K, np.array([-0.3, -0.02, 0, 0, 0]), 640, 480)


def test_the_pixels_beyond_a_lens_models_fold_are_those_without_a_ray():
    """`beyond_fold` is the share of pixels whose undistorted ray does not project back to
    them: beyond the fold OpenCV's iterative undistortion hands a pixel a wrong ray (tens
    to hundreds of px off); inside it the round trip holds to 1e-3 px. The sample's lens folds
    nowhere in its image."""
    cam = _folding_camera()
    fold = fold_radius(cam) * cam.K[0, 0]
    assert 280 < fold < 310, fold
    u, v = np.meshgrid(np.arange(0, 640, 8) + 1.5, np.arange(0, 480, 8) + 1.5)
    px = np.column_stack([u.ravel(), v.ravel()])
    back = cam.project(cam.pixel_rays(px) * 5.0, Pose(np.eye(3), np.zeros(3)))
    err = np.linalg.norm(back - px, axis=1)
    r = np.hypot(px[:, 0] - 319.5, px[:, 1] - 239.5)
    assert err[r < fold - 2].max() < 1e-3
    assert np.median(err[r > fold + 10]) > 5.0
    assert beyond_fold(cam) == pytest.approx(np.mean(r >= fold), abs=0.01)
    assert 0.1 < beyond_fold(cam) < 0.25
    sample = Camera.load(SAMPLE / "camera_truth.yaml")
    assert fold_radius(sample) == float("inf") or beyond_fold(sample) == 0.0


def test_tracking_with_a_lens_that_folds_in_the_image_says_so(tmp_path, sample_model, mirage):
    """A camera file whose distortion folds inside the image (corners never calibrated)
    is tracked, with one warning line that says how much of the image has no ray."""
    cam_file = tmp_path / "folding.yaml"
    _folding_camera().save(cam_file)
    p = mirage("track", SAMPLE / "orbit.mp4", "--model", sample_model, "--camera", cam_file,
               "--end", "3", "-o", tmp_path / "poses.csv")  # fmt: skip
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in (p.stdout + p.stderr).splitlines() if "folds back" in ln]
    assert len(lines) == 1 and "299 px" in lines[0] and "of the image" in lines[0], lines
    p = mirage("track", SAMPLE / "orbit.mp4", "--model", sample_model, "--end", "3",
               "-o", tmp_path / "poses2.csv")  # fmt: skip
    assert p.returncode == 0 and "folds back" not in p.stdout + p.stderr


def test_building_a_model_with_a_lens_that_folds_in_the_image_says_so(tmp_path, mirage):
    """`mirage build-model` warns as `track` does, once, and still builds."""
    cam_file = tmp_path / "folding.yaml"
    _folding_camera().save(cam_file)
    kf = SAMPLE / "keyframes"
    p = mirage("build-model", kf, "--camera", cam_file, "--poses", kf / "poses.csv",
               "-o", tmp_path / "m.mirage")  # fmt: skip
    lines = [ln for ln in (p.stdout + p.stderr).splitlines() if "folds back" in ln]
    assert len(lines) == 1 and "299 px" in lines[0], (lines, p.stderr[-500:])
    assert p.returncode == 0 and (tmp_path / "m.mirage").stat().st_size > 0, p.stderr
