"""`mirage demo`: the whole workflow on sample_data/, in-process, into a project folder."""

from __future__ import annotations

import time
from pathlib import Path

import click
import yaml

from ..errors import InputError
from ..fileio import atomic_write, copy_file, ensure_dir, refuse_overwrite
from ..synth import CALIB_BOARD, CALIB_SQUARE_M
from . import ui
from .options import FOLDER, shown

# the package is installed editable from the repository, which holds sample_data/
DEFAULT_SAMPLE = Path(__file__).resolve().parents[2] / "sample_data"
NEEDED = [
    "calibration",
    "keyframes",
    "keyframes/poses.csv",
    "orbit.mp4",
    "orbit_truth.csv",
    "desired_path.yaml",
]
BOARD, SQUARE = CALIB_BOARD, CALIB_SQUARE_M  # the board the sample data was rendered with


def find_sample_data(folder: Path | None) -> Path:
    """The sample data folder, or one clear error naming what is missing."""
    root = Path(folder) if folder else DEFAULT_SAMPLE
    if not root.is_dir():
        raise InputError(
            f"sample data folder {root} not found; pass --sample-data DIR "
            "(the repository's sample_data/)"
        )
    missing = [n for n in NEEDED if not (root / n).exists()]
    if missing:
        raise InputError(f"sample data folder {root} lacks {', '.join(missing)}")
    return root


def _same_dir(a: Path, b: Path) -> bool:
    try:
        return a.samefile(b)
    except OSError:
        return False


def project_config(overlay: bool) -> dict:
    """mirage.yaml for the demo folder: run `mirage <command>` inside it with no options.

    Keys are the flag names (`model` for --model), as a user would write them.
    """
    track = {"model": "landmark.mirage", "camera": "camera.yaml", "output": "poses.csv"}
    if overlay:
        track["overlay"] = "overlay.mp4"
    return {
        "calibrate": {"board": "{}x{}".format(*BOARD), "square": SQUARE, "output": "camera.yaml"},
        "build-model": {
            "camera": "camera.yaml",
            "poses": "keyframes_poses.csv",
            "output": "landmark.mirage",
        },
        "track": track,
        "report": {
            "path": "desired_path.yaml",
            "truth": "orbit_truth.csv",
            "output": "report.csv",
            "summary": "summary.yaml",
            "plot": "report.png",
        },
    }


@click.command("demo")
@shown(
    "--out",
    "out",
    default="demo_out",
    type=FOLDER,
    help="Folder to write everything into (becomes a project folder with mirage.yaml).",
)
@click.option(
    "--sample-data",
    "sample_data",
    type=FOLDER,
    help="Sample data folder [default: sample_data/ of the repository].",
)
@click.option("--overlay", is_flag=True, help="Also write overlay.mp4 from track (slower).")
def demo_cmd(out, sample_data, overlay):
    """Run calibrate -> build-model -> track -> report on the sample data.

    \b
    Example:
      mirage demo --out demo_out
      cd demo_out && mirage report poses.csv      # options come from mirage.yaml
    """
    src = find_sample_data(Path(sample_data) if sample_data else None)
    if Path(out).exists() and _same_dir(Path(out), src):
        raise InputError(f"--out {out} is the sample data folder; choose another folder")
    written = ["desired_path.yaml", "orbit_truth.csv", "keyframes_poses.csv", "camera.yaml",
               "landmark.mirage", "poses.csv", "report.csv", "summary.yaml", "report.png",
               "overlay.mp4", "mirage.yaml"]  # fmt: skip
    refuse_overwrite({"--out": [str(Path(out) / n) for n in written]}, {"--sample-data": str(src)})
    d = ensure_dir(out)
    t_all = time.perf_counter()
    # copies make the folder self-contained, so mirage.yaml can use plain names
    for name, dest in [
        ("desired_path.yaml", "desired_path.yaml"),
        ("orbit_truth.csv", "orbit_truth.csv"),
        ("keyframes/poses.csv", "keyframes_poses.csv"),
    ]:
        copy_file(src / name, d / dest)
    steps = [
        ("calibrate", lambda: _calibrate(src, d)),
        ("build-model", lambda: _build_model(src, d)),
        ("track", lambda: _track(src, d, overlay)),
        ("report", lambda: _report(d)),
    ]
    timings = {}
    for i, (name, step) in enumerate(steps, 1):
        ui.echo(f"== {i}/{len(steps)} mirage {name} ==")
        t0 = time.perf_counter()
        step()
        timings[name] = time.perf_counter() - t0
        ui.echo(f"   ({timings[name]:.1f} s)")
        ui.echo()
    with atomic_write(d / "mirage.yaml") as f:
        f.write(
            "# Project folder written by `mirage demo`. Paths are relative to this file:\n"
            "# run mirage inside this folder (or pass --config to this file), e.g.\n"
            f"#   mirage track {src / 'orbit.mp4'}\n"
            "#   mirage report poses.csv\n"
        )
        yaml.safe_dump(project_config(overlay), f, sort_keys=False)
    total = time.perf_counter() - t_all
    steps_s = ", ".join(f"{k} {v:.1f} s" for k, v in timings.items())
    ui.echo(f"demo: done in {total:.1f} s ({steps_s}); everything is in {d}/")
    ui.echo(f"      open {d / 'report.png'}; inside {d}, mirage.yaml supplies the options")


# The steps call the pipelines with the commands' defaults (the settings dataclasses) and
# print what the commands print; imported inside, so that `mirage --help` stays fast.
def _calibrate(src: Path, d: Path) -> None:
    from ..calibrate import Board, CalibOptions, detect_images
    from ..frames import resolve_inputs
    from .calibrate import calibrate_detections

    board = Board(*BOARD, SQUARE)
    det = detect_images(resolve_inputs([src / "calibration"], "board images").images, board)
    calibrate_detections(det, board, CalibOptions(), d / "camera.yaml")


def _build_model(src: Path, d: Path) -> None:
    from ..build_model import BuildSettings
    from ..camera import Camera
    from ..pipelines.build import build
    from .build_model import save_model

    t0 = time.perf_counter()
    inputs, poses = [str(src / "keyframes")], str(d / "keyframes_poses.csv")
    res = build(inputs, Camera.load(d / "camera.yaml"), BuildSettings(), poses_csv=poses)
    save_model(res, d / "landmark.mirage", {"inputs": inputs, "poses": poses, "board": None}, t0)


def _track(src: Path, d: Path, overlay: bool) -> None:
    from ..frames import FrameSource
    from ..model import LandmarkModel
    from ..pipelines.track import open_job, track
    from .track import print_summary

    model = LandmarkModel.load(d / "landmark.mirage")
    job = open_job(
        model, FrameSource([src / "orbit.mp4"]), d / "poses.csv", d / "camera.yaml",
        reporter=ui, overlay=d / "overlay.mp4" if overlay else None,
    )  # fmt: skip
    result = track(job, reporter=ui)
    print_summary(result)
    if result.interrupted is not None:
        raise result.interrupted


def _report(d: Path) -> None:
    from ..pipelines.report import report
    from .report import publish_report

    res = report(d / "poses.csv", d / "desired_path.yaml", d / "orbit_truth.csv")
    publish_report(res.report, res.desired, d / "report.csv", d / "summary.yaml", d / "report.png")
