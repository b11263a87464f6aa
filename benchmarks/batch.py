"""Campaign benchmark: wall time of `mirage batch` with 1 and 2 workers, on the local
process pool and on a Dask LocalCluster, over flights cut from the sample orbit.

Each run is the CLI end to end (a fresh output folder, so every flight is computed):
process start, model loads, tracking, reports, campaign.csv and the plot. The Dask
cluster is started before its runs (its start-up is printed, not counted), as a real
cluster would be running already. CPU s is the CPU time of every process of the run (the
Dask one includes its cluster's start-up); CPU / wall is how many cores the run kept busy,
which says whether the machine had a second core to give. Every run's pose and report
CSVs are compared with the serial run's (byte for byte, apart from the `ms` column).

    python benchmarks/batch.py                       # 4 flights of 135 frames
    python benchmarks/batch.py --flights 2 --frames 60
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data"


def mirage(*args, check=True) -> subprocess.CompletedProcess:
    p = subprocess.run(
        [sys.executable, "-m", "mirage_cli", *map(str, args)], capture_output=True, text=True
    )
    if check and p.returncode != 0:
        sys.exit(f"mirage {' '.join(map(str, args))} failed:\n{p.stderr}")
    return p


def write_campaign(d: Path, model: Path, flights: int, frames: int) -> Path:
    lines = [
        "defaults:",
        f"  model: {model}",
        f"  path: {SAMPLE / 'desired_path.yaml'}",
        "flights:",
    ]
    for i in range(flights):
        s = (i * frames) % 540
        lines.append(
            f"  - {{name: f{i}, video: {SAMPLE / 'orbit.mp4'}, start: {s}, end: {s + frames}, "
            f"truth: {SAMPLE / 'orbit_truth.csv'}}}"
        )
    path = d / "campaign.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


def without_ms(path: Path) -> list[list[str]]:
    rows = [ln.split(",") for ln in path.read_text().splitlines()]
    k = rows[0].index("ms")
    return [r[:k] + r[k + 1 :] for r in rows]


def same_outputs(a: Path, b: Path, names: list[str]) -> bool:
    return all(
        without_ms(a / n / "poses.csv") == without_ms(b / n / "poses.csv")
        and (a / n / "report.csv").read_bytes() == (b / n / "report.csv").read_bytes()
        for n in names
    )


def child_cpu() -> float:
    """CPU seconds of the finished child processes (the CLI, its pool, the Dask workers)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def timed(campaign: Path, out: Path, *extra) -> float:
    t0 = time.perf_counter()
    mirage("-q", "batch", campaign, "--out", out, *extra)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=4)
    ap.add_argument("--frames", type=int, default=135, help="frames a flight")
    ap.add_argument("--model", type=Path, help="a built sample model (default: build one)")
    args = ap.parse_args()
    from distributed import LocalCluster

    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        model = args.model
        if model is None:
            model = d / "landmark.mirage"
            mirage("-q", "build-model", SAMPLE / "keyframes", "--camera",
                   SAMPLE / "camera_truth.yaml", "--poses", SAMPLE / "keyframes" / "poses.csv",
                   "-o", model)  # fmt: skip
        campaign = write_campaign(d, model, args.flights, args.frames)
        names = [f"f{i}" for i in range(args.flights)]
        mirage("-q", "track", SAMPLE / "orbit.mp4", "--model", model, "--end", 2,
               "-o", d / "warm.csv")  # fmt: skip
        rows = []
        for w in (1, 2):
            cpu = child_cpu()
            wall = timed(campaign, d / f"pool{w}", "--workers", w)
            rows.append((f"local, --workers {w}", w, wall, child_cpu() - cpu))
        for w in (1, 2):
            t0, cpu = time.perf_counter(), child_cpu()
            with LocalCluster(
                n_workers=w, threads_per_worker=1, processes=True, dashboard_address=None
            ) as cluster:
                up = time.perf_counter() - t0
                wall = timed(campaign, d / f"dask{w}", "--scheduler", cluster.scheduler_address)
            name = f"Dask LocalCluster, {w} worker(s) (start-up {up:.1f} s, not counted)"
            rows.append((name, w, wall, child_cpu() - cpu))
        ref = d / "pool1"
        same = {r: same_outputs(ref, d / r, names) for r in ("pool2", "dask1", "dask2")}

    frames = args.flights * args.frames
    print(f"\n{args.flights} flights x {args.frames} frames of the sample orbit ({frames} frames)")
    print(
        "\n| executor | workers | wall s | frames/s | speed-up vs 1 worker | CPU s "
        "| cores busy (CPU / wall) |"
    )
    print("|---|---|---|---|---|---|---|")
    for i, (name, w, wall, cpu) in enumerate(rows):
        base = rows[i - 1][2] if w == 2 else wall
        print(
            f"| {name} | {w} | {wall:.1f} | {frames / wall:.1f} | {base / wall:.2f} "
            f"| {cpu:.1f} | {cpu / wall:.2f} |"
        )
    print(f"\noutputs identical to the serial run (except `ms`): {same}")
    print(
        f"load average (1 min) {load0:.1f} before, {os.getloadavg()[0]:.1f} after, on "
        f"{os.cpu_count()} CPUs: other processes' load leaves less for the workers"
    )


if __name__ == "__main__":
    main()
