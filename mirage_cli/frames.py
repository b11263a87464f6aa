"""Frames from a video, a ROS bag, image files, a folder or a glob: the one reader of every
command.

INPUT arguments (files, folders, globs, one video or one ROS bag) resolve to a naturally
sorted image list, a video or a bag (`bags.BagRef`, which stands where a video path does);
images are read with a clear error instead of OpenCV's silent None; and `FrameSource`
yields timed frames of any kind, reporting a damaged stretch of a video (or a damaged bag
message) frame by frame (image None) and decoding on after it. A tracker that needs only
gray gets a video's gray straight from the decoder's luma plane when the first frame
proves it the same gray (`luma_range`), skipping FFmpeg's conversion to BGR.
"""

from __future__ import annotations

import contextlib
import glob
import logging
import os
import queue
import re
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from . import bags
from .bags import BagRef, is_bag_path
from .camera import Camera
from .errors import InputError
from .features import to_gray

log = logging.getLogger("mirage")

# FFmpeg writes its own complaints ("moov atom not found") straight to stderr, next to
# our one-line error; silence them (read at the first video open; env can override).
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

IMAGE_EXTS = frozenset(
    {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pnm", ".jp2"}
)
VIDEO_EXTS = frozenset(
    {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".mts"}
)
_GLOB_CHARS = re.compile(r"[*?\[]")

# Gray from the luma plane: the first frame's luma (range-expanded) must be BGR2GRAY of its
# BGR within LUMA_TOLERANCE grey levels on average, and the other range LUMA_MARGIN worse
# (else, e.g. a uniform frame, the range is unknown and the video takes the BGR path:
# FFmpeg's BGR of a uniform full-range grey is up to a level darker, as a limited one's).
LUMA_TOLERANCE = 2.0
LUMA_MARGIN = 1.5
# video range (Y 16-235) to full range (0-255): (Y - 16) * 255 / 219, truncated as FFmpeg's
# conversion to BGR does for grey (on the sample orbit within 1 of BGR2GRAY on 99.9% of the
# pixels, mean 0.84; rounded: 59%, mean 1.33)
_VIDEO_RANGE_LUT = np.clip(np.floor((np.arange(256) - 16) * 255 / 219), 0, 255).astype(np.uint8)


@dataclass
class MediaInput:
    """What INPUT arguments resolved to: a sorted list of images, or one video (or bag)."""

    images: list[Path] = field(default_factory=list)
    video: Path | BagRef | None = None

    @property
    def is_video(self) -> bool:
        """A video or a bag: one stream of numbered frames."""
        return self.video is not None

    @property
    def is_bag(self) -> bool:
        return isinstance(self.video, BagRef)


def natural_key(path: Path) -> list:
    """Sort key so that img2 comes before img10 (people number files without padding)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", str(path))]


def is_image_path(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_EXTS


def is_video_path(path: Path) -> bool:
    """A video by extension, or any other file that OpenCV can open as a video."""
    if path.suffix.lower() in VIDEO_EXTS:
        return True
    if path.suffix.lower() in IMAGE_EXTS or not path.is_file():
        return False
    cap = _open_capture(path, strict=False)
    if cap is None:
        return False
    ok = cap.isOpened() and cap.get(cv2.CAP_PROP_FRAME_COUNT) > 1
    cap.release()
    return bool(ok)


def with_topic(inputs: Iterable, topic: str | None) -> list:
    """INPUT with `--topic` attached to its bag; --topic without a bag is an error (it would
    silently do nothing)."""
    inputs = list(inputs)
    if topic is None:
        return inputs
    out = [
        BagRef(Path(i).expanduser(), topic)
        if not isinstance(i, BagRef) and is_bag_path(Path(i).expanduser())
        else i
        for i in inputs
    ]
    if not any(isinstance(i, BagRef) for i in out):
        raise InputError(
            f"--topic {topic} selects the image topic of a ROS bag, but the input is not one "
            "(a .bag file, a ROS 2 bag folder with metadata.yaml, a .db3 or .mcap file)"
        )
    return [BagRef(i.path, topic) if isinstance(i, BagRef) else i for i in out]


def resolve_inputs(inputs: Iterable, what: str = "images") -> MediaInput:
    """Expand files, folders and globs into sorted image paths, or detect one video or bag."""
    inputs = [i if isinstance(i, BagRef) else str(i) for i in inputs]
    if not inputs:
        raise InputError(f"no input given; pass {what} (files, a folder or a glob) or a video")
    images: list[Path] = []
    videos: list[Path | BagRef] = []
    for arg in inputs:
        if isinstance(arg, BagRef):
            videos.append(arg)
            continue
        p = Path(arg).expanduser()
        if is_bag_path(p):
            videos.append(BagRef(p))
        elif p.is_dir():
            images += [f for f in p.iterdir() if f.is_file() and is_image_path(f)]
        elif p.is_file():
            if is_image_path(p):
                images.append(p)
            elif is_video_path(p):
                videos.append(p)
            else:
                raise InputError(f"{p} is neither an image ({_exts(IMAGE_EXTS)}) nor a video")
        elif _GLOB_CHARS.search(arg):
            hits = [Path(h) for h in glob.glob(str(p), recursive=True)]
            images += [h for h in hits if h.is_file() and is_image_path(h)]
            videos += [h for h in hits if h.is_file() and h.suffix.lower() in VIDEO_EXTS]
            videos += [BagRef(h) for h in hits if is_bag_path(h)]
        else:
            raise InputError(f"input {p} not found")
    if videos:
        if len(videos) > 1 or images:
            raise InputError(
                "give either images or a single video (or bag), not both / several videos"
            )
        return MediaInput(video=videos[0])
    images = sorted(set(images), key=natural_key)
    if not images:
        raise InputError(f"no images found in {', '.join(inputs)} (looked for {_exts(IMAGE_EXTS)})")
    return MediaInput(images=images)


def read_image(path: str | Path, gray: bool = False) -> np.ndarray:
    """Read an image or raise InputError (cv2.imread returns None on corrupt files)."""
    p = Path(path)
    try:
        data = np.fromfile(p, dtype=np.uint8)  # also handles non-ASCII paths
    except OSError as e:
        raise InputError(f"cannot read image {p}: {e.strerror or e}") from None
    try:
        img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
    except cv2.error:
        img = None
    if img is None or img.size == 0:
        raise InputError(f"cannot decode image {p} (corrupt or unsupported format)")
    return img


def luma_range(luma: np.ndarray | None, bgr: np.ndarray | None) -> str | None:
    """Whether the decoder's plane 0 of a frame (`luma`, read with OpenCV's conversion to
    BGR off) is that frame's gray: "limited" (video range 16-235, expanded by
    `expand_luma`; H.264, MPEG-4 and most cameras), "full" (0-255, as is: MJPEG's yuvj,
    gray video) or None: not this frame's gray (packed RGB or BGRA, 10-bit, another size)
    or a frame that cannot tell the ranges apart (a uniform grey)."""
    if luma is None or bgr is None or bgr.ndim != 3 or bgr.shape[2] != 3:
        return None
    if luma.dtype != np.uint8 or luma.shape != bgr.shape[:2]:
        return None
    ref = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.int16)
    err = {
        r: float(np.abs(expand_luma(luma, r).astype(np.int16) - ref).mean())
        for r in ("limited", "full")
    }
    best, other = sorted(err, key=err.get)
    if err[best] > LUMA_TOLERANCE or err[other] - err[best] < LUMA_MARGIN:
        return None
    return best


def expand_luma(luma: np.ndarray, luma_range: str) -> np.ndarray:
    """A luma plane as full-range gray (what BGR2GRAY of the decoded colour gives)."""
    return cv2.LUT(luma, _VIDEO_RANGE_LUT) if luma_range == "limited" else luma


class Frame(NamedTuple):
    """One frame of a source: `id` is what the pose CSV's `frame` column holds."""

    index: int  # position in the video / in the sorted image list
    id: int | str  # video frame number, or the image file name
    time_s: float  # seconds; NaN when the source has no times
    image: np.ndarray | None  # None when the frame cannot be decoded
    colour: np.ndarray | None = None  # with `frames(colour=True)`: the BGR `image` was grayed from


