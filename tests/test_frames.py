"""The one frame reader: image-sequence times (--fps, timestamp names), videos, scaling."""

import itertools
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from conftest import SAMPLE, assert_one_line_error

from mirage_cli.camera import Camera
from mirage_cli.errors import InputError
from mirage_cli.frames import (
    LUMA_TOLERANCE,
    Frame,
    FrameSource,
    gray_frames,
    luma_range,
    matching_camera,
    name_times,
    prefetch,
)


def orbit_frames(folder: Path, names: list[str], first: int = 0) -> list[Path]:
    """Frames first, first + 1, ... of the sample orbit saved under the given names."""
    folder.mkdir(parents=True, exist_ok=True)
    cap = cv2.VideoCapture(str(SAMPLE / "orbit.mp4"))
    cap.set(cv2.CAP_PROP_POS_FRAMES, first)
    paths = []
    for name in names:
        ok, img = cap.read()
        assert ok
        paths.append(folder / name)
        cv2.imwrite(str(paths[-1]), img)
    cap.release()
    return paths


def test_name_times_rule():
    def times(*names):
        return name_times([Path(n) for n in names])

    assert times("1305031102.175304.png", "1305031102.211214.png") == pytest.approx(
        [1305031102.175304, 1305031102.211214]
    )
    assert times("000123456789.png", "000156789123.png") == pytest.approx(
        [0.123456789, 0.156789123]
    )
    ns = times("1403636579763555584.png", "1403636579813555456.png")
    assert ns[1] - ns[0] == pytest.approx(0.05, abs=1e-6)
    assert times("000042.png", "000043.png") is None  # frame counters, not times
    assert times("frame_1305031102.1.png", "frame_1305031102.2.png") is None
    assert times("1.5.png", "1.50.png") is None  # one time twice is not a clock


def test_image_folder_times_from_names_and_fps(tmp_path):
    # tenths of a second written with differing digits: ordered by time, not by name
    orbit_frames(tmp_path / "stamped", ["100.5.png", "100.25.png", "100.75.png"])
    src = FrameSource([tmp_path / "stamped"])
    got = list(src.frames())
    assert [f.id for f in got] == ["100.25.png", "100.5.png", "100.75.png"]
    assert [f.time_s for f in got] == pytest.approx([100.25, 100.5, 100.75])
    assert src.fps == pytest.approx(4.0)
    assert all(f.image.shape == (480, 640, 3) for f in got)
    # --fps wins over names; times count from the first image, whatever --start is
    src = FrameSource([tmp_path / "stamped"], fps=20)
    assert [f.time_s for f in src.frames(start=1)] == pytest.approx([0.05, 0.1])
    # plain counters: no times
    orbit_frames(tmp_path / "plain", ["000001.png", "000002.png"])
    assert all(np.isnan(f.time_s) for f in FrameSource([tmp_path / "plain"]).frames())


def test_video_frames_every_gray_and_fps_refused():
    src = FrameSource([SAMPLE / "orbit.mp4"])
    assert src.is_video and src.size == (640, 480) and src.count == 540
    got = list(src.frames(start=30, end=40, every=4, gray=True))
    assert [f.index for f in got] == [30, 34, 38] and [f.id for f in got] == [30, 34, 38]
    assert [f.time_s for f in got] == pytest.approx([1.0, 34 / 30, 38 / 30])
    assert got[0].image.shape == (480, 640)
    with pytest.raises(InputError, match="--fps"):
        FrameSource([SAMPLE / "orbit.mp4"], fps=30)


def test_matching_camera_scales_or_refuses():
    cam = Camera.load(SAMPLE / "camera_truth.yaml")
    assert matching_camera(cam, 640, 480) is cam
    half = matching_camera(cam, 320, 240)
    assert half.K[0, 0] == pytest.approx(cam.K[0, 0] / 2) and half.size == (320, 240)
    with pytest.raises(InputError, match="320x320"):
        matching_camera(cam, 320, 320)
    third = matching_camera(cam, 213, 160)  # 640x480 shrunk 3x, rounded
    assert third.size == (213, 160) and third.K[1, 1] == pytest.approx(cam.K[1, 1] / 3)
    with pytest.raises(InputError, match="640x472"):
        matching_camera(cam, 640, 472)  # 8 rows cropped: not the same lens scaled


def test_track_image_times_agree_in_csv_and_tum(sample_model, tmp_path, mirage):
    """Timestamped names and --fps give the same times in the pose CSV and the TUM file,
    and the overlay video plays at their rate, one frame each."""
    names = [f"{1699999999.0 + k / 30:.6f}.png" for k in range(6)]
    orbit_frames(tmp_path / "f", names, first=60)
    for extra, t0, dt in [([], 1699999999.0, 1 / 30), (["--fps", "10"], 0.0, 0.1)]:
        csv, tum, ov = tmp_path / "p.csv", tmp_path / "p.tum", tmp_path / "ov.mp4"
        args = ["track", tmp_path / "f", "--model", sample_model, "-o", csv, "--tum", tum]
        p = mirage(*args, "--overlay", ov, *extra)
        assert p.returncode == 0, p.stderr
        est = pd.read_csv(csv)
        assert est["frame"].tolist() == names
        assert est["time_s"].to_numpy() == pytest.approx(t0 + dt * np.arange(6), abs=1e-6)
        assert (est["status"] == "ok").all()
        t = np.loadtxt(tum)
        assert t[:, 0] == pytest.approx(est["time_s"].to_numpy(), abs=1e-6)
        cap = cv2.VideoCapture(str(ov))
        fps, n = cap.get(cv2.CAP_PROP_FPS), int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        cap.release()
        assert fps == pytest.approx(1 / dt, rel=1e-3) and n == len(names)
    p = mirage("track", SAMPLE / "orbit.mp4", "--model", sample_model, "--fps", "5")
    assert_one_line_error(p, 2, "--fps")


