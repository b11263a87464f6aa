"""ROS bags: image frames, the camera from camera_info, and pose topics for truth.

Read with rosbags' `AnyReader` (pure Python, no ROS install): ROS 1 `.bag` files and ROS 2
bags, a folder holding `metadata.yaml` (sqlite3 or mcap storage) or the bare `.db3` /
`.mcap` file. Bags carry their message definitions; one that does not (early ROS 2
sqlite3 bags) is read with the Humble typestore. Every failure a user can cause (a damaged
bag, no or several candidate topics, an unknown image encoding) is an InputError naming
the bag and topic; a single undecodable message is a damaged frame (image None), as a
damaged stretch of a video is.
"""

from __future__ import annotations

import contextlib
import sqlite3
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .camera import LENS_MODELS, Camera
from .errors import InputError

if TYPE_CHECKING:
    import pandas as pd

BAG_SUFFIXES = frozenset({".bag", ".db3", ".mcap"})
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED)
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"


def _pose_of(m) -> tuple:
    return m.position, m.orientation


# pose message type -> (position, orientation) of a message: the body's pose in the world
POSE_TYPES: dict[str, Callable] = {
    "geometry_msgs/msg/PoseStamped": lambda m: _pose_of(m.pose),
    "geometry_msgs/msg/PoseWithCovarianceStamped": lambda m: _pose_of(m.pose.pose),
    "nav_msgs/msg/Odometry": lambda m: _pose_of(m.pose.pose),
    "geometry_msgs/msg/TransformStamped": lambda m: (m.transform.translation, m.transform.rotation),
}


@dataclass(frozen=True)
class Encoding:
    """How a raw `sensor_msgs/Image` encoding is laid out and turned into BGR / gray."""

    channels: int
    dtype: str  # numpy dtype of one channel (byte order from is_bigendian)
    to_bgr: int | None  # cv2.cvtColor code; None: already BGR (or gray)
    to_gray: int | None  # None: already gray


# OpenCV's COLOR_BayerRGGB2* names (aliases of the older BayerBG2*) follow the ROS / sensor
# naming of the top-left 2x2 tile, the same pairing cv_bridge uses.
ENCODINGS: dict[str, Encoding] = {
    "mono8": Encoding(1, "u1", cv2.COLOR_GRAY2BGR, None),
    "8UC1": Encoding(1, "u1", cv2.COLOR_GRAY2BGR, None),
    "mono16": Encoding(1, "u2", cv2.COLOR_GRAY2BGR, None),
    "16UC1": Encoding(1, "u2", cv2.COLOR_GRAY2BGR, None),
    "bgr8": Encoding(3, "u1", None, cv2.COLOR_BGR2GRAY),
    "8UC3": Encoding(3, "u1", None, cv2.COLOR_BGR2GRAY),
    "rgb8": Encoding(3, "u1", cv2.COLOR_RGB2BGR, cv2.COLOR_RGB2GRAY),
    "bgra8": Encoding(4, "u1", cv2.COLOR_BGRA2BGR, cv2.COLOR_BGRA2GRAY),
    "rgba8": Encoding(4, "u1", cv2.COLOR_RGBA2BGR, cv2.COLOR_RGBA2GRAY),
    "bayer_rggb8": Encoding(1, "u1", cv2.COLOR_BayerRGGB2BGR, cv2.COLOR_BayerRGGB2GRAY),
    "bayer_bggr8": Encoding(1, "u1", cv2.COLOR_BayerBGGR2BGR, cv2.COLOR_BayerBGGR2GRAY),
    "bayer_gbrg8": Encoding(1, "u1", cv2.COLOR_BayerGBRG2BGR, cv2.COLOR_BayerGBRG2GRAY),
    "bayer_grbg8": Encoding(1, "u1", cv2.COLOR_BayerGRBG2BGR, cv2.COLOR_BayerGRBG2GRAY),
}


@dataclass(frozen=True)
class BagRef:
    """A bag and the image topic to read from it (None: its only image topic). It stands
    where a video path stands (`name`, `str()`), so every reader of videos takes it."""

    path: Path
    topic: str | None = None

    @property
    def name(self) -> str:
        return self.path.name

    def __str__(self) -> str:
        return str(self.path)

    def __fspath__(self) -> str:
        return str(self.path)


def is_bag_path(p: Path) -> bool:
    """A ROS 1 `.bag` file, a ROS 2 bag folder (holding metadata.yaml), or a `.db3` / `.mcap`
    storage file."""
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.is_file() and p.suffix.lower() in BAG_SUFFIXES


# What a damaged or foreign file makes rosbags raise (beside its own error classes).
_READ_ERRORS: tuple[type[BaseException], ...] = (
    OSError,
    sqlite3.Error,
    struct.error,
    ValueError,
    KeyError,
    IndexError,
    EOFError,
)


def _rosbags_errors() -> tuple[type[BaseException], ...]:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error

    return (AnyReaderError, Reader1Error, Reader2Error, *_READ_ERRORS)