# Image names that are times: seconds with a decimal point (TUM: 1305031102.175304.png), or
# integers of NS_DIGITS or more digits, nanoseconds (EuRoC, ROS bag exports:
# 1403636579763555584.png, 000123456789.png). Shorter integers (000042.png) count frames.
_NUMBER = re.compile(r"^(\d+)(\.\d+)?$")
NS_DIGITS = 12


def name_times(paths: list[Path]) -> np.ndarray | None:
    """Times in seconds read from the file names, or None when they are not timestamps."""
    times = []
    for p in paths:
        m = _NUMBER.match(p.stem)
        if m is None or (m.group(2) is None and len(m.group(1)) < NS_DIGITS):
            return None
        times.append(float(p.stem) if m.group(2) else int(m.group(1)) / 1e9)
    t = np.array(times)
    if len(t) and len(np.unique(t)) < len(t):  # two images at one time: not a clock
        _, first = np.unique(t, return_index=True)
        dup = sorted(set(range(len(t))) - set(first.tolist()))[0]
        twin = int(np.flatnonzero(t == t[dup])[0])
        _warn(
            f"images {paths[twin].name} and {paths[dup].name} have names giving the same "
            f"time ({t[dup]:g} s): time_s is left empty for every frame; rename them or "
            "give --fps"
        )
        return None
    return t


