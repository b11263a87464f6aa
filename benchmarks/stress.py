"""Stress benchmark: hard scenes x pose pipelines, one table.

Scenes are rendered with `mirage synth` (cached under benchmarks/.cache/, keyed by the
scene's synth options, so later runs only track): a floor of repeated tiles with a
look-away, a pole passing in front of the landmark, look-alike opposite sides, motion
blur, far orbits at 2.5 m and 4 m from keyframes at 1.4 m (landmark ~70 px tall at 4 m),
twice the speed with its motion blur, heavy JPEG compression with noise, the tiled floor
with the pole seen from 2.5 m (the floor fills much of the view), auto-exposure hunting
(+-50% gain on the decoded frames), a near orbit at 0.9 m (the landmark overflows the
frame), keyframes from higher up than the video and the tiled floor from 4 m, plus the
committed sample orbit. Every system gets the same landmark model,
built from the scene's keyframes with `build-model`'s defaults, and the same decoded frames:

- mirage: our tracker with its default settings (`mirage track`: each pose smoothed with
  the 15 frames before and after it);
- mirage --smooth 0: the same tracker, each frame's own pose;
- plain OpenCV: benchmarks/track.py's SIFT + FLANN + solvePnPRansac + LM, every frame;
- hloc-style: RootSIFT, mutual nearest neighbour + ratio test against the keyframes near
  the previous pose (all keyframes when lost), matches gated within 60 px of the
  constant-velocity prediction while tracking, pycolmap's LO-RANSAC + refinement
  (`estimate_and_refine_absolute_pose`), and on relocalisation a second-hypothesis test
  (a distinct pose from the remaining matches with half the inliers or more: lost).

    python benchmarks/stress.py                       # all scenes, 120 frames each
    python benchmarks/stress.py --scenes pole,far4 --frames 120 --systems mirage,hloc
    python benchmarks/stress.py --render-only         # just render (cache) the scenes

Rendered scenes are 4 s at 30 fps (120 frames) going 0.6 turns around the landmark (54
deg/s, 1.8 deg per frame), the videos with one ray per pixel (`synth --aa 1`, 4x faster to
render; the keyframes keep 2x2). Rendering them the first time takes about 20 min on 2
free cores (`--jobs`); the tracking itself a few minutes. A wrong pose is an ok frame
more than 10 cm or 5 deg off; "in view" means at least 30% of the landmark's surface
samples project into the image (and are not behind the pole); "out of view": none do.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mirage_cli.runtime import blas_in_calling_thread  # noqa: E402

blas_in_calling_thread()  # before numpy loads: its BLAS in the calling thread, as `mirage` runs it

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from mirage_cli import __version__  # noqa: E402
from mirage_cli.build_model import BuildSettings, build_model, views_from_inputs  # noqa: E402
from mirage_cli.camera import Camera  # noqa: E402
from mirage_cli.features import detect, make_detector  # noqa: E402
from mirage_cli.frames import Frame, FrameSource  # noqa: E402
from mirage_cli.model import LandmarkModel  # noqa: E402
from mirage_cli.pipelines.track import extended_records, tracked_records  # noqa: E402
from mirage_cli.pose import Pose  # noqa: E402
from mirage_cli.runtime import keep_freed_memory, opencv_threads_for_two_callers  # noqa: E402
from mirage_cli.synth import LANDMARK_TARGET  # noqa: E402
from mirage_cli.tracking import Tracker, TrackSettings  # noqa: E402
from mirage_cli.tracking.smooth import SmoothSettings  # noqa: E402
from mirage_cli.trajectory import read_pose_csv, row_pose  # noqa: E402

keep_freed_memory()  # as `mirage track` runs (every system here gets it: one process)

SAMPLE = ROOT / "sample_data"
CACHE = Path(__file__).resolve().parent / ".cache"
CACHE_VERSION = 1  # bump when the renderer or the scene generator changes what it draws
IN_VIEW = 0.3
WRONG_M, WRONG_DEG = 0.10, 5.0
FPS = 30.0
TURNS_PER_S = 0.15  # 54 deg/s around the landmark, whatever --frames (the sample: 26 deg/s)


def _bench_track():
    """benchmarks/track.py, imported by path (its plain OpenCV pipeline is reused)."""
    spec = importlib.util.spec_from_file_location(
        "bench_track", Path(__file__).with_name("track.py")
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# --------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------
@dataclass
class SceneSpec:
    label: str
    keyframe_args: list[str] | None  # None: the committed sample keyframes
    orbit_args: list[str] = field(default_factory=list)
    look_away: tuple[float, float] | None = None  # as shares of the video length
    exposure: float = 0.0  # auto-exposure hunting: the decoded frames' gain swings by this


TILES = ["--floor-tiles", "0.75"]
SCENES = {
    "sample": SceneSpec("sample orbit (540 frames)", None),
    "floor": SceneSpec("floor tiles 0.75 m + look-away", TILES, TILES, (0.45, 0.70)),
    "pole": SceneSpec("pole in front (+ floor tiles)", TILES, TILES + ["--pole"]),
    "lookalike": SceneSpec("look-alike sides", ["--lookalike"], ["--lookalike"]),
    # no look-away here: squeezed into a 4 s video it is a 360 deg/s whip pan, whose 20-55 px
    # smear leaves no features to match (every system loses those frames); blur is the test
    "blur": SceneSpec(
        "blur 4 + noise 3", None, ["--motion-blur", "4", "--noise", "3", "--look-away", "0"]
    ),
    "far2.5": SceneSpec("far orbit 2.5 m", None, ["--video-radius", "2.5"]),
    "far4": SceneSpec("far orbit 4 m", None, ["--video-radius", "4.0"]),
    # twice the speed (3.6 deg a frame; the later --turns wins), blurred as such motion is
    "fast": SceneSpec(
        "fast 108 deg/s + blur 4",
        None,
        ["--turns", "1.2", "--motion-blur", "4", "--look-away", "0"],
    ),
    "lowq": SceneSpec("jpeg 50 + noise 6", None, ["--jpeg-quality", "50", "--noise", "6"]),
    "farpole": SceneSpec(
        "far 2.5 m + pole + tiles", TILES, TILES + ["--pole", "--video-radius", "2.5"]
    ),
    # the gain swings +-50% (1.5 s period) and steps down by a quarter halfway, applied to
    # the decoded frames of a plain orbit (OpenCV rounds and clips to 0-255 as a camera)
    "exposure": SceneSpec("auto-exposure +-50%", None, [], exposure=0.5),
    "near": SceneSpec("near orbit 0.9 m", None, ["--video-radius", "0.9"]),
    "high": SceneSpec("keyframes from 1.1 m high", ["--heights", "1.1"], []),
    "far4tiles": SceneSpec("far 4 m + tiles", TILES, TILES + ["--video-radius", "4.0"]),
}


def _synth(
    out: Path, args: list[str], jobs: int, version: int = CACHE_VERSION, nice: int = 10
) -> Path:
    """Render `mirage synth` into a cache folder named by its arguments and the cache
    `version` of what draws them (atomic); `nice` 0 renders at normal priority."""
    key = hashlib.sha1(repr((version, args)).encode()).hexdigest()[:12]
    folder = CACHE / f"{out.name}-{key}"
    if (folder / "done").is_file():
        return folder
    tmp = folder.with_name(folder.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    cmd = [sys.executable, "-m", "mirage_cli", "-q", "synth", str(tmp), "--jobs", str(jobs)]
    print(f"rendering {folder.name}: mirage synth {' '.join(args)}", file=sys.stderr)
    subprocess.run(["nice", "-n", str(nice), *cmd, *args], check=True, cwd=ROOT)
    (tmp / "done").write_text(" ".join(args) + "\n")
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)
    return folder


def scene_data(name: str, frames: int, jobs: int) -> tuple[Path, Path]:
    """(folder with orbit.mp4 + orbit_truth.csv, keyframes folder) of a scene."""
    spec = SCENES[name]
    if name == "sample":
        return SAMPLE, SAMPLE / "keyframes"
    kf = SAMPLE / "keyframes"
    if spec.keyframe_args is not None:
        kf = _synth(Path("keyframes"), ["--only", "keyframes", *spec.keyframe_args], jobs)
        kf = kf / "keyframes"
    duration = frames / FPS
    args = ["--only", "orbit", "--duration", f"{duration:.4f}"]
    args += ["--turns", f"{TURNS_PER_S * duration:.4f}", "--aa", "1", *spec.orbit_args]
    if spec.look_away:
        a, b = spec.look_away
        args += ["--look-away", f"{a * duration:.3f},{b * duration:.3f}"]
    return _synth(Path(name), args, jobs), kf


def load_frames(video: Path, exposure: float = 0.0) -> tuple[list[np.ndarray], float]:
    t0 = time.perf_counter()
    frames = [f.image for f in FrameSource([video]).frames()]
    rate = len(frames) / (time.perf_counter() - t0)
    if exposure:
        n = len(frames)
        for i, img in enumerate(frames):
            gain = (1 + exposure * np.sin(2 * np.pi * i / FPS / 1.5)) * (
                1.0 if i < n // 2 else 1 - exposure / 2
            )
            frames[i] = cv2.convertScaleAbs(img, alpha=gain)
    return frames, rate


def get_model(keyframes: Path, camera: Camera) -> LandmarkModel:
    s = BuildSettings()
    views = views_from_inputs([str(keyframes)], camera, s, poses_csv=keyframes / "poses.csv")
    return build_model(views, camera, s).model


# --------------------------------------------------------------------------------------
# systems: each returns per frame (pose or None, sigma_pos_m, sigma_rot_deg) and seconds
# --------------------------------------------------------------------------------------
def run_mirage(frames, model, camera, lag=SmoothSettings.lag, tracker=None):
    """`mirage track`'s loop (the tracker, then the smoother) with its default settings,
    frames in memory (`tracker`: one made by the caller)."""
    tr = Tracker(model, camera, TrackSettings()) if tracker is None else tracker
    held = (Frame(i, i, i / FPS, f) for i, f in enumerate(frames))
    t0 = time.perf_counter()
    recs = tracked_records(held, tr, SmoothSettings(lag=lag))
    out = [(r.pose if r.ok else None, r.sigma_pos_m, r.sigma_rot_deg) for r in recs]
    return out, time.perf_counter() - t0


def run_extended(frames, model, camera, tracker=None):
    """`mirage track --extend` (pipelines.track.extended_records): both passes and the
    model's build timed; not among `SYSTEMS` (generalize.py and real.py offer it)."""
    tr = Tracker(model, camera, TrackSettings()) if tracker is None else tracker

    def again():
        return (Frame(i, i, i / FPS, f) for i, f in enumerate(frames))

    t0 = time.perf_counter()
    recs, _ = extended_records(again, tr)
    out = [(r.pose if r.ok else None, r.sigma_pos_m, r.sigma_rot_deg) for r in recs]
    return out, time.perf_counter() - t0