def test_prefetch_keeps_order_and_raises_where_the_error_was():
    def reader():
        yield from (Frame(i, i, i / 30, None) for i in range(5))
        raise InputError("frame 5 is unreadable")

    got = []
    with pytest.raises(InputError, match="frame 5 is unreadable"):
        for f in prefetch(reader(), depth=2):
            got.append(f.index)
    assert got == [0, 1, 2, 3, 4]


def test_gray_frames_in_the_decoding_thread_are_the_trackers_gray():
    """`mirage track` without overlays grays the frames where they are decoded: the same
    pixels the tracking loop computed itself; gray and undecodable frames pass as they are;
    closing it early closes the reader."""
    colour = [f for f in itertools.islice(FrameSource([SAMPLE / "orbit.mp4"]).frames(), 3)]
    mono = Frame(3, 3, 0.1, colour[0].image[..., 1].copy())
    closed = threading.Event()

    def reader():
        try:
            yield from [*colour, mono, Frame(4, 4, 0.13, None)]
            yield from (Frame(i, i, i / 30, None) for i in itertools.count(5))
        finally:
            closed.set()

    frames = prefetch(gray_frames(reader()), depth=2)
    got = [next(frames) for _ in range(5)]
    for f, c in zip(got, colour, strict=False):
        assert f.index == c.index
        assert np.array_equal(f.image, cv2.cvtColor(c.image, cv2.COLOR_BGR2GRAY))
    assert got[3].image is mono.image and got[4].image is None
    frames.close()
    assert closed.wait(5.0)


def test_prefetch_closed_early_stops_and_closes_the_reader():
    closed = threading.Event()

    def reader():
        try:
            for i in itertools.count():
                yield Frame(i, i, i / 30, None)
        finally:
            closed.set()

    frames = prefetch(reader(), depth=2)
    assert [next(frames).index for _ in range(3)] == [0, 1, 2]
    frames.close()  # the consumer stopped (an interrupt, an error downstream)
    assert closed.wait(5.0)
    assert not any(t.name == "mirage-decode" and t.is_alive() for t in threading.enumerate())


def orbit_video(path: Path, fourcc: str, n: int = 12, size=(96, 72), first=None) -> Path:
    """The sample orbit's first `n` frames, resized, written with `fourcc` (a test video of
    another pixel format: MJPG full-range yuvj420p, FFV1 BGRA, HFYU BGR); `first`
    replaces the first frame."""
    cap = cv2.VideoCapture(str(SAMPLE / "orbit.mp4"))
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30, size)
    assert out.isOpened()
    for i in range(n):
        ok, img = cap.read()
        assert ok
        out.write(first if i == 0 and first is not None else cv2.resize(img, size))
    out.release()
    cap.release()
    return path


def gray_diff(a: list[Frame], b: list[Frame]) -> list[float]:
    assert [(f.index, f.id, f.time_s) for f in a] == [(f.index, f.id, f.time_s) for f in b]
    assert [f.image is None for f in a] == [f.image is None for f in b]
    return [
        float(np.abs(x.image.astype(int) - y.image).mean())
        for x, y in zip(a, b, strict=True)
        if x.image is not None
    ]


def test_gray_from_the_luma_plane_is_bgr2gray_with_the_same_frames():
    """The sample video (yuv420p, video range) is grayed from its luma plane: within two
    grey levels of BGR2GRAY on every frame; --start / --every / --end pick the same frame
    ids and times as the colour path."""
    src = FrameSource([SAMPLE / "orbit.mp4"])
    assert src.luma_mode() == "limited"
    fast = list(src.frames(0, 40, luma=True))
    assert all(f.image.dtype == np.uint8 and f.image.shape == (480, 640) for f in fast)
    diff = gray_diff(fast, list(src.frames(0, 40, gray=True)))
    assert len(diff) == 40 and max(diff) <= LUMA_TOLERANCE, diff
    fast = list(src.frames(start=7, end=100, every=5, luma=True))
    colour = list(src.frames(start=7, end=100, every=5))
    assert [f.id for f in fast] == list(range(7, 100, 5))
    assert max(gray_diff(fast, list(gray_frames(iter(colour))))) <= LUMA_TOLERANCE