def _warn(text: str) -> None:
    from .logs import log

    log.warning(text)


class FrameSource:
    """Frames of one video, one bag's image topic or an image sequence, with times, in order.

    Image sequences are timed by `fps` (time = index / fps) when given, else by their names
    when those are timestamps (`name_times`; the images are then ordered by time), else
    their times are NaN. A video is timed by its stream, a bag by its header stamps (the
    frame is the message's index in the topic).
    """

    def __init__(self, inputs: Iterable, what: str = "a video or images", fps=None):
        media = resolve_inputs(inputs, what)
        self.video, self.images = media.video, media.images
        self.times: np.ndarray | None = None
        self._size: tuple[int, int] | None = None
        self._luma: str | None | bool = False  # False: not checked yet (`luma_mode`)
        self.bag: bags.ImageTopic | None = None
        if media.is_bag:
            if fps:
                raise InputError("--fps is for image sequences; a ROS bag has header stamps")
            self.bag = bags.image_topic(self.video)
            self.fps, self.count, self._size = self.bag.fps, self.bag.count, self.bag.size
            return
        if self.video is not None:
            if fps:
                raise InputError("--fps is for image sequences; a video has its own frame rate")
            cap = _open_capture(self.video)
            try:
                self.fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0) or 30.0
                self.count = max(0, int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0))
                self._size = (
                    int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                    int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                )
            finally:
                cap.release()
            return
        self.count = len(self.images)
        self.fps = float(fps or 0.0)
        if fps:
            self.times = np.arange(self.count) / self.fps
        else:
            stamps = name_times(self.images)
            if stamps is not None:
                order = np.argsort(stamps, kind="stable")
                self.images = [self.images[i] for i in order]
                self.times = stamps[order]
                dt = np.diff(self.times)
                self.fps = 1.0 / float(np.median(dt)) if len(dt) else 0.0

    @property
    def is_video(self) -> bool:
        return self.video is not None

    def camera(self) -> Camera | None:
        """The camera a bag's camera_info gives its image topic; None for other sources."""
        return bags.bag_camera(self.bag) if self.bag is not None else None

    @property
    def size(self) -> tuple[int, int]:
        """(width, height): the video's, or the first decodable image's."""
        if self._size is None:
            for p in self.images:
                try:
                    img = read_image(p, gray=True)
                except InputError:
                    continue
                self._size = (img.shape[1], img.shape[0])
                break
            else:
                raise InputError(f"none of the {len(self.images)} images could be read")
        return self._size

    def frames(
        self,
        start: int = 0,
        end: int | None = None,
        every: int = 1,
        gray: bool = False,
        luma: bool = False,
        colour: bool = False,
    ) -> Iterator[Frame]:
        """Frames start, start + every, ... before `end`; undecodable ones with image None.

        `gray`: gray images (read as gray). `luma`: gray images as the tracker's gray
        (BGR2GRAY of the colour frame), a video's straight from its luma plane when its
        first frame proves that the same gray (`luma_mode`; within a grey level or two).
        `colour` (with `luma`): each frame's colour image too, as `Frame.colour`, for the
        overlays: the gray is the same as without it (a second decoder of the video gives
        the colour), so drawing never changes what is tracked.
        """
        if every < 1:
            raise InputError(f"frame step must be >= 1, got {every}")
        if luma and colour:
            if self.bag is None and self.video is not None and self.luma_mode() is not None:
                gray_it = self._video_frames(start, end, every, True, True)
                yield from _with_colour(gray_it, self._video_frames(start, end, every, False))
            else:
                yield from gray_frames(self.frames(start, end, every), keep_colour=True)
            return
        if luma and (self.bag is not None or self.video is None):
            yield from gray_frames(self.frames(start, end, every))
            return
        if self.bag is not None:
            last, warned = None, False  # (index, stamp) of the previous message
            for i, t, img in bags.image_frames(self.bag, start, end, every, gray):
                if last is not None and t == last[1] and not warned:
                    warned = True
                    _warn(
                        f"{self.bag.topic} in {self.bag.path}: messages {last[0]} and {i} have "
                        f"the same header stamp {t:.6f} s; their rows share one time_s, so "
                        "matching them to truth by time (TUM, report --truth) cannot tell "
                        "them apart"
                    )
                last = (i, t)
                yield Frame(i, i, t, img)
            return
        if self.video is not None:
            yield from self._video_frames(start, end, every, gray or luma, luma)
            return
        for i, p in enumerate(self.images):
            if i < start or (end is not None and i >= end) or (i - start) % every:
                continue
            try:
                img = read_image(p, gray=gray)
            except InputError:
                img = None
            t = float(self.times[i]) if self.times is not None else float("nan")
            yield Frame(i, p.name, t, img)

    def luma_mode(self) -> str | None:
        """The range of the video's luma plane when its first frame proves the plane its
        gray (`luma_range`), else None: checked once, at the first gray read."""
        if self._luma is False:
            self._luma = _luma_mode(self.video)
            if self._luma is None:
                log.debug(f"{self.video}: gray by BGR2GRAY (the luma plane is not its gray)")
        return self._luma

    def _video_frames(self, start, end, every, gray, luma=False) -> Iterator[Frame]:
        """Decode in order; a damaged stretch is reported frame by frame as undecodable and
        decoding resumes after it (FFmpeg cannot resync by itself, so reopen and seek).
        `luma`: gray from the luma plane when `luma_mode` allows, not through BGR."""

        def wanted(i):
            return i >= start and (i - start) % every == 0 and (end is None or i < end)

        mode = self.luma_mode() if luma else None
        cap, i = _open_capture(self.video, luma=mode is not None), 0
        try:
            if start > 0:
                _seek(cap, start)
                i = int(cap.get(cv2.CAP_PROP_POS_FRAMES))
            while end is None or i < end:
                try:
                    ok = cap.grab()
                except cv2.error:
                    ok = False
                if not ok:
                    if not self.count or i >= self.count:
                        break  # the real end of the video
                    if wanted(i):
                        yield Frame(i, i, i / self.fps, None)
                    i += 1
                    cap.release()
                    cap = _open_capture(self.video, luma=mode is not None)
                    _seek(cap, i)
                    while i < self.count and int(cap.get(cv2.CAP_PROP_POS_FRAMES)) != i:
                        if wanted(i):
                            yield Frame(i, i, i / self.fps, None)
                        i += 1
                        _seek(cap, i)
                    continue
                if wanted(i):
                    frame = _retrieve(cap, gray, mode)
                    ms = cap.get(cv2.CAP_PROP_POS_MSEC)
                    t = ms / 1000.0 if ms and ms > 0 else i / self.fps
                    yield Frame(i, i, t, frame)
                i += 1
        finally:
            cap.release()