@contextlib.contextmanager
def open_bag(path: Path):
    """An open `AnyReader`; anything rosbags raises on a damaged bag is one InputError."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    errors = _rosbags_errors()
    try:
        reader = AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except errors as e:
        raise InputError(f"cannot read ROS bag {path}: {_why(e)}") from None
    try:
        yield reader
    except errors as e:
        raise InputError(f"cannot read ROS bag {path}: {_why(e)}") from None
    finally:
        with contextlib.suppress(*errors):
            reader.close()


def _why(e: BaseException) -> str:
    s = str(e).strip().splitlines()
    return s[0] if s else type(e).__name__


def topics(reader) -> dict[str, str]:
    """Topic -> message type of an open bag (a topic of mixed types is left out)."""
    return {name: info.msgtype for name, info in reader.topics.items() if info.msgtype}


def pick_topic(path, found: dict[str, str], kinds, chosen: str | None, what: str, flag: str) -> str:
    """The topic to read: `chosen` (which must be of one of `kinds`), else the bag's only
    topic of those kinds; none or several is an error that lists them."""
    names = sorted(t for t, typ in found.items() if typ in kinds)
    if chosen is not None:
        if chosen in names:
            return chosen
        if chosen in found:
            raise InputError(
                f"topic {chosen} in {path} is a {found[chosen]}; "
                f"{what} topics: {', '.join(names) or 'none'}"
            )
        raise InputError(
            f"no topic {chosen} in {path} ({what} topics: {', '.join(names) or 'none'})"
        )
    if not names:
        raise InputError(f"no {what} topics in {path}")
    if len(names) > 1:
        raise InputError(
            f"several {what} topics in {path}: {', '.join(names)}; pick one with {flag}"
        )
    return names[0]


def stamp_s(msg, bag_ns: int) -> float:
    """The header stamp in seconds; the bag's receive time when the stamp is unset (0)."""
    st = msg.header.stamp
    ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
    return (ns if ns else bag_ns) / 1e9


# --------------------------------------------------------------------------------------
# images
# --------------------------------------------------------------------------------------
def check_encoding(msg, msgtype: str, topic: str) -> None:
    """Refuse an image the decoder does not know, naming the topic and the encoding."""
    if msgtype == COMPRESSED:
        fmt = str(msg.format).strip()
        if "compresseddepth" in fmt.lower().replace(" ", ""):
            raise InputError(
                f"topic {topic}: compressed image format {fmt!r} is not supported "
                "(depth images; use a jpeg or png image topic)"
            )
        return
    if msg.encoding not in ENCODINGS:
        raise InputError(
            f"topic {topic}: image encoding {msg.encoding!r} is not supported "
            f"(supported: {', '.join(ENCODINGS)})"
        )


