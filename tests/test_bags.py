"""ROS bags in (ROS 1 .bag, ROS 2 sqlite3 and mcap, written here with rosbags' writers from
frames of sample_data/orbit.mp4) and motion-capture truth in `mirage report`."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import SAMPLE, run_here
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from mirage_cli import bags as bags_module
from mirage_cli.bags import BagRef, read_poses
from mirage_cli.camera import Camera
from mirage_cli.frames import FrameSource

N = 5  # frames of the orbit in each bag
T0 = 1_700_000_000  # header stamps start here (s), 30 fps
KINDS = ("ros1", "sqlite3", "mcap")
TRACKED = KINDS  # every storage tracked end to end (and read frame by frame)
IMG, INFO = "/cam/image_raw", "/cam/camera_info"


class BagWriter:
    """A ROS 1 bag or a ROS 2 bag (sqlite3 / mcap storage), messages built by field name."""

    def __init__(self, path, kind: str):
        self.ros1 = kind == "ros1"
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:
            self.w = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.w = Writer2(path, version=9, storage_plugin=plugin)
        self.cons: dict[str, object] = {}

    def __enter__(self):
        self.w.open()
        return self

    def __exit__(self, *exc):
        self.w.close()

    def msg(self, typ: str, **fields):
        return self.ts.types[typ](**fields)

    def header(self, t: float):
        sec = int(np.floor(t))
        stamp = self.msg("builtin_interfaces/msg/Time", sec=sec, nanosec=round((t - sec) * 1e9))
        extra = {"seq": 0} if self.ros1 else {}
        return self.msg("std_msgs/msg/Header", stamp=stamp, frame_id="cam", **extra)

    def write(self, topic: str, typ: str, t: float, message) -> None:
        if topic not in self.cons:
            self.cons[topic] = self.w.add_connection(topic, typ, typestore=self.ts)
        ser = self.ts.serialize_ros1 if self.ros1 else self.ts.serialize_cdr
        self.w.write(self.cons[topic], int(round(t * 1e9)), ser(message, typ))

    def image(self, topic: str, t: float, img: np.ndarray, encoding: str, rows=None) -> None:
        """A raw image; `rows` overrides the height the message claims (a damaged one)."""
        h, w = img.shape[:2]
        data = np.ascontiguousarray(img).reshape(-1).view(np.uint8)
        m = self.msg(
            "sensor_msgs/msg/Image",
            header=self.header(t),
            height=rows or h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=data.size // h,
            data=data,
        )
        self.write(topic, "sensor_msgs/msg/Image", t, m)

    def compressed(self, topic: str, t: float, img: np.ndarray, fmt: str) -> None:
        data = cv2.imencode("." + fmt, img)[1].ravel()
        m = self.msg(
            "sensor_msgs/msg/CompressedImage", header=self.header(t), format=fmt, data=data
        )
        self.write(topic, "sensor_msgs/msg/CompressedImage", t, m)

    def camera_info(self, topic: str, t: float, cam: Camera) -> None:
        k, d, r, p = ("K", "D", "R", "P") if self.ros1 else ("k", "d", "r", "p")
        roi = self.msg(
            "sensor_msgs/msg/RegionOfInterest",
            x_offset=0,
            y_offset=0,
            height=0,
            width=0,
            do_rectify=False,
        )
        P = np.zeros((3, 4))
        P[:, :3] = cam.K
        fields = {
            k: cam.K.ravel().copy(),
            d: cam.dist.copy(),
            r: np.eye(3).ravel(),
            p: P.ravel(),
        }
        m = self.msg(
            "sensor_msgs/msg/CameraInfo",
            header=self.header(t),
            height=cam.height,
            width=cam.width,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **fields,
        )
        self.write(topic, "sensor_msgs/msg/CameraInfo", t, m)

    def pose(self, topic: str, t: float, xyz, wxyz, typ="geometry_msgs/msg/PoseStamped"):
        point = self.msg("geometry_msgs/msg/Point", x=xyz[0], y=xyz[1], z=xyz[2])
        quat = self.msg("geometry_msgs/msg/Quaternion", w=wxyz[0], x=wxyz[1], y=wxyz[2], z=wxyz[3])
        pose = self.msg("geometry_msgs/msg/Pose", position=point, orientation=quat)
        self.write(topic, typ, t, self.msg(typ, header=self.header(t), pose=pose))


def bag_path(tmp_path, name: str, kind: str):
    return tmp_path / (f"{name}.bag" if kind == "ros1" else f"{name}_{kind}")


@pytest.fixture(scope="module")
def orbit():
    """The first N frames of the sample orbit, decoded once."""
    cap = cv2.VideoCapture(str(SAMPLE / "orbit.mp4"))
    frames = [cap.read()[1] for _ in range(N)]
    cap.release()
    assert all(f is not None for f in frames)
    return frames


@pytest.fixture(scope="module")
def bags(orbit, tmp_path_factory):
    """The orbit frames (bgr8) with camera_info, in each bag format; and as PNG files."""
    root = tmp_path_factory.mktemp("bags")
    cam = Camera.load(SAMPLE / "camera_truth.yaml")
    out = {}
    for kind in KINDS:
        path = bag_path(root, "orbit", kind)
        with BagWriter(path, kind) as w:
            w.camera_info(INFO, T0, cam)
            for i, img in enumerate(orbit):
                w.image(IMG, T0 + i / 30, img, "bgr8")
        out[kind] = path
    pngs = root / "pngs"
    pngs.mkdir()
    for i, img in enumerate(orbit):
        cv2.imwrite(str(pngs / f"{i:03d}.png"), img)
    out["pngs"] = pngs
    return out


def mirage(*argv) -> tuple[int, str]:
    """`mirage ARGV` in this process (one import for every run): exit code and stderr."""
    p = run_here("-q", *argv)
    return p.returncode, p.stderr


def assert_error(code: int, err: str, contains: str) -> None:
    """Exit 2 and one line `mirage: error: ...` holding `contains`."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, (code, err)
    assert lines[0].startswith("mirage: error: ") and "Traceback" not in err, err
    assert contains in lines[0], lines[0]