def run_unsmoothed(frames, model, camera):
    """`mirage track --smooth 0`: each frame's own pose."""
    return run_mirage(frames, model, camera, lag=0)


def run_plain(frames, model, camera):
    poses, sec = _bench_track().run_plain_opencv(frames, model, camera)
    return [(p, np.nan, np.nan) for p in poses], sec


def rootsift(d: np.ndarray) -> np.ndarray:
    """Arandjelovic & Zisserman's RootSIFT: L1-normalise, square root (unit L2 norm)."""
    d = np.asarray(d, np.float32)
    return np.sqrt(d / (np.abs(d).sum(axis=1, keepdims=True) + 1e-12))


def mutual_ratio_match(q: np.ndarray, t: np.ndarray, ratio: float = 0.8):
    """Mutual nearest neighbours that also pass the ratio test (unit-norm descriptors)."""
    if len(q) < 2 or len(t) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    s = q @ t.T
    top2 = np.argpartition(-s, 1, axis=1)[:, :2]
    s2 = np.take_along_axis(s, top2, axis=1)
    first = np.argmax(s2, axis=1)
    best = top2[np.arange(len(q)), first]
    d1 = np.sqrt(np.maximum(2 - 2 * s2.max(axis=1), 0))
    d2 = np.sqrt(np.maximum(2 - 2 * s2.min(axis=1), 0))
    mutual = np.argmax(s, axis=0)[best] == np.arange(len(q))
    keep = mutual & (d1 < ratio * d2)
    return np.flatnonzero(keep), best[keep]