def gray_frames(frames: Iterator[Frame], keep_colour: bool = False) -> Iterator[Frame]:
    """`frames` with colour images turned gray (`keep_colour`: the colour kept as
    `Frame.colour`): done where the frames are decoded (a thread of `prefetch`'s), not on
    the tracking thread (0.24 s of the sample orbit's 540 frames)."""
    try:
        for f in frames:
            if f.image is not None and f.image.ndim == 3:
                f = f._replace(image=to_gray(f.image), colour=f.image if keep_colour else None)
            yield f
    finally:
        _close(frames)


def _close(frames) -> None:
    close = getattr(frames, "close", None)
    if close is not None:
        close()


def _with_colour(gray: Iterator[Frame], colour: Iterator[Frame]) -> Iterator[Frame]:
    """`gray`'s frames, each with the colour image of the same index from `colour` (None
    when that decoder did not give it: a damaged stretch can end otherwise in each)."""
    try:
        c = next(colour, None)
        for g in gray:
            while c is not None and c.index < g.index:
                c = next(colour, None)
            same = c is not None and c.index == g.index and g.image is not None
            yield g._replace(colour=c.image if same else None)
    finally:
        _close(gray)
        _close(colour)


def prefetch(frames: Iterator[Frame], depth: int = 4) -> Iterator[Frame]:
    """`frames`, decoded ahead in a thread of their own.

    FFmpeg's decoding and image reading release the GIL, so they run on the second core
    while the tracker works on the first; the frames, their order and any error (raised
    where it happened in the sequence) are those of `frames`. Closing this generator (the
    consumer stopped or was interrupted) stops the thread and closes `frames` there.
    Decoding is far faster than tracking, so a few frames ahead (`depth`) keep it fed
    without holding many (a 4K frame is 25 MB).
    """
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def work():
        try:
            for f in frames:
                if not put(f):
                    return
            put(done)
        except BaseException as e:  # delivered in order, raised in the consumer
            put((done, e))
        finally:
            close = getattr(frames, "close", None)
            if close is not None:
                close()

    thread = threading.Thread(target=work, name="mirage-decode", daemon=True)
    thread.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if type(item) is tuple and item[0] is done:  # a Frame is a NamedTuple
                raise item[1]
            yield item
    finally:
        stop.set()
        thread.join(timeout=5.0)


