"""Image and video inputs shared by every command.

Commands take INPUT arguments that may be files, folders or globs, or one video; this
module turns them into a sorted list of images or a video, reads images with a clear
error instead of OpenCV's silent None, and samples video frames.
"""

from __future__ import annotations

import glob
import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .errors import InputError, cv_message

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


@dataclass
class MediaInput:
    """What INPUT arguments resolved to: a sorted list of images, or one video."""

    images: list[Path] = field(default_factory=list)
    video: Path | None = None

    @property
    def is_video(self) -> bool:
        return self.video is not None


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


def resolve_inputs(inputs: Iterable[str], what: str = "images") -> MediaInput:
    """Expand files, folders and globs into sorted image paths, or detect one video."""
    inputs = [str(i) for i in inputs]
    if not inputs:
        raise InputError(f"no input given; pass {what} (files, a folder or a glob) or a video")
    images: list[Path] = []
    videos: list[Path] = []
    for arg in inputs:
        p = Path(arg).expanduser()
        if p.is_dir():
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
        else:
            raise InputError(f"input {p} not found")
    if videos:
        if len(videos) > 1 or images:
            raise InputError("give either images or a single video, not both / several videos")
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


@dataclass(frozen=True)
class VideoInfo:
    frames: int
    fps: float
    width: int
    height: int


def video_info(path: str | Path) -> VideoInfo:
    cap = _open_capture(Path(path))
    try:
        return VideoInfo(
            frames=max(0, int(cap.get(cv2.CAP_PROP_FRAME_COUNT))),
            fps=float(cap.get(cv2.CAP_PROP_FPS) or 0.0),
            width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
        )
    finally:
        cap.release()


def iter_video(
    path: str | Path, every: int = 1, gray: bool = False
) -> Iterator[tuple[int, float, np.ndarray]]:
    """Yield (frame index, time in s, frame) for every `every`-th frame.

    Skipped frames are only grabbed, not decoded into images, which is most of the cost
    of sampling a long video sparsely.
    """
    if every < 1:
        raise InputError(f"frame step must be >= 1, got {every}")
    p = Path(path)
    cap = _open_capture(p)
    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    index = 0
    try:
        while True:
            try:
                if not cap.grab():
                    break
                if index % every == 0:
                    ok, frame = cap.retrieve()
                    if not ok or frame is None:
                        break
                    t = index / fps if fps > 0 else cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
                    if gray and frame.ndim == 3:
                        frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
                    yield index, float(t), frame
            except cv2.error as e:
                raise InputError(f"cannot decode frame {index} of {p}: {cv_message(e)}") from None
            index += 1
    finally:
        cap.release()
    if index == 0:
        raise InputError(f"video {p} has no readable frames (corrupt or unsupported codec)")


def _open_capture(p: Path, strict: bool = True):
    try:
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


def _exts(exts) -> str:
    return ", ".join(sorted(e.lstrip(".") for e in exts))
