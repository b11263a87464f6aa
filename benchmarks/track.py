"""Tracking benchmark on the sample orbit: accuracy against truth, lost frames, speed.

Runs `mirage track`'s pipeline with every --method, plus a plain OpenCV user's pipeline
(SIFT + FLANN ratio matching against all model points + solvePnPRansac + LM refinement,
no temporal tracking), on the same decoded video in the same process, and the decode-only
frame rate of the video as the physical ceiling.

    python benchmarks/track.py                # all methods
    python benchmarks/track.py --methods mirage-s --repeats 3
    mirage synth /tmp/blur --only orbit --duration 6 --motion-blur 4 --noise 3
    python benchmarks/track.py --data /tmp/blur --methods mirage-s,sqpnp   # stress test
    git worktree add /tmp/old <commit>
    python benchmarks/track.py --methods mirage-s --no-plain --repeats 5 --against /tmp/old

`--against` runs another checkout's `mirage track` on the same video and model, each run
interleaved with this checkout's, and prints both (frames/s by the command's summary, wall
seconds, peak memory) and their ratio: the side-by-side comparison on a shared machine.
The in-process loops run with numpy's BLAS in the calling thread, as `mirage` does.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ENV = dict(os.environ)  # the commands run in the caller's environment, as a user's would
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mirage_cli.runtime import blas_in_calling_thread  # noqa: E402

blas_in_calling_thread()  # before numpy loads: its BLAS in the calling thread, as `mirage` runs it

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from mirage_cli.build_model import BuildSettings, build_model, views_from_inputs  # noqa: E402
from mirage_cli.camera import Camera  # noqa: E402
from mirage_cli.features import detect, make_detector  # noqa: E402
from mirage_cli.frames import Frame, FrameSource  # noqa: E402
from mirage_cli.model import LandmarkModel  # noqa: E402
from mirage_cli.pipelines.track import tracked_records  # noqa: E402
from mirage_cli.pose import Pose  # noqa: E402
from mirage_cli.runtime import keep_freed_memory, opencv_threads_for_two_callers  # noqa: E402
from mirage_cli.solver import METHODS  # noqa: E402
from mirage_cli.synth import LANDMARK_TARGET  # noqa: E402
from mirage_cli.tracking import Tracker, TrackSettings  # noqa: E402
from mirage_cli.tracking.smooth import SmoothSettings  # noqa: E402
from mirage_cli.trajectory import read_pose_csv, row_pose  # noqa: E402

keep_freed_memory()  # as `mirage track` runs (every system here gets it: one process)

SAMPLE = ROOT / "sample_data"
IN_VIEW = 0.3  # share of the landmark inside the image for a frame to count as "in view"


def load_frames(video: Path) -> tuple[list[np.ndarray], float]:
    t0 = time.perf_counter()
    frames = [f.image for f in FrameSource([video]).frames()]
    return frames, len(frames) / (time.perf_counter() - t0)


def get_model(camera: Camera, path: Path | None) -> LandmarkModel:
    if path is not None and path.is_file():
        return LandmarkModel.load(path)
    views = views_from_inputs(
        [str(SAMPLE / "keyframes")],
        camera,
        BuildSettings(),
        poses_csv=SAMPLE / "keyframes" / "poses.csv",
    )
    return build_model(views, camera, BuildSettings()).model


def run_mirage(frames, model, camera, method):
    """`mirage track`'s loop (the tracker, then the smoother) over frames held in memory."""
    tr = Tracker(model, camera, TrackSettings(method=method))
    t0 = time.perf_counter()
    held = (Frame(i, i, float("nan"), f) for i, f in enumerate(frames))
    recs = tracked_records(held, tr, SmoothSettings())
    poses = [rec.pose if rec.ok else None for rec in recs]
    return poses, time.perf_counter() - t0


def run_plain_opencv(frames, model, camera):
    """What an OpenCV user writes first: every frame matched against every model point."""
    det = make_detector(model.detector)
    X, D = [], []
    for kf in model.keyframes:
        _, d, pid = kf.linked()
        X.append(model.points[pid])
        D.append(d)
    X, D = np.concatenate(X), np.concatenate(D).astype(np.float32)
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    flann.add([D])
    flann.train()
    poses = []
    t0 = time.perf_counter()
    cv2.setRNGSeed(0)
    for f in frames:
        kp, d = detect(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY), det)
        pose = None
        if d is not None and len(kp) >= 6:
            knn = flann.knnMatch(d.astype(np.float32), k=2)
            good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
            if len(good) >= 6:
                obj = X[[m.trainIdx for m in good]]
                img = kp[[m.queryIdx for m in good]].astype(np.float64)
                try:
                    ok, rvec, tvec, inl = cv2.solvePnPRansac(
                        obj,
                        img,
                        camera.K,
                        camera.dist,
                        reprojectionError=3.0,
                        iterationsCount=500,
                        confidence=0.999,
                        flags=cv2.SOLVEPNP_EPNP,
                    )
                    if ok and inl is not None and len(inl) >= 15:
                        i = inl.ravel()
                        rvec, tvec = cv2.solvePnPRefineLM(
                            obj[i], img[i], camera.K, camera.dist, rvec, tvec
                        )
                        pose = Pose.from_rvec_tvec(rvec, tvec)
                except cv2.error:
                    pose = None
        poses.append(pose)
    return poses, time.perf_counter() - t0