@pytest.fixture(scope="module")
def tracked(bags, sample_model):
    """`mirage track` on the PNG frames and on a ROS 1 bag and a ROS 2 bag of each storage
    (sqlite3, mcap; camera from camera_info)."""
    out = {}
    for name in ("pngs", *TRACKED):
        out[name] = bags[name].parent / f"track_{name}.csv"
        code, err = mirage("track", bags[name], "--model", sample_model, "-o", out[name])
        assert code == 0, err
    return out


# --------------------------------------------------------------------------------------
# frames from bags
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", TRACKED)
def test_track_on_a_bag_gives_the_poses_of_the_same_frames(tracked, kind):
    ref = pd.read_csv(tracked["pngs"], dtype=str, keep_default_na=False)
    got = pd.read_csv(tracked[kind], dtype=str, keep_default_na=False)
    assert list(got.columns) == list(ref.columns) and len(got) == len(ref) == N
    same = [c for c in ref.columns if c not in ("frame", "time_s", "ms")]
    pd.testing.assert_frame_equal(got[same], ref[same])  # every pose digit, every diagnostic
    assert (ref["status"] == "ok").all()
    assert got["frame"].tolist() == [str(i) for i in range(N)]  # index in the topic
    t = got["time_s"].astype(float).to_numpy()  # header stamps
    np.testing.assert_allclose(t - T0, np.arange(N) / 30, atol=2e-6)


def test_every_storage_yields_the_same_frames(bags, orbit):
    """What track reads: the same images, ids and stamps from every bag format."""
    for kind in KINDS:
        frames = list(FrameSource([bags[kind]]).frames())
        assert [f.id for f in frames] == list(range(N))
        assert all(np.array_equal(f.image, orbit[f.index]) for f in frames)
        t = np.array([f.time_s for f in frames])
        np.testing.assert_allclose(t - T0, np.arange(N) / 30, atol=2e-6)