def matching_camera(camera: Camera, width: int, height: int) -> Camera:
    """The camera for frames of another size: scaled when the aspect ratio matches, to
    within the half pixel each side was rounded to (800x600 shrunk 3x is 267x200); a crop
    of a few rows (1920x1088 against 1920x1080) is not a scale and is refused."""
    if (width, height) == camera.size:
        return camera
    if abs(width * camera.height - height * camera.width) <= (camera.width + camera.height) / 2:
        log.warning(
            f"frames are {width}x{height}, camera is {camera.width}x{camera.height}:"
            " scaling the intrinsics"
        )
        return camera.scaled(width, height)
    raise InputError(
        f"frames are {width}x{height} but the camera was calibrated at "
        f"{camera.width}x{camera.height} (other aspect ratio); calibrate at this "
        "size or resize the video"
    )


def _seek(cap, frame: int) -> None:
    try:
        cap.set(cv2.CAP_PROP_POS_FRAMES, frame)
    except cv2.error:
        pass


def _open_capture(p: Path, strict: bool = True, luma: bool = False):
    """`p` opened by OpenCV (None, or InputError when `strict`, if it cannot be); `luma`:
    by FFmpeg with the conversion to BGR off (frames are the decoder's plane 0)."""
    try:
        if luma:
            with _quiet_opencv():  # "BGR conversion turned OFF ... at your own risk"
                cap = cv2.VideoCapture(str(p), cv2.CAP_FFMPEG, [cv2.CAP_PROP_CONVERT_RGB, 0])
        else:
            cap = cv2.VideoCapture(str(p))
    except cv2.error:
        cap = None
    if cap is None or not cap.isOpened():
        if cap is not None:
            cap.release()
        if strict:
            raise InputError(f"cannot open video {p} (missing, corrupt or unsupported codec)")
        return None
    return cap


def _retrieve(cap, gray: bool, luma: str | None, raw: bool = False) -> np.ndarray | None:
    """The grabbed frame, None when it does not decode: BGR, or gray by BGR2GRAY, or (with
    `luma`, its range) the luma plane of a capture opened with `luma`, as full range.
    A raw frame's retrieval is quiet ("unsupported picture format ... treated as 8UC1"):
    OpenCV says it once a process, at the first retrieval its log level lets through."""
    try:
        with _quiet_opencv() if raw or luma is not None else contextlib.nullcontext():
            ok, frame = cap.retrieve()
        if not ok or frame is None:
            return None
        if luma is not None:
            return expand_luma(frame, luma) if frame.ndim == 2 else None
        return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if gray and frame.ndim == 3 else frame
    except cv2.error:
        return None


def _luma_mode(p: Path) -> str | None:
    """`luma_range` of the video's first frame, read both ways (FFmpeg only), or None."""
    first: dict[bool, np.ndarray | None] = {}
    for luma in (False, True):
        cap = _open_capture(p, strict=False, luma=luma)
        if cap is None:
            return None
        try:
            if not luma and cap.getBackendName() != "FFMPEG":
                return None
            first[luma] = _retrieve(cap, False, None, raw=luma) if cap.grab() else None
        except cv2.error:
            return None
        finally:
            cap.release()
    return luma_range(first[True], first[False])


@contextlib.contextmanager
def _quiet_opencv():
    """OpenCV's warnings off (its errors still shown), the log level restored after."""
    try:
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    except (AttributeError, cv2.error):
        level = None
    try:
        yield
    finally:
        if level is not None:
            cv2.utils.logging.setLogLevel(level)


def _exts(exts) -> str:
    return ", ".join(sorted(e.lstrip(".") for e in exts))
