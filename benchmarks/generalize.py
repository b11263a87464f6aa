"""Generalisation benchmark: random scene families, tuning seeds apart from report seeds.

Every scene is drawn at random by `mirage synth --random SEED --family F` (the landmark,
photographs on its faces, floor, light drift, occluder, blur, noise, camera intrinsics and
distortion, keyframe and video distances and heights; see mirage_cli/families.py), rendered
once and cached under benchmarks/.cache/. Each system gets the same model, built from the
scene's keyframes with `build-model`'s defaults and the scene's true camera, and the same
decoded frames (systems as in benchmarks/stress.py: mirage with its defaults, the plain
OpenCV pipeline, the hloc-style pipeline; `extend`: `mirage track --extend`, the model
grown by the frames tracked well from new views and the rest tracked again).

Seeds 0-99 are for tuning; seeds 1000-1029 are the report seeds, not looked at while
developing. A wrong pose is an ok frame more than 10 cm or 5 deg off (far family: more
than 2.5% of the range or 5 deg). "In view": at least 30% of the landmark's surface
samples project into the image and are not behind the occluder; "out of view": none do.
Honesty = RMS error / RMS reported 1-sigma over ok frames (pooled over a family's seeds,
and its worst seed). Each system's rows are repeated for the scenes whose landmark has a
drum and for those of boxes alone. `--systems hinted` runs mirage with the true pose (5 cm
and 1 deg off) as its hint whenever it holds no pose: what it would track if finding the
landmark were solved (a diagnostic, not a system).

    python benchmarks/generalize.py                        # report seeds, every family
    python benchmarks/generalize.py --seeds tune --count 10 --systems mirage
    python benchmarks/generalize.py --families far --seeds 3,7 --per-seed
    python benchmarks/generalize.py --render-only          # render (cache) the scenes
    python benchmarks/generalize.py --seeds tune --systems mirage,hinted   # search or track?
    python benchmarks/generalize.py --families near --seeds 0-47 --set max_sigma_range=0.02

Scenes are 150 frames (5 s at 30 fps); rendering one takes ~10-15 s on 2 cores, the
first full report run ~20 min of rendering; the peers run on the first 10 report seeds
of each family (--peer-seeds) so that a full run stays under an hour on 2 cores.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mirage_cli.runtime import blas_in_calling_thread  # noqa: E402

blas_in_calling_thread()  # before numpy loads: its BLAS in the calling thread, as `mirage`

import numpy as np  # noqa: E402
import yaml  # noqa: E402


def _stress():
    """benchmarks/stress.py, imported by path (its systems, loaders and model set-up)."""
    spec = importlib.util.spec_from_file_location("bench_stress", ROOT / "benchmarks/stress.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bench_stress"] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


stress = _stress()

from mirage_cli import __version__  # noqa: E402
from mirage_cli.camera import Camera  # noqa: E402
from mirage_cli.families import FAMILIES  # noqa: E402
from mirage_cli.pose import Pose, rodrigues  # noqa: E402
from mirage_cli.runtime import opencv_threads_for_two_callers  # noqa: E402
from mirage_cli.trajectory import read_pose_csv, row_pose  # noqa: E402

CACHE = ROOT / "benchmarks" / ".cache"
CACHE_VERSION = 2  # bump when mirage_cli/families.py or the renderer changes what it draws
TUNE_SEEDS = range(0, 100)
REPORT_SEEDS = range(1000, 1030)
FPS = 30.0
IN_VIEW = 0.3
WRONG_M, WRONG_DEG, WRONG_FAR_SHARE = 0.10, 5.0, 0.025
SYSTEMS = ("mirage", "extend", "plain", "hloc", "hinted")


def scene_folder(family: str, seed: int, frames: int, jobs: int) -> Path:
    """The rendered scene (keyframes/, orbit.mp4, orbit_truth.csv, scene.yaml), cached."""
    args = ["--random", str(seed), "--family", family, "--only", "keyframes,orbit"]
    args += ["--duration", f"{frames / FPS:.4f}", "--fps", f"{FPS:g}", "--aa", "1"]
    # normal priority: niced, renders starved behind the test suite (4 min a scene)
    return stress._synth(Path(f"{family}{seed}"), args, jobs, version=CACHE_VERSION, nice=0)


def score(results, truth, target, far: bool, seconds: float) -> dict:
    """Per-frame errors of one system on one scene and its summary figures."""
    vis = truth["landmark_visible"].to_numpy()[: len(results)]
    ok = np.array([r[0] is not None for r in results])
    idx = np.flatnonzero(ok)
    pe, re, rng, sp, sr = (np.zeros(len(idx)) for _ in range(5))
    for k, i in enumerate(idx):
        p, sp[k], sr[k] = results[i]
        t = row_pose(truth.iloc[i])
        pe[k], re[k] = p.distance_to(t), p.angle_to(t)
        rng[k] = np.linalg.norm(t.center - target)
    limit = WRONG_FAR_SHARE * rng if far else WRONG_M
    inview = vis >= IN_VIEW
    return {
        "tracked": 100 * ok[inview].mean() if inview.any() else np.nan,
        "ok_out": int((ok & (vis == 0)).sum()),
        "wrong": int(((pe > limit) | (re > WRONG_DEG)).sum()),
        "pe": pe,
        "re": re,
        "pct": 100 * pe / np.maximum(rng, 1e-9),
        "sp": sp,
        "sr": sr,
        "fps": len(results) / seconds,
    }


def honesty(err, sig) -> float:
    if not len(err) or not np.isfinite(sig).all():
        return np.nan
    return float(np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(sig**2)))


HINT_M, HINT_DEG = 0.05, 1.0  # the hinted run's hint: the truth this far off (RMS)


class HintedTracker(stress.Tracker):
    """mirage's tracker given, whenever it holds no pose, the true pose HINT_M / HINT_DEG
    off as its hint (where the last frame's uncertain pose would say to look): what the
    tracking would give if finding the landmark were solved, so that a family's lost
    frames split into the search's and the tracking's."""

    def __init__(self, model, camera, truth, settings, seed: int = 0):
        super().__init__(model, camera, settings)
        self._truth, self._rng = truth, np.random.default_rng(seed)

    def process(self, gray, ahead=()):
        if self.prev_pose is None and self.hint is None:
            t = row_pose(self._truth.iloc[self._frame_no + 1])
            turn = rodrigues(self._rng.normal(size=3) * np.radians(HINT_DEG) / np.sqrt(3))
            C = t.center + self._rng.normal(size=3) * HINT_M / np.sqrt(3)
            self.hint = Pose.from_center(turn @ t.R_wc, C)
        return super().process(gray, ahead)


def run_scene(folder: Path, systems: list[str], overrides: dict | None = None) -> dict[str, dict]:
    """Each system on one scene; `overrides`: mirage's TrackSettings fields set (`--set`)."""
    camera = Camera.load(folder / "camera_truth.yaml")
    truth = read_pose_csv(folder / "orbit_truth.csv")
    recipe = yaml.safe_load((folder / "scene.yaml").read_text())
    target = np.array(
        yaml.safe_load((folder / "desired_path.yaml").read_text())["look_at_m"], float
    )
    frames, _ = stress.load_frames(folder / "orbit.mp4")
    model = stress.get_model(folder / "keyframes", camera)
    settings = dataclasses.replace(stress.TrackSettings(), **(overrides or {}))
    out = {}
    for sy in systems:
        if sy == "hinted":
            hinted = HintedTracker(model, camera, truth, settings)
            res, sec = stress.run_mirage(frames, model, camera, tracker=hinted)
        elif sy == "mirage":  # (without overrides: the defaults, as stress.run_mirage's)
            tracker = stress.Tracker(model, camera, settings)
            res, sec = stress.run_mirage(frames, model, camera, tracker=tracker)
        elif sy == "extend":  # `mirage track --extend`: both passes and the build timed
            tracker = stress.Tracker(model, camera, settings)
            res, sec = stress.run_extended(frames, model, camera, tracker=tracker)
        else:
            res, sec = stress.SYSTEMS[sy](frames, model, camera)
        out[sy] = score(res, truth, target, recipe["family"] == "far", sec)
        out[sy]["drum"] = recipe["landmark"]["drums"] > 0
    return out


def summarise(label: str, family: str, per_seed: dict[int, dict]) -> str:
    """One table row for a system over a family's seeds."""
    rs = list(per_seed.values())
    tracked = np.array([r["tracked"] for r in rs])
    cat = {k: np.concatenate([r[k] for r in rs]) for k in ("pe", "re", "pct", "sp", "sr")}
    worst_p = max((honesty(r["pe"], r["sp"]) for r in rs), default=np.nan, key=_nan_low)
    worst_r = max((honesty(r["re"], r["sr"]) for r in rs), default=np.nan, key=_nan_low)
    f = stress.fmt
    return (
        f"| {family} | {label} | {len(rs)} | {sum(r['wrong'] for r in rs)} "
        f"| {sum(r['ok_out'] for r in rs)} | {f(np.nanmedian(tracked), '.1f')} "
        f"| {f(np.nanmin(tracked), '.1f')} "
        f"| {f(np.median(cat['pct']) if len(cat['pct']) else np.nan, '.3f')} "
        f"| {f(np.median(cat['re']) if len(cat['re']) else np.nan, '.3f')} "
        f"| {f(honesty(cat['pe'], cat['sp']), '.2f')} / {f(honesty(cat['re'], cat['sr']), '.2f')} "
        f"| {f(worst_p, '.2f')} / {f(worst_r, '.2f')} "
        f"| {f(np.median([r['fps'] for r in rs]), '.0f')} |"
    )


def by_landmark(label: str, family: str, per_seed: dict[int, dict]) -> list[str]:
    """The rows again for the scenes whose landmark has a drum and for those of boxes
    alone, when there are both: a drum's print wraps a curved face that far views see
    40-60 px wide, so the two kinds fail differently and a family's median hides which."""
    drum = {s: r for s, r in per_seed.items() if r["drum"]}
    boxes = {s: r for s, r in per_seed.items() if not r["drum"]}
    if not drum or not boxes:
        return []
    return [summarise(label + ", a drum", family, drum),
            summarise(label + ", boxes only", family, boxes)]  # fmt: skip


def _nan_low(v: float) -> float:
    return -np.inf if not np.isfinite(v) else v


def parse_seeds(text: str, count: int | None) -> list[int]:
    if text in ("report", "tune"):
        seeds = list(REPORT_SEEDS if text == "report" else TUNE_SEEDS)
    else:
        seeds = []
        for part in text.split(","):
            a, _, b = part.partition("-")
            seeds += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return seeds[:count] if count else seeds


def _as_bool(text: str) -> bool:
    words = {"1": True, "true": True, "yes": True, "0": False, "false": False, "no": False}
    if text.lower() not in words:
        raise ValueError(text)
    return words[text.lower()]


def parse_overrides(items: list[str]) -> dict:
    """`--set NAME=VALUE` -> {NAME: VALUE} for TrackSettings' plain fields, VALUE read as
    the field's default's type (an experiment run as one command, its figures reproducible)."""
    plain = {
        f.name: type(f.default)
        for f in dataclasses.fields(stress.TrackSettings)
        if isinstance(f.default, (bool, int, float, str))
    }
    out = {}
    for item in items:
        name, eq, value = item.partition("=")
        if not eq or name not in plain:
            raise ValueError(f"--set {item}: not NAME=VALUE of a TrackSettings field")
        kind = plain[name]
        try:
            out[name] = _as_bool(value) if kind is bool else kind(value)
        except ValueError:
            raise ValueError(f"--set {item}: {value!r} is not of type {kind.__name__}") from None
    return out


def parse_args() -> tuple[argparse.Namespace, dict]:
    """The command line (families and systems as lists), and its `--set` overrides; a
    one-line error when any is bad."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default=",".join(FAMILIES), help=f"of {', '.join(FAMILIES)}")
    ap.add_argument("--seeds", default="report", help="report, tune, or e.g. 0-9,15")
    ap.add_argument("--count", type=int, help="only the first COUNT of those seeds")
    ap.add_argument("--systems", default="mirage,plain,hloc", help=f"of {', '.join(SYSTEMS)}")
    ap.add_argument("--peer-seeds", type=int, default=10, help="seeds per family for peers")
    ap.add_argument("--frames", type=int, default=150, help="frames per scene (30 fps)")
    ap.add_argument("--jobs", type=int, default=2, help="render processes (first run only)")
    ap.add_argument("--render-only", action="store_true", help="render (cache) the scenes, stop")
    ap.add_argument("--per-seed", action="store_true", help="also print a row per seed")
    ap.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE",
        help="a TrackSettings field for mirage (repeatable), e.g. max_sigma_range=0.02",
    )  # fmt: skip
    args = ap.parse_args()
    try:
        overrides = parse_overrides(args.set)
    except ValueError as e:
        ap.error(str(e))
    args.families = [f.strip() for f in args.families.split(",") if f.strip()]
    args.systems = [s.strip() for s in args.systems.split(",") if s.strip()]
    bad = [f for f in args.families if f not in FAMILIES]
    bad += [s for s in args.systems if s not in SYSTEMS]
    if bad:
        ap.error(f"unknown family/system {', '.join(bad)}")
    return args, overrides


def main():
    args, overrides = parse_args()
    fams, systems = args.families, args.systems
    seeds = parse_seeds(args.seeds, args.count)
    if "hloc" in systems:
        try:
            import pycolmap  # noqa: F401
        except ImportError:
            systems.remove("hloc")
            print("hloc-style: not run, pycolmap is not installed", file=sys.stderr)
    t_start = time.perf_counter()
    folders = {(f, s): scene_folder(f, s, args.frames, args.jobs) for f in fams for s in seeds}
    if args.render_only:
        print(f"{len(folders)} scenes rendered under {CACHE}")
        return
    opencv_threads_for_two_callers()
    results: dict[str, dict[str, dict[int, dict]]] = {f: {} for f in fams}
    peer_seeds = set(seeds[: args.peer_seeds])
    for (fam, seed), folder in folders.items():
        run = [s for s in systems if s in ("mirage", "extend", "hinted") or seed in peer_seeds]
        per = run_scene(folder, run, overrides)
        for sy, r in per.items():
            results[fam].setdefault(sy, {})[seed] = r
            if args.per_seed:
                print(
                    f"{fam} {seed} {sy} ({'a drum' if r['drum'] else 'boxes'}): "
                    f"tracked {r['tracked']:.1f}% wrong {r['wrong']} "
                    f"ok-out {r['ok_out']} pos% {np.median(r['pct']) if len(r['pct']) else 0:.3f} "
                    f"honesty {honesty(r['pe'], r['sp']):.2f}/{honesty(r['re'], r['sr']):.2f} "
                    f"fps {r['fps']:.0f}",
                    file=sys.stderr,
                    flush=True,
                )
    header = (
        "| family | system | scenes | wrong poses | ok out of view | tracked in view % median "
        "| worst seed | pos median % range | rot median deg | honesty pos / rot pooled "
        "| worst seed pos / rot | fps median |"
    )
    lines = [header, "|" + "---|" * 12]
    labels = {
        **stress.SYSTEM_LABELS,
        "hinted": "mirage, hinted when lost",
        "extend": "mirage --extend",
    }
    if overrides:
        labels["mirage"] = "mirage (--set)"
    for fam in fams:
        for sy in systems:
            per = results[fam].get(sy, {})
            if not per:
                continue
            lines.append(summarise(labels[sy], fam, per))
            if sy == "mirage" and len(per) > len(peer_seeds) and len(systems) > 1:
                same = {s: r for s, r in per.items() if s in peer_seeds}
                lines.append(summarise(labels[sy] + ", peers' seeds", fam, same))
            lines += by_landmark(labels[sy], fam, per)
    print("\n".join(lines))
    print(
        f"\nmirage-cli {__version__}; seeds {args.seeds}"
        f"{f' (first {args.count})' if args.count else ''}: {seeds[0]}-{seeds[-1]}; "
        f"{f'settings {overrides}; ' if overrides else ''}"
        f"{args.frames} frames per scene at 30 fps, 640x480; peers on the first "
        f"{args.peer_seeds} seeds of each family; {time.perf_counter() - t_start:.0f} s"
    )


if __name__ == "__main__":
    main()
