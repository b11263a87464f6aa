"""`mirage demo`: the whole workflow on sample_data/, in-process, into a project folder."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import click
import yaml

from . import ui
from .errors import InputError
from .fileio import atomic_write, ensure_dir

# the package is installed editable from the repository, which holds sample_data/
DEFAULT_SAMPLE = Path(__file__).resolve().parents[1] / "sample_data"
NEEDED = [
    "calibration",
    "keyframes",
    "keyframes/poses.csv",
    "orbit.mp4",
    "orbit_truth.csv",
    "desired_path.yaml",
]
BOARD, SQUARE = (9, 6), 0.025


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


def project_config(overlay: bool) -> dict:
    """mirage.yaml for the demo folder: run `mirage <command>` inside it with no options.

    Keys are the flag names (`model` for --model), as a user would write them.
    """
    track = {"model": "landmark.mirage", "camera": "camera.yaml", "output": "poses.csv"}
    if overlay:
        track["overlay"] = "overlay.mp4"
    return {
        "calibrate": {"board": "9x6", "square": SQUARE, "output": "camera.yaml"},
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
@click.option(
    "--out",
    "out",
    default="demo_out",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Folder to write everything into (becomes a project folder with mirage.yaml).",
)
@click.option(
    "--sample-data",
    "sample_data",
    type=click.Path(file_okay=False),
    help="Sample data folder [default: sample_data/ of the repository].",
)
@click.option("--overlay", is_flag=True, help="Also write overlay.mp4 from track (slower).")
@click.pass_context
def demo_cmd(ctx, out, sample_data, overlay):
    """Run calibrate -> build-model -> track -> report on the sample data.

    \b
    Example:
      mirage demo --out demo_out
      cd demo_out && mirage report poses.csv      # options come from mirage.yaml
    """
    # imported here so that `mirage --help` stays fast (the stages pull in OpenCV)
    from .build_model_cli import build_model_cmd
    from .calibrate_cli import calibrate
    from .report_cli import report_cmd
    from .track_cli import track_cmd

    src = find_sample_data(Path(sample_data) if sample_data else None)
    d = ensure_dir(out)
    t_all = time.perf_counter()
    # copies make the folder self-contained, so mirage.yaml can use plain names
    for name, dest in [
        ("desired_path.yaml", "desired_path.yaml"),
        ("orbit_truth.csv", "orbit_truth.csv"),
        ("keyframes/poses.csv", "keyframes_poses.csv"),
    ]:
        shutil.copyfile(src / name, d / dest)

    steps = [
        (
            "calibrate",
            calibrate,
            {
                "inputs": (str(src / "calibration"),),
                "board": BOARD,
                "square": SQUARE,
                "output": str(d / "camera.yaml"),
            },
        ),
        (
            "build-model",
            build_model_cmd,
            {
                "inputs": (str(src / "keyframes"),),
                "camera_path": str(d / "camera.yaml"),
                "poses_path": str(d / "keyframes_poses.csv"),
                "output": str(d / "landmark.mirage"),
            },
        ),
        (
            "track",
            track_cmd,
            {
                "video": (str(src / "orbit.mp4"),),
                "model_path": str(d / "landmark.mirage"),
                "camera_path": str(d / "camera.yaml"),
                "output": str(d / "poses.csv"),
                "overlay": str(d / "overlay.mp4") if overlay else None,
            },
        ),
        (
            "report",
            report_cmd,
            {
                "poses": str(d / "poses.csv"),
                "path": str(d / "desired_path.yaml"),
                "truth": str(d / "orbit_truth.csv"),
                "output": str(d / "report.csv"),
                "summary": str(d / "summary.yaml"),
                "plot": str(d / "report.png"),
            },
        ),
    ]
    timings = {}
    for i, (name, cmd, kwargs) in enumerate(steps, 1):
        ui.echo(f"== {i}/{len(steps)} mirage {name} ==")
        t0 = time.perf_counter()
        ctx.invoke(cmd, **kwargs)
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
