"""Throughput off the sample: `mirage track` on footage it was not tuned on.

For each scene of a matrix (640x480 / 1080p / 4K x normal / weak texture / dusk / from
above, and models of 18-144 keyframes of the same landmark), `mirage track` runs as a user
runs it, in a subprocess: frames/s by its summary, wall seconds from start (model loading
included), seconds to the first pose (`--end 1`), peak memory, the CPU time per frame after
the first pose and how many cores it kept busy (CPU over wall time), the share of in-view
frames that needed a full detection (detect / relocalise rows of the CSV), accuracy against the
truth (median error, wrong poses over 10 cm or 5 deg). The plain OpenCV peer
(benchmarks/track.py: SIFT + FLANN against every model point + solvePnPRansac, no
temporal tracking) tracks the same video in this process for the speed ratio.

The 1080p and 4K videos film the sample landmark with a camera of square pixels whose focal
length is 2.25x / 4.5x the model's (a sharper camera than the keyframes'): the model is
the 640x480 keyframes' throughout. Rendered scenes and built models are cached
(benchmarks/.cache).

    python benchmarks/throughput.py                    # the matrix (renders once: ~1 h)
    python benchmarks/throughput.py --scenes 480-normal,1080-normal --no-peer
    python benchmarks/throughput.py --scenes 1080-normal --repeats 3 --against /tmp/old

`--against` runs another checkout's `mirage track` on the same video and model, interleaved
with this checkout's runs, and prints the median of the run-by-run frames/s ratios.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mirage_cli.runtime import blas_in_calling_thread  # noqa: E402

blas_in_calling_thread()  # before numpy loads, as `mirage` runs

import numpy as np  # noqa: E402


def _load(name: str):
    """A sibling benchmark script, imported by path."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / f"benchmarks/{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[f"bench_{name}"] = mod
    spec.loader.exec_module(mod)
    return mod


stress = _load("stress")
bench_track = stress._bench_track()

from mirage_cli.camera import Camera  # noqa: E402
from mirage_cli.frames import FrameSource  # noqa: E402
from mirage_cli.model import LandmarkModel  # noqa: E402
from mirage_cli.synth import default_camera  # noqa: E402
from mirage_cli.trajectory import read_pose_csv, row_pose  # noqa: E402

CACHE_VERSION = 1
FPS = 30.0
IN_VIEW = 0.3
CONDITIONS = {  # orbit options of `mirage synth`, keyframe options (None: the sample's)
    "normal": ([], None),
    "weak": (["--weak-texture"], ["--weak-texture"]),
    "dusk": (["--dusk"], None),
    "above": (["--video-height", "2.2"], None),
}
HEIGHTS = {"480": 480, "1080": 1080, "4k": 2160}
MODELS = {18: "20", 36: None, 72: "5", 144: "2.5"}  # keyframes: --keyframe-step
DEFAULT_SCENES = (
    "480-normal,480-weak,480-dusk,480-above,1080-normal,1080-weak,1080-dusk,1080-above,"
    "4k-normal,480-normal@18,480-normal@72,480-normal@144"
)


def video_camera(height: int) -> Camera:
    """The sample's webcam at `height` rows, 16:9 above 480, square pixels: the focal
    length grows with the rows (a sharper camera than the model's)."""
    cam = default_camera()
    if height == 480:
        return cam
    s, w = height / 480, round(height * 16 / 9)
    K = np.array([[cam.K[0, 0] * s, 0, (w - 1) / 2], [0, cam.K[0, 0] * s, (height - 1) / 2],
                  [0, 0, 1.0]])  # fmt: skip
    return Camera(K, cam.dist.copy(), w, height)


def scene(name: str, seconds: float, jobs: int) -> tuple[Path, Path, Path]:
    """(video folder, keyframes folder, camera YAML) of a scene 'RES-CONDITION[@KEYFRAMES]'."""
    res, _, kfs = name.partition("@")
    height, cond = res.split("-")
    orbit, kf_args = CONDITIONS[cond]
    step = MODELS[int(kfs)] if kfs else None
    kf = stress.SAMPLE / "keyframes"
    if kf_args is not None or step is not None:
        args = ["--only", "keyframes", *(kf_args or [])]
        args += ["--keyframe-step", step] if step else []
        kf = stress._synth(Path("tp-keyframes"), args, jobs, CACHE_VERSION, nice=0) / "keyframes"
    args = ["--only", "orbit", "--duration", f"{seconds:g}", "--aa", "1", *orbit]
    if height != "480":  # the video's own camera, written once (relative: a stable key)
        cam = stress.CACHE / f"tp-camera-{height}.yaml"
        if not cam.is_file():
            stress.CACHE.mkdir(parents=True, exist_ok=True)
            video_camera(HEIGHTS[height]).save(cam)
        args += ["--camera", str(cam.relative_to(ROOT))]
    folder = stress._synth(Path(f"tp-{res}"), args, jobs, CACHE_VERSION, nice=0)
    return folder, kf, folder / "camera_truth.yaml"


def model_for(keyframes: Path, spacing: str | None) -> tuple[Path, float, float]:
    """The keyframes' model, built with their own camera and every keyframe kept
    (`--spacing-deg` their step), cached; and its build's wall seconds and peak MB."""
    name = keyframes.parent.name if keyframes.parent != stress.SAMPLE else "sample"
    path = stress.CACHE / f"tp-model-{name}.mirage"
    stats = path.with_suffix(".build")
    if not stats.is_file():
        argv = ["build-model", str(keyframes), "--poses", str(keyframes / "poses.csv")]
        argv += ["--camera", str(keyframes.parent / "camera_truth.yaml"), "-o", str(path)]
        argv += ["--spacing-deg", spacing] if spacing else []
        _, wall, mb, _ = run_cli(ROOT, argv)
        stats.write_text(f"{wall} {mb}\n")
    wall, mb = (float(v) for v in stats.read_text().split())
    return path, wall, mb


def run_cli(root: Path, argv: list[str]) -> tuple[str, float, float, float]:
    """`mirage ARGV` of the checkout at `root` in a subprocess: (its output, wall seconds
    from start, peak resident MB, CPU seconds of all its threads, user + system)."""
    env = dict(os.environ, PYTHONPATH=str(root))
    t0 = time.perf_counter()
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([sys.executable, "-c", bench_track.PEAK, *argv],
                       capture_output=True, text=True, cwd=root, env=env)  # fmt: skip
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    if p.returncode != 0:
        raise SystemExit(f"mirage {' '.join(argv[:2])} failed:\n{p.stderr[-2000:]}")
    kb = re.search(r"peak_rss_kb (\d+)", p.stderr)
    return p.stdout + p.stderr, wall, int(kb.group(1)) / 1024 if kb else float("nan"), cpu


def track_row(root: Path, video: Path, model: Path, camera: Path, truth) -> dict:
    """One `mirage track` run: its figures and the CSV's against the truth."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "poses.csv"
        argv = ["track", str(video), "--model", str(model), "--camera", str(camera)]
        text, wall, mb, cpu = run_cli(root, [*argv, "-o", str(out)])
        rows = read_pose_csv(out)
        ok = np.flatnonzero(rows["status"].to_numpy() == "ok")
        # the wall time of a run that stops at the first ok pose: start-up, model, search
        n0 = int(ok[0]) + 1 if len(ok) else 1
        _, first, _, cpu0 = run_cli(
            root, [*argv, "-o", str(Path(tmp) / "first.csv"), "--end", str(n0)]
        )
    # CPU after the first pose, per frame and per second of wall time: how much of two
    # cores the tracking keeps busy (2 on a 2-core machine: bound by CPU, not by waiting)
    frames = max(len(rows) - n0, 1)
    cpu_ms = 1000 * (cpu - cpu0) / frames
    cores = (cpu - cpu0) / max(wall - first, 1e-9)
    fps = float(re.search(r"throughput ([\d.]+) frames/s", text).group(1))
    vis = truth["landmark_visible"].to_numpy()[: len(rows)]
    inview = vis >= IN_VIEW
    full = rows["mode"].isin(["detect", "relocalise"]).to_numpy()
    # steady: in view and at least a second from any frame with the landmark out of view
    # (leaving and finding it again takes detections whatever the footage)
    near = np.convolve(vis < IN_VIEW, np.ones(61), mode="same") > 0
    err, wrong = [], 0
    for i in np.flatnonzero(rows["status"].to_numpy() == "ok"):
        t, p = row_pose(truth.iloc[i]), row_pose(rows.iloc[i])
        e = p.distance_to(t)
        wrong += int(e > 0.10 or p.angle_to(t) > 5.0 or vis[i] == 0)
        err.append(e)
    ok_in = (rows["status"].to_numpy() == "ok")[inview]
    return {
        "fps": fps, "wall": wall, "first": first, "mb": mb, "cpu_ms": cpu_ms, "cores": cores,
        "full": 100 * full[inview].mean(), "steady": 100 * full[~near].mean(),
        "tracked": 100 * ok_in.mean(),
        "med_mm": 1000 * float(np.median(err)) if err else float("nan"), "wrong": wrong,
    }  # fmt: skip


def peer_fps(video: Path, model: Path, camera: Path, frames: int) -> float:
    """The plain OpenCV pipeline over the first `frames` frames, decoded as it goes (as
    `mirage track` decodes), in this process."""
    m, cam = LandmarkModel.load(model), Camera.load(camera)
    images = (f.image for f in FrameSource([video]).frames(end=frames))
    t0 = time.perf_counter()
    poses, _ = bench_track.run_plain_opencv(images, m, cam)
    return len(poses) / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--scenes",
        default=DEFAULT_SCENES,
        help="comma-separated RES-CONDITION[@KEYFRAMES]: RES 480 | 1080 | 4k, "
        "CONDITION normal | weak | dusk | above, KEYFRAMES 18 | 36 | 72 | 144",
    )
    ap.add_argument("--seconds", type=float, default=10.0, help="video length (30 frames/s)")
    ap.add_argument("--repeats", type=int, default=1, help="runs per scene (median)")
    ap.add_argument("--against", type=Path, help="another checkout, run interleaved")
    ap.add_argument("--no-peer", action="store_true", help="skip the plain OpenCV peer")
    ap.add_argument("--peer-frames", type=int, default=150, help="frames the peer tracks")
    ap.add_argument("--jobs", type=int, default=2, help="render processes")
    args = ap.parse_args()  # fmt: skip
    names = [n.strip() for n in args.scenes.split(",") if n.strip()]
    for n in names:
        res, _, kfs = n.partition("@")
        h, _, cond = res.partition("-")
        if h not in HEIGHTS or cond not in CONDITIONS or (kfs and kfs not in map(str, MODELS)):
            ap.error(f"unknown scene {n!r}")
    roots = [ROOT] + ([args.against.resolve()] if args.against else [])
    print(f"throughput, {args.seconds:g} s videos; median of {args.repeats} run(s)\n")
    print(
        "| scene | frames/s | wall s | first pose s | peak MB | CPU ms per frame / cores busy "
        "| full detections % of in view / steady | tracked in view % | median error mm | wrong "
        "| peer frames/s | ratio |"
        + (" vs --against: frames/s ratio, its first pose s |" if args.against else "")
    )
    print("|---" * (12 + bool(args.against)) + "|")
    for name in names:
        _row(name, args, roots)


def _row(name: str, args, roots: list[Path]) -> None:
    video, kf, cam = scene(name, args.seconds, args.jobs)
    kfs = name.partition("@")[2]
    model, build_s, build_mb = model_for(kf, MODELS[int(kfs)] if kfs else None)
    truth = read_pose_csv(video / "orbit_truth.csv")
    runs = {r: [] for r in roots}
    for _ in range(max(1, args.repeats)):
        for r in roots:
            runs[r].append(track_row(r, video / "orbit.mp4", model, cam, truth))
    med = {k: float(np.median([x[k] for x in runs[ROOT]])) for k in runs[ROOT][0]}
    peer = float("nan") if args.no_peer else peer_fps(
        video / "orbit.mp4", model, cam, args.peer_frames
    )  # fmt: skip
    nk = len(LandmarkModel.load(model).keyframes)
    line = (
        f"| {name} ({nk} kf; build {build_s:.0f} s, {build_mb:.0f} MB) | {med['fps']:.1f} "
        f"| {med['wall']:.1f} | {med['first']:.2f} | {med['mb']:.0f} "
        f"| {med['cpu_ms']:.1f} / {med['cores']:.2f} | {med['full']:.1f} / "
        f"{med['steady']:.1f} "
        f"| {med['tracked']:.1f} | {med['med_mm']:.2f} | {med['wrong']:.0f} | {peer:.1f} "
        f"| {med['fps'] / peer:.1f}x |"
    )
    if args.against:
        pair = [a["fps"] / b["fps"] for a, b in zip(runs[ROOT], runs[roots[1]], strict=True)]
        first = np.median([b["first"] for b in runs[roots[1]]])
        line += f" {np.median(pair):.2f}x, {first:.2f} s |"
    print(line, flush=True)


if __name__ == "__main__":
    main()
