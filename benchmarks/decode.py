"""Decoding benchmark: ms per frame to decode a video to gray, the colour way (FFmpeg's BGR,
then BGR2GRAY: `mirage track` before issue 31, and now with --overlay / --rerun) against
the decoder's luma plane (`FrameSource.frames(luma=True)`), in interleaved runs.

    python benchmarks/decode.py --make /tmp/decode          # 640x480, 1080p, 4K from the
    python benchmarks/decode.py /tmp/decode/*.mp4 --repeats 5   # sample orbit (mp4v)

Both ways run in this process, one after the other per repeat; the medians and their ratio
are printed, with the luma path's check (`luma_mode`) and the mean grey-level difference.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mirage_cli.frames import FrameSource, gray_frames  # noqa: E402

SIZES = {"640x480": (640, 480), "1080p": (1920, 1080), "4k": (3840, 2160)}


def make_videos(out: Path, frames: int) -> list[Path]:
    """The sample orbit's first frames upscaled (bicubic) to each size, written as mp4v."""
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, size in SIZES.items():
        path = out / f"orbit_{name}.mp4"
        cap = cv2.VideoCapture(str(ROOT / "sample_data" / "orbit.mp4"))
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30, size)
        for _ in range(frames):
            ok, img = cap.read()
            if not ok:
                break
            writer.write(cv2.resize(img, size, interpolation=cv2.INTER_CUBIC))
        writer.release()
        cap.release()
        paths.append(path)
        print(f"wrote {path}")
    return paths


def ms_per_frame(video: Path, luma: bool, limit: int) -> tuple[float, float]:
    """Decoding to gray, wall and CPU (all threads) ms per frame; the luma path's one check
    at open (two opens, a first frame decoded both ways: `check_ms`) not counted."""
    src = FrameSource([video])
    if luma:
        src.luma_mode()
    t0, c0 = time.perf_counter(), time.process_time()
    frames = src.frames(0, limit, luma=True) if luma else gray_frames(src.frames(0, limit))
    n = max(sum(1 for _ in frames), 1)
    return (time.perf_counter() - t0) * 1000 / n, (time.process_time() - c0) * 1000 / n


def check_ms(video: Path) -> float:
    t0 = time.perf_counter()
    FrameSource([video]).luma_mode()
    return (time.perf_counter() - t0) * 1000


def grey_difference(video: Path, limit: int) -> float:
    src = FrameSource([video])
    pairs = zip(src.frames(0, limit, luma=True), src.frames(0, limit, gray=True), strict=True)
    return float(np.mean([np.abs(a.image.astype(int) - b.image).mean() for a, b in pairs]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("videos", nargs="*", type=Path)
    ap.add_argument("--make", type=Path, help="write the test videos into this folder first")
    ap.add_argument("--frames", type=int, default=90, help="frames decoded per run")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    videos = list(args.videos) + (make_videos(args.make, args.frames) if args.make else [])
    head = "wall ms colour/luma  ratio  CPU ms colour/luma  ratio  mode"
    print(f"{'video':18s} {'size':>9s}  {head}")
    for video in videos:
        src = FrameSource([video])
        runs: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
        for _ in range(args.repeats):
            for luma in (False, True):
                runs[luma].append(ms_per_frame(video, luma, args.frames))
        (w0, c0), (w1, c1) = (np.median(runs[k], axis=0) for k in (False, True))
        w, h = src.size
        print(
            f"{video.name:18s} {f'{w}x{h}':>9s} {w0:8.2f} {w1:8.2f} {w1 / w0:9.2f}"
            f" {c0:8.2f} {c1:8.2f} {c1 / c0:9.2f}  {src.luma_mode()}"
        )
        print(
            f"{'':28s}mean |luma - BGR2GRAY| {grey_difference(video, 10):.2f} grey levels,"
            f" check at open {check_ms(video):.0f} ms"
        )


if __name__ == "__main__":
    main()
