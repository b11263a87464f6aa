"""Real-footage benchmark: every real set under ../shared/data/real/ that is present, plus a
forward-moving synthetic scene, x pose pipelines, one table.

A real set is a folder with `camera.yaml`, `keyframes/` (+ `keyframes/poses.csv`), `frames/`
and `truth.csv` (see ../shared/data/real/README.md). The model is built from the keyframes
with `build-model`'s defaults; the frames are tracked as an image folder. Every system gets
the same model and the same decoded frames (systems as in benchmarks/stress.py):

- mirage: `mirage track`'s loop with its defaults (smoothed);
- mirage --smooth 0: each frame's own pose;
- plain OpenCV: SIFT + FLANN + solvePnPRansac + LM, every frame;
- hloc-style: RootSIFT, mutual NN + ratio, pycolmap LO-RANSAC + refinement (needs pycolmap).

The forward-moving scene ("forward", rendered by `mirage synth --path forward`, cached in
benchmarks/.cache/) has a camera moving 25 cm towards and across the landmark with the
keyframes along the same path: a camera path that is not an orbit. It is scored twice for
mirage: built with the defaults, and with every view and every point kept (`--roi none
--spacing-deg 1`, the reference the defaults must stay within 1.2x of).

A wrong pose is an ok frame more than 10 cm or 5 deg off (real sets: 2.5% of the range or
5 deg, whichever is smaller in metres). Honesty = RMS error / RMS reported 1-sigma.

Each real set is also tracked with its frames shrunk 2x and 3x (`--shrink`): the
landmark then looks as from 2-3x further against the keyframes (the case for keyframe
patches), on real pixels.

    python benchmarks/real.py                     # every set present, every system
    python benchmarks/real.py --systems mirage,plain --sets dtu_scan37
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mirage_cli.runtime import blas_in_calling_thread  # noqa: E402

blas_in_calling_thread()  # before numpy loads: its BLAS in the calling thread, as `mirage` runs it

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from mirage_cli import __version__  # noqa: E402
from mirage_cli.build_model import ROI, BuildSettings, build_model, views_from_inputs  # noqa: E402
from mirage_cli.camera import Camera  # noqa: E402
from mirage_cli.frames import FrameSource  # noqa: E402
from mirage_cli.runtime import keep_freed_memory, opencv_threads_for_two_callers  # noqa: E402
from mirage_cli.trajectory import read_pose_csv, row_pose  # noqa: E402

keep_freed_memory()
REAL = ROOT.parent / "shared" / "data" / "real"
CACHE = Path(__file__).resolve().parent / ".cache"
WRONG_M, WRONG_DEG, WRONG_RANGE = 0.10, 5.0, 0.025


def _stress():
    spec = importlib.util.spec_from_file_location(
        "bench_stress", Path(__file__).with_name("stress.py")
    )
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def real_sets(names: list[str] | None) -> list[Path]:
    if not REAL.is_dir():
        return []
    found = sorted(
        d for d in REAL.iterdir()
        if (d / "camera.yaml").is_file() and (d / "keyframes" / "poses.csv").is_file()
        and (d / "frames").is_dir() and (d / "truth.csv").is_file()
    )  # fmt: skip
    return [d for d in found if names is None or d.name in names]


def _forward_pose(f: float, wobble: float = 0.0):
    """The forward path at f in [0, 1]: 25 cm towards and across the landmark, looking at
    it with the heading and tilt swinging by a few degrees (`wobble` scales the swing)."""
    from mirage_cli.pose import look_at, matrix_from_rpy
    from mirage_cli.synth import LANDMARK_TARGET

    C = np.array([1.30, -0.10, 0.50]) + f * np.array([-0.22, 0.22, -0.04])
    C = C + wobble * np.array([0.01 * np.sin(7 * f), 0.01 * np.sin(11 * f), 0.008 * np.sin(5 * f)])
    base = look_at(C, LANDMARK_TARGET)
    yaw = np.radians(3.0 * np.sin(2 * np.pi * f) * (0.5 + wobble))
    tilt = np.radians(2.0 * np.sin(3 * np.pi * f) * wobble)
    R_wc = base.R_wc @ matrix_from_rpy(tilt, yaw, 0.0)
    return base.from_center(R_wc, C)


def forward_scene(jobs: int = 1) -> Path:
    """The forward-moving synthetic scene (rendered once, cached): the sample's landmark
    and camera, 9 keyframes along the path (JPEG 95), 150 frames along it with a wobble."""
    out = CACHE / "forward-v1"
    if (out / "truth.csv").is_file():
        return out
    import shutil

    import cv2

    from mirage_cli import synth
    from mirage_cli.records import FrameRecord, Status
    from mirage_cli.render import Renderer, stable_rng
    from mirage_cli.trajectory import write_trajectory

    tmp = out.with_suffix(".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "keyframes").mkdir(parents=True)
    (tmp / "frames").mkdir()
    cam = synth.default_camera()
    cam.save(tmp / "camera.yaml")
    scene = synth.landmark_scene(0)
    kf_r, fr_r = Renderer(scene, cam, aa=2), Renderer(scene, cam, aa=1)
    kfs = []
    for k, f in enumerate(np.linspace(0, 1, 9)):
        pose = _forward_pose(f)
        img = kf_r.render(pose, 1.5, stable_rng(0, f"fw-kf-{k}"))
        cv2.imwrite(str(tmp / "keyframes" / f"kf_{k:03d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        kfs.append(FrameRecord(Status.OK, pose, f"kf_{k:03d}.jpg"))
    write_trajectory(tmp / "keyframes" / "poses.csv", kfs)
    rows = []
    for i, f in enumerate(np.linspace(0.02, 0.98, 150)):
        pose = _forward_pose(f, wobble=1.0)
        img = fr_r.render(pose, 1.5, stable_rng(0, f"fw-frame-{i}"))
        cv2.imwrite(str(tmp / "frames" / f"{i:06d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        rows.append(FrameRecord(Status.OK, pose, f"{i:06d}.jpg", i / 30.0))
    write_trajectory(tmp / "truth.csv", rows)
    tmp.rename(out)
    return out


def load(folder: Path):
    camera = Camera.load(folder / "camera.yaml")
    frames = [f.image for f in FrameSource([folder / "frames"]).frames()]
    truth = read_pose_csv(folder / "truth.csv")
    return camera, frames, truth


def shrunk(camera: Camera, frames: list, f: float):
    """The frames and their camera shrunk `f` times: the landmark looks as from `f` times
    further with the same camera, against keyframes at their own scale (the far family's
    situation, on real pixels; the model keeps its camera)."""
    w, h = round(camera.width / f), round(camera.height / f)
    small = [cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in frames]
    return camera.scaled(w, h), small


def model_for(folder: Path, camera: Camera, settings: BuildSettings):
    kf = folder / "keyframes"
    views = views_from_inputs([str(kf)], camera, settings, poses_csv=kf / "poses.csv")
    return build_model(views, camera, settings).model


def score(results, truth, seconds) -> dict:
    pe, re, rng, sp, sr = [], [], [], [], []
    n = len(results)
    ok = np.array([r[0] is not None for r in results])
    target = np.array([0.0, 0.0, 0.0])
    for i in np.flatnonzero(ok):
        p, sig_p, sig_r = results[i]
        t = row_pose(truth.iloc[i])
        pe.append(p.distance_to(t))
        re.append(p.angle_to(t))
        rng.append(np.linalg.norm(t.transform(target[None])[0]))
        sp.append(sig_p)
        sr.append(sig_r)
    pe, re, rng, sp, sr = map(np.array, (pe, re, rng, sp, sr))

    def honesty(err, sig):
        if not len(err) or not np.isfinite(sig).all():
            return np.nan
        return float(np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(sig**2)))

    lim = np.minimum(WRONG_M, WRONG_RANGE * rng) if len(rng) else rng
    return {
        "tracked": 100 * ok.mean(),
        "wrong": int(((pe > lim) | (re > WRONG_DEG)).sum()),
        "pos_med": np.median(pe) if len(pe) else np.nan,
        "pos_p95": np.percentile(pe, 95) if len(pe) else np.nan,
        "rot_med": np.median(re) if len(re) else np.nan,
        "rot_p95": np.percentile(re, 95) if len(re) else np.nan,
        "hon_pos": honesty(pe, sp),
        "hon_rot": honesty(re, sr),
        "fps": n / seconds,
    }


def main():
    st = _stress()
    systems_all = {**st.SYSTEMS, "extend": st.run_extended}  # (extend: on request)
    labels = {**st.SYSTEM_LABELS, "extend": "mirage --extend"}
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default=None, help="real sets by folder name (default: all)")
    ap.add_argument("--systems", default=",".join(st.SYSTEMS), help=", ".join(systems_all))
    ap.add_argument("--no-forward", action="store_true", help="skip the synthetic scene")
    ap.add_argument("--jobs", type=int, default=2, help="render processes (first run only)")
    ap.add_argument("--shrink", default="2,3", help="also each real set's frames shrunk by")
    args = ap.parse_args()
    systems = [s.strip() for s in args.systems.split(",") if s.strip()]
    bad = [s for s in systems if s not in systems_all]
    if bad:
        ap.error(f"unknown system {', '.join(bad)}")
    notes = []
    if "hloc" in systems:
        try:
            import pycolmap

            notes.append(f"pycolmap {pycolmap.__version__}")
        except ImportError:
            systems.remove("hloc")
            notes.append("hloc-style: not run, pycolmap is not installed (pip install pycolmap)")
    opencv_threads_for_two_callers()
    sets = real_sets(args.sets.split(",") if args.sets else None)
    if not sets:
        notes.append(f"no real set found under {REAL}")
    shrinks = [float(f) for f in args.shrink.split(",") if f.strip()]
    scenes = [(d.name, d, False, 1.0) for d in sets]
    scenes += [(f"{d.name} shrunk {f:g}x", d, False, f) for d in sets for f in shrinks]
    if not args.no_forward:
        scenes.append(("forward (synthetic)", forward_scene(args.jobs), True, 1.0))
    header = (
        "| scene | system | tracked % | wrong | pos median mm | pos p95 mm | rot median deg "
        "| rot p95 deg | honesty pos / rot | fps |"
    )
    lines = [header, "|" + "---|" * 10]
    models = {}
    for name, folder, synthetic, shrink in scenes:
        camera, frames, truth = load(folder)
        if folder not in models:
            models[folder] = model_for(folder, camera, BuildSettings())
        model = models[folder]
        if shrink != 1.0:  # a camera that far again (or that much coarser), real pixels
            camera, frames = shrunk(camera, frames, shrink)
        runs = [(s, systems_all[s], model, labels[s]) for s in systems]
        if synthetic and "mirage" in systems:
            full = BuildSettings(spacing_deg=1.0, roi=ROI("none"))
            runs.append(("all", systems_all["mirage"], model_for(folder, camera, full),
                         "mirage, every view and point"))  # fmt: skip
        kept = f"{len(model.keyframes)} keyframes, {len(model.points)} points"
        for _, fn, m, label in runs:
            t0 = time.perf_counter()
            res, sec = fn(frames, m, camera)
            del t0
            r = score(res, truth, sec)
            fmt = st.fmt
            lines.append(
                f"| {name} | {label} | {fmt(r['tracked'], '.1f')} | {r['wrong']} "
                f"| {fmt(1000 * r['pos_med'], '.2f')} | {fmt(1000 * r['pos_p95'], '.2f')} "
                f"| {fmt(r['rot_med'], '.3f')} | {fmt(r['rot_p95'], '.3f')} "
                f"| {fmt(r['hon_pos'], '.2f')} / {fmt(r['hon_rot'], '.2f')} "
                f"| {fmt(r['fps'], '.1f')} |"
            )
            print(lines[-1], file=sys.stderr, flush=True)
        notes.append(f"{name}: model of {kept}")
    print("\n".join(lines))
    print(f"\nmirage-cli {__version__}; " + "; ".join(notes))


if __name__ == "__main__":
    main()