def test_camera_comes_from_camera_info(bags, tmp_path, sample_model):
    truth = Camera.load(SAMPLE / "camera_truth.yaml")
    for kind in KINDS:
        cam = FrameSource([bags[kind]]).camera()
        assert np.array_equal(cam.K, truth.K) and np.array_equal(cam.dist, truth.dist)
        assert cam.size == truth.size
    # a camera_info of another camera than the model's: tracked with it, and said so
    other = Camera(truth.K * [[1.1], [1.1], [1]], truth.dist, truth.width, truth.height)
    path = bag_path(tmp_path, "other", "mcap")
    with BagWriter(path, "mcap") as w:
        w.camera_info(INFO, T0, other)
        w.image(IMG, T0, np.zeros((480, 640, 3), np.uint8), "bgr8")
    p = run_here("track", path, "--model", sample_model, "-o", tmp_path / "p.csv")
    assert "tracking with the camera_info of /cam/image_raw (640x480, fx 572 px)" in p.stdout
    assert p.returncode == 3  # a black frame: no landmark in it
    assert FrameSource([path]).camera().fx == pytest.approx(1.1 * truth.fx)


def mosaic(bgr: np.ndarray, pattern: str) -> np.ndarray:
    """The raw sensor image of a Bayer pattern named by its top-left 2x2 tile (rggb: R at
    (0, 0), G at (0, 1) and (1, 0), B at (1, 1))."""
    ch = {"b": 0, "g": 1, "r": 2}
    out = np.empty(bgr.shape[:2], np.uint8)
    for k, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        out[dy::2, dx::2] = bgr[dy::2, dx::2, ch[pattern[k]]]
    return out


def test_compressed_raw_and_bayer_images_decode_to_the_frame(orbit, tmp_path):
    img = orbit[0]
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    path = bag_path(tmp_path, "encodings", "sqlite3")
    with BagWriter(path, "sqlite3") as w:
        w.compressed("/jpeg/compressed", T0, img, "jpeg")
        w.compressed("/png/compressed", T0, img, "png")
        w.image("/rgb8", T0, img[:, :, ::-1], "rgb8")
        w.image("/mono8", T0, gray, "mono8")
        w.image("/mono16", T0, gray.astype(np.uint16) * 257, "mono16")
        for pat in ("rggb", "bggr", "gbrg", "grbg"):
            w.image(f"/bayer_{pat}", T0, mosaic(img, pat), f"bayer_{pat}8")

    def first(topic, gray=False):
        src = FrameSource([BagRef(path, topic)])
        assert src.count == 1 and src.size == (640, 480)
        return next(src.frames(gray=gray)).image

    assert np.array_equal(first("/png/compressed"), img)
    assert np.abs(first("/jpeg/compressed").astype(int) - img).mean() < 3  # lossy
    assert np.array_equal(first("/rgb8"), img)
    assert np.array_equal(first("/mono8", gray=True), gray)
    assert np.array_equal(first("/mono16", gray=True), gray)
    for pat in ("rggb", "bggr", "gbrg", "grbg"):
        got = first(f"/bayer_{pat}").astype(int)
        err = np.abs(got - img).mean(axis=(0, 1))  # per channel B, G, R
        swapped = np.abs(got[:, :, ::-1] - img).mean(axis=(0, 1))
        assert err.max() < 6 and swapped[[0, 2]].min() > 2 * err.max(), (pat, err, swapped)