def decode_image(msg, msgtype: str, topic: str, gray: bool = False) -> np.ndarray | None:
    """A `sensor_msgs/Image` or `CompressedImage` as an 8-bit BGR (or gray) image; None when
    the data do not hold the image (truncated, corrupt); an unknown encoding is an error."""
    check_encoding(msg, msgtype, topic)
    data = np.asarray(msg.data, dtype=np.uint8)
    if msgtype == COMPRESSED:
        try:
            img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
        except cv2.error:
            img = None
        return img if img is not None and img.size else None
    enc = ENCODINGS[msg.encoding]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(enc.dtype).itemsize
    row = w * enc.channels * item
    if h <= 0 or w <= 0 or step < row or data.size < h * step:
        return None
    px = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, :row])
    if item > 1:
        order = ">" if msg.is_bigendian else "<"
        px = px.view(order + enc.dtype).astype(np.uint16)
        px = (px // 257).astype(np.uint8)  # the full 16-bit range onto 8 bits
    img = px.reshape(h, w, enc.channels) if enc.channels > 1 else px.reshape(h, w)
    code = enc.to_gray if gray else enc.to_bgr
    return img if code is None else cv2.cvtColor(img, code)


@dataclass(frozen=True)
class ImageTopic:
    """An image topic of a bag: its messages, the first image's size and the mean rate."""

    path: Path
    topic: str
    msgtype: str
    count: int
    size: tuple[int, int]  # (width, height)
    fps: float  # messages per second over the bag's duration (for --start 4s and overlays)


def image_topic(ref: BagRef) -> ImageTopic:
    """Select the image topic (`ref.topic` or the only one) and check its first frame: its
    encoding must be known and it must decode (its size is the sequence's)."""
    with open_bag(ref.path) as r:
        found = topics(r)
        topic = pick_topic(ref.path, found, IMAGE_TYPES, ref.topic, "image", "--topic")
        info = r.topics[topic]
        cons = [c for c in r.connections if c.topic == topic]
        first = None
        for con, _, raw in r.messages(connections=cons):
            msg = r.deserialize(raw, con.msgtype)
            img = decode_image(msg, con.msgtype, topic, gray=True)
            if img is not None:
                first = img
                break
        if first is None:
            raise InputError(f"no image of topic {topic} in {ref.path} can be decoded")
        span = (r.end_time - r.start_time) / 1e9
        count = int(info.msgcount)
    fps = (count - 1) / span if count > 1 and span > 0 else 0.0
    return ImageTopic(Path(ref.path), topic, info.msgtype, count, first.shape[1::-1], fps)


def image_frames(
    it: ImageTopic, start: int = 0, end: int | None = None, every: int = 1, gray: bool = False
) -> Iterator[tuple[int, float, np.ndarray | None]]:
    """(index in the topic, header stamp s, image or None) for messages start, start +
    every, ... before `end`; the others are skipped without being decoded."""
    from rosbags.highlevel import AnyReaderError

    with open_bag(it.path) as r:
        cons = [c for c in r.connections if c.topic == it.topic]
        for i, (con, t_ns, raw) in enumerate(r.messages(connections=cons)):
            if end is not None and i >= end:
                break
            if i < start or (i - start) % every:
                continue
            try:
                msg = r.deserialize(raw, con.msgtype)
            except AnyReaderError:  # a damaged message: a damaged frame
                yield i, t_ns / 1e9, None
                continue
            yield i, stamp_s(msg, t_ns), decode_image(msg, con.msgtype, it.topic, gray)


# --------------------------------------------------------------------------------------
# camera_info
# --------------------------------------------------------------------------------------
def camera_info_topic(found: dict[str, str], image_topic: str) -> str | None:
    """The CameraInfo topic of an image topic: the one in its nearest namespace
    (/cam/image_raw/compressed -> /cam/image_raw/camera_info, /cam/camera_info), else the
    bag's only one; None when there is none or no way to choose."""
    infos = {t for t, typ in found.items() if typ == CAMERA_INFO}
    parts = image_topic.rstrip("/").split("/")
    for k in range(len(parts) - 1, 0, -1):
        cand = "/".join(parts[:k]) + "/camera_info"
        if cand in infos:
            return cand
    return next(iter(infos)) if len(infos) == 1 else None


def camera_from_info(msg, where: str, size: tuple[int, int] | None = None) -> Camera | None:
    """A Camera from a `sensor_msgs/CameraInfo` (ROS 1 K/D or ROS 2 k/d spelling); None for
    an uncalibrated one (K all zero). ROS plumb_bob and rational_polynomial coefficients
    are OpenCV's order; equidistant is OpenCV's fisheye model. A message without a size
    (0x0, some drivers) takes `size`, the images' (width, height)."""
    K = np.asarray(msg.k if hasattr(msg, "k") else msg.K, float)
    D = np.asarray(msg.d if hasattr(msg, "d") else msg.D, float)
    if K.size == 9 and not np.isfinite(K).all():
        raise InputError(
            f"{where}: the camera matrix K holds NaN or infinity ({K.tolist()}); give the "
            "camera with --camera FILE"
        )
    if K.size != 9 or not K[0] > 0:
        return None
    name = str(msg.distortion_model).strip().lower() or "plumb_bob"
    model = LENS_MODELS.get(name)
    if model is None:
        raise InputError(
            f"{where}: distortion_model {msg.distortion_model!r} is not supported "
            f"(use one of {', '.join(LENS_MODELS)})"
        )
    w, h = int(msg.width), int(msg.height)
    if (w, h) == (0, 0) and size is not None:
        w, h = size
    try:
        return Camera(K.reshape(3, 3), D, w, h, model=model)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None


def bag_camera(it: ImageTopic) -> Camera | None:
    """The camera of an image topic from its camera_info (first message), or None."""
    with open_bag(it.path) as r:
        topic = camera_info_topic(topics(r), it.topic)
        if topic is None:
            return None
        cons = [c for c in r.connections if c.topic == topic]
        for con, _, raw in r.messages(connections=cons):
            msg = r.deserialize(raw, con.msgtype)
            return camera_from_info(msg, f"{topic} in {it.path}", it.size)
    return None


# --------------------------------------------------------------------------------------
# poses (motion-capture truth)
# --------------------------------------------------------------------------------------
def read_poses(path, topic: str | None = None) -> pd.DataFrame:
    """A pose topic (PoseStamped, PoseWithCovarianceStamped, Odometry, TransformStamped) as
    the table `trajectory.read_tum` returns: frames numbered, time_s = header stamps."""
    from . import validate
    from .trajectory import pose_table

    with open_bag(Path(path)) as r:
        found = topics(r)
        topic = pick_topic(path, found, POSE_TYPES, topic, "pose", "--truth-topic")
        get = POSE_TYPES[found[topic]]
        cons = [c for c in r.connections if c.topic == topic]
        rows = []
        for con, t_ns, raw in r.messages(connections=cons):
            msg = r.deserialize(raw, con.msgtype)
            p, q = get(msg)
            rows.append((stamp_s(msg, t_ns), p.x, p.y, p.z, q.w, q.x, q.y, q.z))
    if not rows:
        raise InputError(f"topic {topic} in {path} has no messages")
    a = np.array(rows, float)
    what = f"topic {topic} of bag"
    if not np.isfinite(a).all():
        raise InputError(f"{what} {path}: a pose holds NaN or inf")
    validate.unique_times(a[:, 0], path, what)
    q = validate.unit_quaternion_rows(a[:, 4:8], path, what)
    return pose_table(range(len(a)), a[:, 0], a[:, 1:4], q)
