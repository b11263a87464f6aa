"""How alike consecutive detections err: the figure behind `SmoothSettings.min_run`. For the
random scenes of `benchmarks/generalize.py` (far tuning seeds by default), each scene is
tracked unsmoothed; each detection's position error against the truth is whitened by its
own reported covariance (a flowed frame repeats its anchor's points and is left out), and
errors beyond `--clip` sigma are dropped. Printed: the correlation of detections `lag`
apart in each scene's sequence, and over 31-frame windows n x Var(window mean) / Var(one
detection): 1 for independent errors, the window's n for identical ones.

    python tools/detection_correlation.py                    # far, seeds 10-29
    python tools/detection_correlation.py --family near --seeds 10-19
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import generalize  # noqa: E402
import numpy as np  # noqa: E402

from mirage_cli.camera import Camera  # noqa: E402
from mirage_cli.frames import Frame  # noqa: E402
from mirage_cli.pipelines.track import tracked_records  # noqa: E402
from mirage_cli.tracking import Tracker, TrackSettings  # noqa: E402
from mirage_cli.tracking.smooth import SmoothSettings, world_covariance  # noqa: E402
from mirage_cli.trajectory import read_pose_csv  # noqa: E402

LAGS = (1, 2, 3, 5, 10, 15)
WINDOW = 31  # frames: the smoother's window at its default lag of 15


def whitened_detections(folder: Path, clip: float) -> tuple[np.ndarray, np.ndarray]:
    """Frame numbers and whitened position errors (n, 3) of a scene's detections."""
    stress = generalize.stress
    cam = Camera.load(folder / "camera_truth.yaml")
    truth = read_pose_csv(folder / "orbit_truth.csv")
    centres = truth[["x_m", "y_m", "z_m"]].to_numpy(float)
    frames, _ = stress.load_frames(folder / "orbit.mp4")
    model = stress.get_model(folder / "keyframes", cam)
    held = (Frame(i, i, i / stress.FPS, f) for i, f in enumerate(frames))
    records = tracked_records(held, Tracker(model, cam, TrackSettings()), SmoothSettings(lag=0))
    found, z = [], []
    for i, r in enumerate(records):
        m = r.measurement
        if m is None or m.anchor != i:
            continue
        C = world_covariance(m.cov, m.pose)[3:, 3:]
        w = np.linalg.solve(np.linalg.cholesky(C), m.pose.center - centres[i])
        if np.all(np.abs(w) < clip):
            found.append(i)
            z.append(w)
    return np.array(found, int), np.array(z, float).reshape(-1, 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--family", choices=["near", "far", "above"], default="far")
    ap.add_argument("--seeds", default="10-29", help="e.g. 10-29 or report")
    ap.add_argument("--clip", type=float, default=4.0, help="drop errors beyond this sigma")
    ap.add_argument("--frames", type=int, default=150, help="frames per scene (as rendered)")
    args = ap.parse_args()
    scenes = []
    for seed in generalize.parse_seeds(args.seeds, None):
        folder = generalize.scene_folder(args.family, seed, args.frames, 2)
        found, z = whitened_detections(folder, args.clip)
        if len(z) >= 2:
            scenes.append((found, z))
        print(f"{args.family} {seed}: {len(z)} detections", file=sys.stderr)
    if not scenes:
        sys.exit("no scene has two detections")
    var = np.mean(np.concatenate([z for _, z in scenes]) ** 2, axis=0)
    print("| lag (detections) | " + " | ".join(map(str, LAGS)) + " |")
    print("|---|" + "---|" * len(LAGS))
    rho = []
    for lag in LAGS:
        pairs = [(z[lag:] * z[:-lag]) / var for _, z in scenes if len(z) > lag]
        rho.append(np.concatenate(pairs).mean() if pairs else np.nan)
    print("| correlation | " + " | ".join(f"{r:.2f}" for r in rho) + " |")
    ratios = [
        sel.sum() * np.mean(z[sel], axis=0) ** 2 / var
        for found, z in scenes
        for start in range(0, args.frames, WINDOW)
        if (sel := (found >= start) & (found < start + WINDOW)).sum() >= 6
    ]
    r = np.array(ratios)
    print(f"\n{len(r)} windows of {WINDOW} frames with 6+ detections: n x Var(mean) / Var(one)"
          f" mean {r.mean():.2f}, median {np.median(r):.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