def test_storage_files_frame_ranges_and_damaged_messages(orbit, bags, tmp_path):
    # the .db3 / .mcap file itself reads as its bag folder does
    for kind in ("sqlite3", "mcap"):
        (storage,) = bags[kind].glob(f"*.{'db3' if kind == 'sqlite3' else 'mcap'}")
        src = FrameSource([storage])
        assert src.count == N and src.camera() is not None
        frames = list(src.frames(start=1, end=4, every=2))  # --start / --end / --every
        assert [f.index for f in frames] == [1, 3] and [f.id for f in frames] == [1, 3]
        assert all(np.array_equal(f.image, orbit[f.index]) for f in frames)
        assert frames[0].time_s == pytest.approx(T0 + 1 / 30, abs=1e-6)
    # a truncated message is a damaged frame; the frames after it decode
    path = bag_path(tmp_path, "damaged", "ros1")
    with BagWriter(path, "ros1") as w:
        for i in range(3):  # message 1 says 480 rows, its data hold 100
            w.image(IMG, T0 + i, orbit[i][: 100 if i == 1 else 480], "bgr8", rows=480)
    frames = list(FrameSource([path]).frames(gray=True))
    assert [f.image is None for f in frames] == [False, True, False]
    assert np.array_equal(frames[2].image, cv2.cvtColor(orbit[2], cv2.COLOR_BGR2GRAY))


def test_topic_selection_and_bad_bags_are_one_line_errors(orbit, bags, tmp_path, sample_model):
    out = tmp_path / "p.csv"
    two = bag_path(tmp_path, "two", "ros1")
    with BagWriter(two, "ros1") as w:
        w.image("/left/image_raw", T0, orbit[0], "bgr8")
        w.image("/right/image_raw", T0, orbit[1], "bgr8")
    code, err = mirage("track", two, "--model", sample_model, "-o", out)
    msg = f"several image topics in {two}: /left/image_raw, /right/image_raw; pick one with --topic"
    assert_error(code, err, msg)
    # --topic picks
    img = next(FrameSource([BagRef(two, "/right/image_raw")]).frames()).image
    assert np.array_equal(img, orbit[1])
    code, err = mirage("track", two, "--topic", "/cam", "--model", sample_model, "-o", out)
    assert_error(code, err, "no topic /cam in")
    code, err = mirage("track", bags["pngs"], "--topic", "/x", "--model", sample_model, "-o", out)
    assert_error(code, err, "--topic /x selects the image topic of a ROS bag")

    none = bag_path(tmp_path, "none", "mcap")
    with BagWriter(none, "mcap") as w:
        w.camera_info(INFO, T0, Camera.load(SAMPLE / "camera_truth.yaml"))
    code, err = mirage("track", none, "--model", sample_model, "-o", out)
    assert_error(code, err, f"no image topics in {none}")

    odd = bag_path(tmp_path, "odd", "sqlite3")
    with BagWriter(odd, "sqlite3") as w:
        w.image(IMG, T0, np.zeros((4, 4), np.float32), "32FC1")
    code, err = mirage("track", odd, "--model", sample_model, "-o", out)
    assert_error(code, err, "topic /cam/image_raw: image encoding '32FC1' is not supported")
    assert not out.exists()

    # build-model: the camera from camera_info, else --camera is needed
    poses = SAMPLE / "keyframes" / "poses.csv"
    code, err = mirage("build-model", two, "--topic", "/left/image_raw", "--poses", poses)
    assert_error(code, err, "no calibrated camera_info for /left/image_raw; give --camera")
    code, err = mirage("build-model", bags["pngs"], "--poses", poses)
    assert_error(code, err, "give --camera FILE")


# --------------------------------------------------------------------------------------
# motion-capture truth in mirage report
# --------------------------------------------------------------------------------------
T_BC = np.array([0.05, -0.02, 0.10])  # camera centre in the body frame (m)
R_BC = Rotation.from_euler("xyz", [-95.0, 3.0, -88.0], degrees=True)  # camera axes in body
OFFSET = 0.25  # s: truth stamps + OFFSET = frame stamps


def transform_text() -> str:
    x, y, z, w = R_BC.as_quat()
    return " ".join(f"{v:.17g}" for v in (*T_BC, w, x, y, z))