class HlocStyle:
    """A careful hloc-style localiser/tracker on the same model (see the module doc)."""

    def __init__(self, model: LandmarkModel, camera: Camera, gate_px=60.0, ransac_px=4.0):
        import pycolmap

        self.pycolmap, self.model, self.camera = pycolmap, model, camera
        self.detector = make_detector(model.detector)
        d = np.zeros(8)
        d[: min(8, camera.dist.size)] = camera.dist.ravel()[:8]
        fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
        if np.any(d[4:]):
            params = [fx, fy, cx, cy, *d[:2], *d[2:4], d[4], *d[5:8]]
            cam_model = "FULL_OPENCV"
        else:
            params, cam_model = [fx, fy, cx, cy, *d[:4]], "OPENCV"
        self.pcam = pycolmap.Camera(
            model=cam_model, width=camera.width, height=camera.height, params=params
        )
        self.opts = pycolmap.AbsolutePoseEstimationOptions()
        self.opts.ransac.max_error = ransac_px
        self.opts.ransac.random_seed = 0
        self.gate_px, self.min_inliers = gate_px, 15
        X, D, K = [], [], []
        for k, kf in enumerate(model.keyframes):
            _, desc, pid = kf.linked()
            X.append(model.points[pid])
            D.append(rootsift(desc))
            K.append(np.full(len(pid), k))
        self.X, self.D, self.kf = np.concatenate(X), np.concatenate(D), np.concatenate(K)
        self.prev: list[Pose] = []  # the last ok poses of consecutive frames

    def _estimate(self, uv, X):
        r = self.pycolmap.estimate_and_refine_absolute_pose(
            uv, X, self.pcam, self.opts, return_covariance=True
        )
        if r is None or r["num_inliers"] < self.min_inliers:
            return None
        cfw = r["cam_from_world"]
        pose = Pose(cfw.rotation.matrix(), np.asarray(cfw.translation))
        inl = np.asarray(r["inlier_mask"], bool)
        return pose, inl, np.asarray(r["covariance"])

    def _sigmas(self, pose, cov, uv, X):
        """pycolmap's covariance assumes 1 px noise: scale by the residual variance, then
        the camera centre's (C = -R^T t, left rotation perturbation) RMS and the angle's."""
        res = self.camera.project(X, pose) - uv
        s2 = float((res**2).sum()) / max(2 * len(uv) - 6, 1)
        R, t = pose.R, pose.t
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        J = np.hstack([-R.T @ tx, -R.T])
        c = J @ cov @ J.T * s2
        return float(np.sqrt(np.trace(c))), float(np.degrees(np.sqrt(np.trace(cov[:3, :3]) * s2)))

    def process(self, gray):
        kps, desc = detect(gray, self.detector)
        if desc is None or len(kps) < self.min_inliers:
            self.prev = []
            return None, np.nan, np.nan
        q = rootsift(desc)
        tracking = bool(self.prev)
        if tracking:
            near = self.model.nearest_keyframes(self.prev[-1], 4)
            sel = np.flatnonzero(np.isin(self.kf, near))
        else:
            sel = np.arange(len(self.X))
        qi, ti = mutual_ratio_match(q, self.D[sel])
        uv, X = kps[qi].astype(np.float64), self.X[sel[ti]]
        if tracking:
            pred = self.prev[-1]
            if len(self.prev) > 1:  # constant velocity: T_k+1 = T_k T_k-1^-1 T_k
                a, b = self.prev[-2], self.prev[-1]
                dR = b.R @ a.R.T
                pred = Pose(dR @ b.R, dR @ b.t + (b.t - dR @ a.t))
            front = pred.transform(X)[:, 2] > 0
            near_px = np.full(len(X), False)
            if front.any():
                proj = self.camera.project(X[front], pred)
                near_px[front] = np.linalg.norm(proj - uv[front], axis=1) < self.gate_px
            uv, X = uv[near_px], X[near_px]
        if len(uv) < self.min_inliers:
            self.prev = []
            return None, np.nan, np.nan
        first = self._estimate(uv, X)
        if first is None:
            self.prev = []
            return None, np.nan, np.nan
        pose, inl, cov = first
        if not tracking:  # relocalisation: is there a distinct second explanation?
            rest = ~inl
            if rest.sum() >= self.min_inliers:
                second = self._estimate(uv[rest], X[rest])
                if (
                    second is not None
                    and second[1].sum() >= 0.5 * inl.sum()
                    and (
                        second[0].distance_to(pose) > WRONG_M
                        or second[0].angle_to(pose) > WRONG_DEG
                    )
                ):
                    self.prev = []
                    return None, np.nan, np.nan
        if pose.transform(LANDMARK_TARGET[None])[0, 2] <= 0:
            self.prev = []
            return None, np.nan, np.nan
        sp, sr = self._sigmas(pose, cov, uv[inl], X[inl])
        self.prev = (self.prev + [pose])[-2:]
        return pose, sp, sr