def score(name, poses, truth, seconds, n_frames):
    vis = truth["landmark_visible"].to_numpy()
    pos_err, rot_err, rng = [], [], []
    wrong = ok_out = 0
    ok = np.array([p is not None for p in poses])
    for i, p in enumerate(poses):
        if p is None:
            continue
        t = row_pose(truth.iloc[i])
        if vis[i] == 0:
            ok_out += 1
        e, r = p.distance_to(t), p.angle_to(t)
        d = np.linalg.norm(t.center - LANDMARK_TARGET)
        if e > 0.10 or r > 5.0:
            wrong += 1
        pos_err.append(e)
        rot_err.append(r)
        rng.append(e / d * 100)
    inview = vis >= IN_VIEW
    pe, re, pr = (np.array(a) if a else np.array([np.nan]) for a in (pos_err, rot_err, rng))
    return {
        "pipeline": name,
        "tracked_in_view_%": 100 * ok[inview].mean(),
        "ok_out_of_view": ok_out,
        "pos_med_m": np.median(pe),
        "pos_p95_m": np.percentile(pe, 95),
        "pos_med_%range": np.median(pr),
        "rot_med_deg": np.median(re),
        "rot_p95_deg": np.percentile(re, 95),
        "wrong_poses": wrong,
        "fps": n_frames / seconds,
    }


def reacquisition(poses, truth) -> int:
    """Frames from the landmark's return into view (>= IN_VIEW) to the first ok pose."""
    vis = truth["landmark_visible"].to_numpy()
    out = np.flatnonzero(vis == 0)
    if not len(out):
        return 0
    back = out[-1] + 1
    while back < len(vis) and vis[back] < IN_VIEW:
        back += 1
    for k in range(back, len(poses)):
        if poses[k] is not None:
            return k - back
    return -1


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--model", type=Path, help="existing model (default: build from sample)")
    ap.add_argument("--repeats", type=int, default=1, help="runs per pipeline (median fps)")
    ap.add_argument("--no-plain", action="store_true", help="skip the plain OpenCV pipeline")
    ap.add_argument("--no-command", action="store_true", help="skip the end-to-end CLI run")
    ap.add_argument(
        "--against", type=Path, help="another checkout whose `mirage track` runs side by side"
    )
    ap.add_argument(
        "--data",
        type=Path,
        default=SAMPLE,
        help="folder with orbit.mp4 + orbit_truth.csv (e.g. from mirage synth)",
    )
    args = ap.parse_args()
    opencv_threads_for_two_callers()  # as `mirage track` sizes it (every system here)
    camera = Camera.load(SAMPLE / "camera_truth.yaml")
    truth = read_pose_csv(args.data / "orbit_truth.csv")
    decode = []
    for _ in range(max(1, args.repeats)):
        frames, dfps = load_frames(args.data / "orbit.mp4")
        decode.append(dfps)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory():
        model = get_model(camera, args.model)
    build_s = time.perf_counter() - t0
    print(
        f"orbit: {len(frames)} frames, {int((truth['landmark_visible'] == 0).sum())} out of "
        f"view; model: {len(model.keyframes)} keyframes, {len(model.points)} points "
        f"({build_s:.1f} s)\n"
    )
    rows, reacq = [], {}
    pipelines = [
        (m, lambda m=m: run_mirage(frames, model, camera, m)) for m in args.methods.split(",")
    ]
    if not args.no_plain:
        pipelines.append(
            ("plain OpenCV (SIFT+FLANN+RANSAC+LM)", lambda: run_plain_opencv(frames, model, camera))
        )
    for name, fn in pipelines:
        times = []
        for _ in range(max(1, args.repeats)):
            poses, sec = fn()
            times.append(sec)
        rows.append(score(name, poses, truth, float(np.median(times)), len(frames)))
        reacq[name] = reacquisition(poses, truth)
    cols = list(rows[0].keys())
    print("| " + " | ".join(cols) + " | reacquire_frames |")
    print("|" + "---|" * (len(cols) + 1))
    for r in rows:
        cells = [r["pipeline"]] + [
            f"{r[c]:.4f}"
            if isinstance(r[c], float) and c.startswith(("pos", "rot"))
            else f"{r[c]:.1f}"
            if isinstance(r[c], float)
            else str(r[c])
            for c in cols[1:]
        ]
        print("| " + " | ".join(cells) + f" | {reacq[r['pipeline']]} |")
    print(
        f"\ndecode-only: {np.median(decode):.0f} frames/s (median of {len(decode)}); "
        "fps columns exclude decoding (frames held in memory)"
    )
    if not args.no_command:
        command_tables(args, rows, model, decode)


