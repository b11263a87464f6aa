"""The one frame reader: image-sequence times (--fps, timestamp names), videos, scaling."""

import itertools
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
    Frame,
    FrameSource,
    gray_frames,
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
