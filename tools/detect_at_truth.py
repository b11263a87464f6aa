"""What the tracker finds at the true pose, frame by frame, against what it tracked: tells a
scene whose views do not match the model (lost even at the truth) from one whose views
match but are never found (found at the truth, lost when tracking) or too vague to be
`ok` (uncertain at the truth). A random scene of `benchmarks/generalize.py`:

    python tools/detect_at_truth.py above 2          # every 5th in-view frame
    python tools/detect_at_truth.py far 1025 --every 10

For each frame: the status, inliers, matches and sigma of a detection whose prediction is
the true pose (`Tracker._detect`, as a frame right after a tracked one), and the
position error of what `mirage track`'s loop (smoothed) gave, or '-' when it gave no pose.
The scene is rendered and cached as `generalize.py` does; the model built from its
keyframes with `build-model`'s defaults and the true camera.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import generalize  # noqa: E402

from mirage_cli.camera import Camera  # noqa: E402
from mirage_cli.features import to_gray  # noqa: E402
from mirage_cli.tracking import Tracker, TrackSettings  # noqa: E402
from mirage_cli.trajectory import read_pose_csv, row_pose  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("family", choices=["near", "far", "above"])
    ap.add_argument("seed", type=int)
    ap.add_argument("--every", type=int, default=5, help="every Nth in-view frame")
    ap.add_argument("--frames", type=int, default=150, help="frames per scene (as rendered)")
    args = ap.parse_args()
    stress = generalize.stress
    folder = generalize.scene_folder(args.family, args.seed, args.frames, 2)
    cam = Camera.load(folder / "camera_truth.yaml")
    truth = read_pose_csv(folder / "orbit_truth.csv")
    frames, _ = stress.load_frames(folder / "orbit.mp4")
    model = stress.get_model(folder / "keyframes", cam)
    tracked, _ = stress.run_mirage(frames, model, cam)
    probe = Tracker(model, cam, TrackSettings())
    visible = truth["landmark_visible"].to_numpy()
    print("| frame | at the truth | inliers / matches | sigma mm / deg | tracked error mm |")
    print("|---|---|---|---|---|")
    counts = collections.Counter()
    for i in range(0, len(frames), args.every):
        if visible[i] < generalize.IN_VIEW:
            continue
        t = row_pose(truth.iloc[i])
        # a fresh state whose prediction is the truth: no flow, no velocity, not lost
        probe.prev_pose, probe.velocity, probe.lost_run, probe.hint = t, None, 0, None
        probe.track_px, probe._pending = None, {}
        rec = probe._detect(to_gray(frames[i]))
        counts[str(rec.status)] += 1
        got = tracked[i][0]
        err = f"{1000 * got.distance_to(t):.1f}" if got is not None else "-"
        print(
            f"| {i} | {rec.status} | {rec.inliers} / {rec.matches} "
            f"| {1000 * rec.sigma_pos_m:.1f} / {rec.sigma_rot_deg:.2f} | {err} |"
        )
    n = sum(counts.values())
    shown = [i for i in range(0, len(frames), args.every) if visible[i] >= generalize.IN_VIEW]
    ok = sum(tracked[i][0] is not None for i in shown)
    print(f"\nat the truth: {dict(counts)} of {n}; tracked: {ok} of {n}")


if __name__ == "__main__":
    main()
