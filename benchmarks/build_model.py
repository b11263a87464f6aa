"""Benchmark `mirage build-model` on the 36 sample keyframes (issue 5).

    python benchmarks/build_model.py [--detector sift|orb|akaze] [--repeat N]

Times each stage of the build (reading, features, matching + triangulation), the model
save and load, and checks the model against the synthetic truth: linked 3D points per
keyframe, reprojection RMS, and the median distance of the points on the landmark
(inside its bounding box + 2 cm) to its true surface. Prints markdown tables.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mirage_cli.build_model import BuildSettings, build_model, views_from_inputs  # noqa: E402
from mirage_cli.camera import Camera  # noqa: E402
from mirage_cli.features import DETECTORS, DetectorSettings  # noqa: E402
from mirage_cli.model import LandmarkModel  # noqa: E402
from mirage_cli.synth import LANDMARK_BOUNDS, landmark_surface_distance  # noqa: E402

KF = ROOT / "sample_data" / "keyframes"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--detector", default="sift", choices=DETECTORS)
    ap.add_argument("--repeat", type=int, default=3, help="builds to time (best is reported)")
    args = ap.parse_args()
    cam = Camera.load(ROOT / "sample_data" / "camera_truth.yaml")
    settings = BuildSettings(detector=DetectorSettings(args.detector))
    stages: dict[str, float] = {}
    builds, reads = [], []
    for _ in range(max(1, args.repeat)):
        t0 = time.perf_counter()
        views = views_from_inputs([KF], cam, settings, poses_csv=KF / "poses.csv")
        t1 = time.perf_counter()
        marks: dict[str, float] = {}

        def prog(name, k, n, marks=marks):
            marks[name] = time.perf_counter()

        res = build_model(views, cam, settings, prog)
        t2 = time.perf_counter()
        reads.append(t1 - t0)
        builds.append(t2 - t0)
        if t2 - t0 <= min(builds):
            stages = {
                "read + select views": t1 - t0,
                "features": marks["features"] - t1,
                "matching": marks["matching"] - marks["features"],
                "tracks + triangulation": t2 - marks["matching"],
            }
    model = res.model
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "landmark.mirage"
        t0 = time.perf_counter()
        model.save(path)
        save_s = time.perf_counter() - t0
        size_mb = path.stat().st_size / 1e6
        loads = []
        for _ in range(5):
            t0 = time.perf_counter()
            LandmarkModel.load(path)
            loads.append(time.perf_counter() - t0)
    s = model.summary()
    X = model.points
    on = np.all((X >= LANDMARK_BOUNDS[0] - 0.02) & (X <= LANDMARK_BOUNDS[1] + 0.02), axis=1)
    surf = landmark_surface_distance(X[on]) * 1000
    linked = [kf.n_linked for kf in model.keyframes]

    print(f"## build-model on sample_data/keyframes ({args.detector}, {os.cpu_count()} CPUs)\n")
    print("| stage | seconds |\n|---|---:|")
    for k, v in stages.items():
        print(f"| {k} | {v:.2f} |")
    print(f"| **build total** (best of {len(builds)}) | **{min(builds):.2f}** |")
    print(f"| save | {save_s:.2f} |")
    print(f"| load (median of 5) | {np.median(loads):.3f} |\n")
    print("| quality | value |\n|---|---:|")
    print(f"| keyframes | {s['keyframes']} |")
    print(f"| 3D points | {s['points']} ({on.sum()} on the landmark) |")
    print(f"| linked points per keyframe min / median | {min(linked)} / {np.median(linked):.0f} |")
    print(f"| mean track length | {s['mean_track_length']:.2f} |")
    print(f"| reprojection RMS / mean (px) | {s['rms_reprojection_px']:.3f} / "
          f"{s['mean_reprojection_px']:.3f} |")  # fmt: skip
    print(f"| surface distance median / p90 (mm) | {np.median(surf):.2f} / "
          f"{np.percentile(surf, 90):.2f} |")  # fmt: skip
    print(f"| azimuth coverage / largest gap (deg) | {s['azimuth_coverage_deg']:.0f} / "
          f"{s['largest_gap_deg']:.0f} |")  # fmt: skip
    print(f"| model file size (MB) | {size_mb:.1f} |")


if __name__ == "__main__":
    main()
