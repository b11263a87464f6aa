"""Runtime and accuracy of mirage_cli.calibrate vs a plain OpenCV loop on the same images.

    python benchmarks/calibrate.py [--runs 5]

Images: sample_data/calibration (rendered, with camera_truth.yaml) when present, else the
13 real photos in tests/data/chessboard-right cycled to 20 (also with --real).
Prints a markdown table.
"""

from __future__ import annotations

import argparse
import statistics
import time
from itertools import cycle, islice
from pathlib import Path

import cv2
import numpy as np

from mirage_cli.boards import Board
from mirage_cli.calibrate import CalibOptions, calibrate, detect_images
from mirage_cli.camera import Camera

ROOT = Path(__file__).resolve().parents[1]
SYNTH = ROOT / "sample_data" / "calibration"
REAL = ROOT / "tests" / "data" / "chessboard-right"
BOARD = Board(9, 6, 0.025)


def images(real: bool = False) -> tuple[list[Path], Camera | None, str]:
    truth = ROOT / "sample_data" / "camera_truth.yaml"
    found = sorted(SYNTH.glob("*.jpg")) if SYNTH.is_dir() and not real else []
    if len(found) >= 20 and truth.is_file():
        return found[:20], Camera.load(truth), "sample_data/calibration (rendered)"
    return list(islice(cycle(sorted(REAL.glob("*.jpg"))), 20)), None, "real photos x20"


def run_mirage(paths, workers):
    det = detect_images(paths, BOARD, workers=workers)
    c = calibrate(det, BOARD, CalibOptions())
    return c.K, c.rms_px, len(c.views)


def run_opencv(paths):
    """What most calibration scripts do (OpenCV's tutorial): classic detector, 11 px
    cornerSubPix half-window, calibrateCamera, no outlier handling."""
    obj, pts, size = [], [], None
    for p in paths:
        gray = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        size = gray.shape[::-1]
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, corners = cv2.findChessboardCorners(gray, (BOARD.cols, BOARD.rows), flags=flags)
        if ok:
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
            pts.append(cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), crit))
            obj.append(BOARD.object_points)
    rms, K, *_ = cv2.calibrateCamera(obj, pts, size, None, None)
    return K, rms, len(pts)


def timed(fn, runs):
    times, out = [], None
    for _ in range(runs):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--real", action="store_true", help="use the real photos (cycled to 20)")
    args = ap.parse_args()
    paths, truth, label = images(args.real)
    rows = [
        ("plain OpenCV loop", *timed(lambda: run_opencv(paths), args.runs)),
        ("mirage_cli.calibrate, 1 worker", *timed(lambda: run_mirage(paths, 1), args.runs)),
        (
            "mirage_cli.calibrate, default workers",
            *timed(lambda: run_mirage(paths, None), args.runs),
        ),
    ]
    base = rows[0][1]
    print(f"{len(paths)} images 640x480 from {label}; median of {args.runs} runs\n")
    head = "| pipeline | time (s) | ratio vs OpenCV | views | RMS (px) | fx | fy | cx | cy |"
    if truth is not None:
        head += " max intrinsic error vs truth (px) |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    if truth is not None:
        print(
            f"| truth | | | | | {truth.fx:.2f} | {truth.fy:.2f} | {truth.cx:.2f} | "
            f"{truth.cy:.2f} | |"
        )
    for name, t, (K, rms, n) in rows:
        line = (
            f"| {name} | {t:.3f} | {t / base:.2f} | {n} | {rms:.3f} | {K[0, 0]:.2f} | "
            f"{K[1, 1]:.2f} | {K[0, 2]:.2f} | {K[1, 2]:.2f} |"
        )
        if truth is not None:
            err = np.abs(
                np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
                - [truth.fx, truth.fy, truth.cx, truth.cy]
            ).max()
            line += f" {err:.2f} |"
        print(line)


if __name__ == "__main__":
    main()