def test_video_whose_luma_is_not_its_gray_falls_back_to_bgr(tmp_path):
    """Packed BGR / BGRA videos (HFYU, FFV1) fail the first-frame check and are grayed by
    BGR2GRAY, pixel for pixel as before; full-range MJPEG passes as it is; a first frame of
    uniform grey cannot tell the ranges apart: BGR2GRAY."""
    for fourcc in ("HFYU", "FFV1"):
        src = FrameSource([orbit_video(tmp_path / f"{fourcc}.avi", fourcc)])
        assert src.luma_mode() is None, fourcc
        assert max(gray_diff(list(src.frames(luma=True)), list(src.frames(gray=True)))) == 0
    src = FrameSource([orbit_video(tmp_path / "mjpg.avi", "MJPG")])
    assert src.luma_mode() == "full"
    assert max(gray_diff(list(src.frames(luma=True)), list(src.frames(gray=True)))) <= 2
    flat = np.full((72, 96, 3), 113, np.uint8)
    src = FrameSource([orbit_video(tmp_path / "flat.avi", "MJPG", first=flat)])
    assert src.luma_mode() is None
    bgr = cv2.imread(str(SAMPLE / "keyframes" / "kf_000.jpg"))
    y = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV)[..., 0]
    assert luma_range(y, bgr) == "full"
    assert luma_range(y.astype(np.uint16), bgr) is None  # 10-bit planes
    assert luma_range(y[:, :-1], bgr) is None and luma_range(None, bgr) is None


def test_damaged_video_stretch_on_the_luma_path(tmp_path):
    """Damaged bytes mid-video: the luma path reports the same undecodable frames as the
    colour path and decodes on after them."""
    data = bytearray((SAMPLE / "orbit.mp4").read_bytes())
    a = len(data) // 6
    data[a : a + 100_000] = np.random.default_rng(0).integers(0, 256, 100_000, np.uint8).tobytes()
    (tmp_path / "damaged.mp4").write_bytes(bytes(data))
    src = FrameSource([tmp_path / "damaged.mp4"])
    fast = list(src.frames(0, 200, every=3, luma=True))
    assert 0 < sum(f.image is None for f in fast) < len(fast) // 4
    assert fast[-1].image is not None
    assert max(gray_diff(fast, list(src.frames(0, 200, every=3, gray=True)))) <= LUMA_TOLERANCE


def test_colour_with_the_luma_gray_tracks_the_same_gray(tmp_path):
    """Overlays need the colour: `frames(luma=True, colour=True)` gives the same gray as
    without colour (pixel for pixel) and each frame's own colour image, on the luma path (a
    second decoder), on a damaged video (both decoders' frames stay aligned by index), and
    on sources without a luma plane (the colour is what was grayed)."""
    src = FrameSource([SAMPLE / "orbit.mp4"])
    both = list(src.frames(5, 60, every=4, luma=True, colour=True))
    gray = list(src.frames(5, 60, every=4, luma=True))
    colour = list(src.frames(5, 60, every=4))
    assert [f.id for f in both] == [f.id for f in gray] == list(range(5, 60, 4))
    assert all(np.array_equal(a.image, b.image) for a, b in zip(both, gray, strict=True))
    assert all(np.array_equal(a.colour, c.image) for a, c in zip(both, colour, strict=True))
    data = bytearray((SAMPLE / "orbit.mp4").read_bytes())
    a = len(data) // 6
    data[a : a + 100_000] = np.random.default_rng(0).integers(0, 256, 100_000, np.uint8).tobytes()
    (tmp_path / "damaged.mp4").write_bytes(bytes(data))
    src = FrameSource([tmp_path / "damaged.mp4"])
    both = list(src.frames(0, 200, every=3, luma=True, colour=True))
    gray = list(src.frames(0, 200, every=3, luma=True))
    colour = {f.index: f.image for f in src.frames(0, 200, every=3)}
    assert [f.id for f in both] == [f.id for f in gray] and any(f.image is None for f in both)
    for f, g in zip(both, gray, strict=True):
        assert (f.image is None) == (g.image is None) and (f.colour is None) == (f.image is None)
        if f.image is not None:
            assert np.array_equal(f.image, g.image) and np.array_equal(f.colour, colour[f.index])
    folder = list(FrameSource([SAMPLE / "keyframes"]).frames(0, 3, luma=True, colour=True))
    first = cv2.imread(str(sorted((SAMPLE / "keyframes").glob("*.jpg"))[0]))
    assert np.array_equal(folder[0].colour, first)
    assert np.array_equal(folder[0].image, cv2.cvtColor(first, cv2.COLOR_BGR2GRAY))


def test_luma_path_says_nothing_on_stderr():
    """OpenCV warns twice of a capture with BGR conversion off ("at your own risk",
    "unsupported picture format"): the luma path silences both and restores the level
    (`mirage track`'s own stderr: test_track's damaged-video test)."""
    code = (
        "import cv2; from mirage_cli.frames import FrameSource as S; "
        f"n = len(list(S([r'{SAMPLE / 'orbit.mp4'}']).frames(3, 30, 4, luma=True))); "
        "print(n, cv2.utils.logging.getLogLevel())"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0 and p.stdout.split() == ["7", "3"] and p.stderr == "", p.stderr