def run_hloc(frames, model, camera):
    h = HlocStyle(model, camera)
    out = []
    t0 = time.perf_counter()
    for f in frames:
        out.append(h.process(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)))
    return out, time.perf_counter() - t0


SYSTEMS = {"mirage": run_mirage, "unsmoothed": run_unsmoothed, "plain": run_plain,
           "hloc": run_hloc}  # fmt: skip
SYSTEM_LABELS = {"mirage": "mirage (default)", "unsmoothed": "mirage --smooth 0",
                 "plain": "plain OpenCV", "hloc": "hloc-style"}  # fmt: skip


# --------------------------------------------------------------------------------------
# scoring and the table
# --------------------------------------------------------------------------------------
def score(results, truth, seconds) -> dict:
    vis = truth["landmark_visible"].to_numpy()
    n = len(results)
    ok = np.array([r[0] is not None for r in results])
    pe, re, rng, sp, sr = [], [], [], [], []
    for i in np.flatnonzero(ok):
        p, sig_p, sig_r = results[i]
        t = row_pose(truth.iloc[i])
        pe.append(p.distance_to(t))
        re.append(p.angle_to(t))
        rng.append(np.linalg.norm(t.center - LANDMARK_TARGET))
        sp.append(sig_p)
        sr.append(sig_r)
    pe, re, rng, sp, sr = map(np.array, (pe, re, rng, sp, sr))
    inview = vis[:n] >= IN_VIEW

    def honesty(err, sig):
        if not len(err) or not np.isfinite(sig).all():
            return np.nan
        return float(np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(sig**2)))

    return {
        "tracked": 100 * ok[inview].mean() if inview.any() else np.nan,
        "ok_out": int((ok & (vis[:n] == 0)).sum()),
        "wrong": int(((pe > WRONG_M) | (re > WRONG_DEG)).sum()),
        "pos_med": np.median(pe) if len(pe) else np.nan,
        "pos_p95": np.percentile(pe, 95) if len(pe) else np.nan,
        "pct_med": np.median(100 * pe / rng) if len(pe) else np.nan,
        "rot_med": np.median(re) if len(re) else np.nan,
        "hon_pos": honesty(pe, sp),
        "hon_rot": honesty(re, sr),
        "fps": n / seconds,
    }