def command_tables(args, rows, model, decode) -> None:
    """`mirage track` end to end (and, with --against, interleaved with another checkout's):
    frames/s by its summary against the decode-only ceiling."""
    loop = next((r["fps"] for r in rows if r["pipeline"] == "mirage-s"), float("nan"))
    checkouts = [("this checkout", ROOT)]
    if args.against is not None:
        checkouts.append((f"{args.against}", args.against.resolve()))
    per_run = command_runs(model, args.data / "orbit.mp4", max(1, args.repeats), checkouts)
    runs = {k: tuple(np.median(np.array(v), axis=0).tolist()) for k, v in per_run.items()}
    ceiling = float(np.median(decode))
    fps, wall, mb, cpu = runs[ROOT]
    print(
        f"\n| end to end | frames/s | share of the decode-only ceiling |\n|---|---|---|\n"
        f"| `mirage track` (its summary; wall {wall:.1f} s with start-up, peak {mb:.0f} MB) "
        f"| {fps:.1f} | {fps / ceiling:.3f} |\n| the tracking loop (mirage-s row) | {loop:.1f} "
        f"| {loop / ceiling:.3f} |\n| decode only | {ceiling:.0f} | 1 |"
    )
    if args.against is None:
        return
    print(
        f"\n| `mirage track`, runs interleaved (median of {max(1, args.repeats)}) | frames/s "
        "(summary) | wall s | CPU s | peak MB |\n|---|---|---|---|---|"
    )
    for name, path in checkouts:
        f, w, m, c = runs[path]
        print(f"| {name} | {f:.1f} | {w:.1f} | {c:.1f} | {m:.0f} |")
    f0, w0, _, c0 = runs[checkouts[1][1]]
    print(f"| ratio (this / other) | {fps / f0:.2f}x | {wall / w0:.2f} | {cpu / c0:.2f} | |")
    # the shared machine's speed drifts over minutes (the same work takes 40% more CPU in
    # a loaded phase): the ratio of each run to the other checkout's run beside it cancels
    # the drift better than the ratio of the medians
    other = per_run[checkouts[1][1]]
    pair = np.array([a[0] / b[0] for a, b in zip(per_run[ROOT], other, strict=True)])
    print(
        f"\nrun-by-run frames/s ratios: median {np.median(pair):.2f}x, range "
        f"{pair.min():.2f}-{pair.max():.2f}; this checkout's runs "
        + ", ".join(f"{r[0]:.1f}" for r in per_run[ROOT])
    )


# runs `python -m mirage_cli ARGS...` and reports its own peak memory at exit (VmHWM: a
# child's rusage would count the parent's pages it was forked from)
PEAK = (
    "import atexit, runpy, sys\n"
    "def peak():\n"
    "    for line in open('/proc/self/status'):\n"
    "        if line.startswith('VmHWM:'):\n"
    "            print('peak_rss_kb', line.split()[1], file=sys.stderr)\n"
    "atexit.register(peak)\n"
    "sys.argv = ['mirage'] + sys.argv[1:]\n"
    "runpy.run_module('mirage_cli', run_name='__main__')\n"
)


def command_runs(model, video: Path, repeats: int, checkouts) -> dict:
    """`mirage track` end to end in a subprocess of each checkout, interleaved: per checkout
    a list of (frames/s of its summary, wall seconds including start-up and model loading,
    peak resident memory in MB, CPU seconds user + system), one per run."""
    res = {path: [] for _, path in checkouts}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "model.mirage"
        model.save(path)
        for _ in range(repeats):
            for _, root in checkouts:
                env = dict(ENV, PYTHONPATH=str(root))  # that checkout's package
                t0 = time.perf_counter()
                ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                p = subprocess.run(
                    [sys.executable, "-c", PEAK, "track", str(video), "--model", str(path),
                     "-o", str(Path(tmp) / "poses.csv")],
                    capture_output=True, text=True, cwd=root, env=env,
                )  # fmt: skip
                wall = time.perf_counter() - t0
                ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu = ru1.ru_utime + ru1.ru_stime - ru0.ru_utime - ru0.ru_stime
                text = p.stdout + p.stderr
                m = re.search(r"([0-9.]+) frames/s", text)
                kb = re.search(r"peak_rss_kb (\d+)", text)
                if p.returncode != 0 or m is None or kb is None:
                    raise SystemExit(f"mirage track ({root}) failed: {text.strip()[-300:]}")
                res[root].append((float(m.group(1)), wall, int(kb.group(1)) / 1024, cpu))
    return res


if __name__ == "__main__":
    main()