def body_poses(frames: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps, body positions and body quaternions (x, y, z, w) whose camera is the sample
    truth: T_W_body = T_W_camera * inverse(T_body_camera), computed here with scipy."""
    truth = pd.read_csv(SAMPLE / "orbit_truth.csv").set_index("frame").loc[frames]
    R_wc = Rotation.from_quat(truth[["qx", "qy", "qz", "qw"]].to_numpy())
    R_wb = R_wc * R_BC.inv()
    c_wb = truth[["x_m", "y_m", "z_m"]].to_numpy() - R_wb.apply(T_BC)
    stamps = T0 + np.array(frames) / 30 - OFFSET
    return stamps, c_wb, R_wb.as_quat()


def report(poses, truth, tmp_path, name, *opts) -> tuple[pd.DataFrame, dict]:
    out, summary = tmp_path / f"{name}.csv", tmp_path / f"{name}.yaml"
    path = SAMPLE / "desired_path.yaml"
    code, err = mirage("report", poses, "--path", path, "--truth", truth, *opts, "-o", out,
                       "--summary", summary)  # fmt: skip
    assert code == 0, err
    return pd.read_csv(out), yaml.safe_load(summary.read_text())


def test_tum_and_bag_truth_with_offset_and_transform_match_the_pose_csv_truth(tracked, tmp_path):
    poses = tracked["ros1"]  # frames 0..N-1, header stamps T0 + i / 30
    ref, ref_summary = report(poses, SAMPLE / "orbit_truth.csv", tmp_path, "ref")
    assert ref_summary["truth_frames"] == N and ref_summary["frames_without_truth"] == 0
    cols = ["position_error_m", "rotation_error_deg"]
    assert ref[cols].notna().all().all()

    # TUM body poses, frame 3 missing: that frame gets no truth error and is counted
    frames = [i for i in range(N) if i != 3]
    t, c, q = body_poses(frames)
    tum = tmp_path / "mocap.txt"
    np.savetxt(tum, np.column_stack([t, c, q]), fmt="%.17g", header="t x y z qx qy qz qw")
    got, summary = report(
        poses, tum, tmp_path, "tum", "--t-offset", OFFSET, "--truth-transform", transform_text()
    )
    keep = np.array(frames)
    np.testing.assert_allclose(got.loc[keep, cols], ref.loc[keep, cols], rtol=0, atol=1e-9)
    assert got.loc[3, cols].isna().all()
    assert summary["truth_frames"] == N - 1 and summary["frames_without_truth"] == 1
    assert summary["errors"]["position_error_m"]["n"] == N - 1

    # without the offset nothing is within --t-max-diff: one line saying so
    code, err = mirage("report", poses, "--path", SAMPLE / "desired_path.yaml", "--truth", tum)
    assert_error(code, err, "do not overlap the pose times within 10 ms")

    # a bag pose topic (the transform from a file); two pose topics need --truth-topic
    t, c, q = body_poses(list(range(N)))
    bag = bag_path(tmp_path, "mocap", "mcap")
    with BagWriter(bag, "mcap") as w:
        for i in range(N):
            w.pose("/mocap/pose", t[i], c[i], q[i, [3, 0, 1, 2]])
            w.pose("/other/pose", t[i], [0, 0, 0], [1, 0, 0, 0])
    code, err = mirage("report", poses, "--path", SAMPLE / "desired_path.yaml", "--truth", bag)
    assert_error(code, err, "several pose topics in")
    tfile = tmp_path / "T_body_camera.txt"
    tfile.write_text("# x y z qw qx qy qz\n" + transform_text() + "\n")
    got, summary = report(
        poses, bag, tmp_path, "bag", "--truth-topic", "/mocap/pose", "--t-offset", OFFSET,
        "--truth-transform", tfile,
    )  # fmt: skip
    np.testing.assert_allclose(got[cols], ref[cols], rtol=0, atol=1e-9)
    assert summary["frames_without_truth"] == 0


def test_every_pose_message_type_reads_as_the_same_table(tmp_path):
    t, c, q = body_poses(list(range(N)))
    path = bag_path(tmp_path, "types", "ros1")
    with BagWriter(path, "ros1") as w:
        m = w.msg
        for i in range(N):
            point = m("geometry_msgs/msg/Point", x=c[i, 0], y=c[i, 1], z=c[i, 2])
            vec = m("geometry_msgs/msg/Vector3", x=c[i, 0], y=c[i, 1], z=c[i, 2])
            quat = m("geometry_msgs/msg/Quaternion", x=q[i, 0], y=q[i, 1], z=q[i, 2], w=q[i, 3])
            pose = m("geometry_msgs/msg/Pose", position=point, orientation=quat)
            cov = m("geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=np.zeros(36))
            zero = m("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
            twist = m(
                "geometry_msgs/msg/TwistWithCovariance",
                twist=m("geometry_msgs/msg/Twist", linear=zero, angular=zero),
                covariance=np.zeros(36),
            )
            h = w.header(t[i])
            msgs = {
                "geometry_msgs/msg/PoseStamped": m(
                    "geometry_msgs/msg/PoseStamped", header=h, pose=pose
                ),
                "geometry_msgs/msg/PoseWithCovarianceStamped": m(
                    "geometry_msgs/msg/PoseWithCovarianceStamped", header=h, pose=cov
                ),
                "nav_msgs/msg/Odometry": m(
                    "nav_msgs/msg/Odometry", header=h, child_frame_id="body", pose=cov, twist=twist
                ),
                "geometry_msgs/msg/TransformStamped": m(
                    "geometry_msgs/msg/TransformStamped",
                    header=h,
                    child_frame_id="body",
                    transform=m("geometry_msgs/msg/Transform", translation=vec, rotation=quat),
                ),
            }
            for typ, msg in msgs.items():
                w.write("/" + typ.split("/")[-1], typ, t[i], msg)
    tables = [read_poses(path, "/" + typ.split("/")[-1]) for typ in bags_module.POSE_TYPES]
    for df in tables:
        np.testing.assert_allclose(df["time_s"], t, rtol=0, atol=1e-6)
        np.testing.assert_allclose(df[["x_m", "y_m", "z_m"]], c, rtol=0, atol=1e-12)
        np.testing.assert_allclose(df[["qx", "qy", "qz", "qw"]], q, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "opts,message",
    [
        (["--truth-transform", "1 2 3"], "expected 7 numbers 'x y z qw qx qy qz'"),
        (["--truth-transform", "0 0 0 2 0 0 0"], "the quaternion qw qx qy qz has norm 2"),
        (["--t-offset", "0.5"], "--t-offset applies to truth matched by time"),
        (["--truth-topic", "/mocap"], "--truth-topic /mocap picks a pose topic of a ROS bag"),
    ],
)
def test_bad_truth_options_are_one_line_errors(opts, message, tmp_path):
    poses = SAMPLE / "orbit_truth.csv"
    code, err = mirage("report", poses, "--path", SAMPLE / "desired_path.yaml", "--truth",
                       poses, *opts, "-o", tmp_path / "r.csv")  # fmt: skip
    assert_error(code, err, message)
    assert not (tmp_path / "r.csv").exists()


def test_frames_with_one_header_stamp_warn(orbit, tmp_path, caplog):
    """Two image messages with the same header stamp (a driver that stamps at the trigger,
    a re-recorded bag): their rows share a time_s, which time matching cannot tell apart,
    so reading them warns once, naming both messages (issue 30)."""
    path = bag_path(tmp_path, "dup", "ros1")
    with BagWriter(path, "ros1") as w:
        for i, t in enumerate([0.0, 1 / 30, 1 / 30, 3 / 30]):
            w.image(IMG, T0 + t, orbit[i], "bgr8")
    with caplog.at_level("WARNING", logger="mirage"):
        frames = list(FrameSource([path]).frames(0, None, 1))
    assert len(frames) == 4
    warned = [r.getMessage() for r in caplog.records if "same header stamp" in r.getMessage()]
    assert len(warned) == 1 and "messages 1 and 2" in warned[0], caplog.text