def fmt(v, spec):
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES), help=f"of {', '.join(SCENES)}")
    ap.add_argument("--systems", default=",".join(SYSTEMS), help=f"of {', '.join(SYSTEMS)}")
    ap.add_argument("--frames", type=int, default=120, help="frames per rendered scene")
    ap.add_argument("--jobs", type=int, default=2, help="render processes (first run only)")
    ap.add_argument("--render-only", action="store_true", help="render (cache) the scenes, stop")
    args = ap.parse_args()
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    systems = [s.strip() for s in args.systems.split(",") if s.strip()]
    bad = [s for s in scenes if s not in SCENES] + [s for s in systems if s not in SYSTEMS]
    if bad:
        ap.error(f"unknown scene/system {', '.join(bad)}")
    notes = []
    if "hloc" in systems:
        try:
            import pycolmap

            notes.append(f"pycolmap {pycolmap.__version__}")
        except ImportError:
            systems.remove("hloc")
            notes.append("hloc-style: not run, pycolmap is not installed (pip install pycolmap)")
    opencv_threads_for_two_callers()  # as `mirage track` sizes it (every system here)
    camera = Camera.load(SAMPLE / "camera_truth.yaml")
    data = {s: scene_data(s, args.frames, args.jobs) for s in scenes}  # render first
    if args.render_only:
        for s, (folder, kf) in data.items():
            print(f"{s}: {folder} (keyframes {kf})")
        return
    header = (
        "| scene | system | tracked in view % | ok out of view | wrong poses | pos median m "
        "| pos median % range | pos p95 m | rot median deg | honesty pos / rot | fps |"
    )
    lines = [header, "|" + "---|" * 11]
    decode = {}
    for s in scenes:
        folder, kf = data[s]
        truth = read_pose_csv(folder / "orbit_truth.csv")
        frames, decode[s] = load_frames(folder / "orbit.mp4", SCENES[s].exposure)
        model = get_model(kf, camera)
        for sy in systems:
            res, sec = SYSTEMS[sy](frames, model, camera)
            r = score(res, truth, sec)
            lines.append(
                f"| {SCENES[s].label} | {SYSTEM_LABELS[sy]} | {fmt(r['tracked'], '.1f')} "
                f"| {r['ok_out']} | {r['wrong']} | {fmt(r['pos_med'], '.4f')} "
                f"| {fmt(r['pct_med'], '.3f')} | {fmt(r['pos_p95'], '.4f')} "
                f"| {fmt(r['rot_med'], '.3f')} | {fmt(r['hon_pos'], '.2f')} / "
                f"{fmt(r['hon_rot'], '.2f')} | {fmt(r['fps'], '.1f')} |"
            )
            print(lines[-1], file=sys.stderr, flush=True)
        del frames
    print("\n".join(lines))
    dec = ", ".join(f"{s} {v:.0f}" for s, v in decode.items())
    print(
        f"\nmirage-cli {__version__}; {args.frames} frames per rendered scene at 30 fps, "
        f"640x480; fps excludes decoding (decode-only frames/s: {dec}); honesty = RMS error / "
        "RMS reported 1-sigma over ok frames (hloc-style: pycolmap's covariance scaled by the "
        "residual variance; plain OpenCV reports none)" + ("; " + "; ".join(notes) if notes else "")
    )


if __name__ == "__main__":
    main()
