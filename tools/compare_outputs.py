"""Produce every output file of the sample data, `mirage demo` and benchmarks/stress.py with
one checkout, or compare two such output folders (the behaviour-preserving check of a
refactoring, issue 29).

    python tools/compare_outputs.py produce ROOT OUT [--stress SCENES]   # run ROOT's code
    python tools/compare_outputs.py compare OLD_OUT NEW_OUT

`produce` runs ROOT's package (PYTHONPATH=ROOT, so install the project in compat editable
mode: `pip install -e . --config-settings editable_mode=compat`): `mirage demo`, then in
the demo folder `mirage track` of the sample orbit with --tum/--kitti and with --smooth 0,
`mirage calibrate` on the sample chessboard images, `mirage batch` of two flights of the
sample orbit, and stress.py's mirage systems (default and --smooth 0) on its scenes, each
scene's poses and sigmas written to a CSV with every digit (repr), its model saved as a
model archive, and stress.py's printed table for those systems.

`compare` compares every file of the two folders: CSVs cell by cell except the `ms` column
(the time a frame took) and `seconds` (a flight's), batch's done.json without its
timings, output hashes and input sizes and mtimes; the checkout's and the output folder's absolute
paths, which outputs quote, are replaced by placeholders; the stress table is written
without its `fps`; every other file byte for byte (model archives by their members); it
lists what differs.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
SKIP_FILES = {"report.png", "campaign.png", "log.txt"}  # plots: matplotlib metadata
TIMING_COLUMNS = ("ms", "seconds")  # the time a frame (track) or a flight (batch) took


def _run(root: Path, args: list[str], cwd: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(root))
    cmd = ["nice", "-n", "5", sys.executable, "-m", "mirage_cli", "-q", *args]
    p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    (cwd / "log.txt").open("a").write(f"$ {' '.join(args)}\n{p.stdout}{p.stderr}")
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed ({p.returncode}): {p.stderr[-500:]}")


STRESS = r"""
import csv, importlib.util, sys
from pathlib import Path
root, out, scenes = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3].split(",")
spec = importlib.util.spec_from_file_location("stress", root / "benchmarks" / "stress.py")
st = importlib.util.module_from_spec(spec)
sys.modules["stress"] = st  # its dataclasses look their module up
spec.loader.exec_module(st)
st.opencv_threads_for_two_callers()
camera = st.Camera.load(st.SAMPLE / "camera_truth.yaml")
lines = []
for s in scenes:
    folder, kf = st.scene_data(s, 120, 1)
    truth = st.read_pose_csv(folder / "orbit_truth.csv")
    frames, _ = st.load_frames(folder / "orbit.mp4", st.SCENES[s].exposure)
    model = st.get_model(kf, camera)
    model.save(out / f"stress_{s}.mirage")
    for sy in ("mirage", "unsmoothed"):
        res, sec = st.SYSTEMS[sy](frames, model, camera)
        with open(out / f"stress_{s}_{sy}.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["frame", "R", "t", "sigma_pos_m", "sigma_rot_deg"])
            for i, (p, sp, sr) in enumerate(res):
                R = "" if p is None else repr(p.R.ravel().tolist())
                t = "" if p is None else repr(p.t.ravel().tolist())
                w.writerow([i, R, t, repr(sp), repr(sr)])
        r = st.score(res, truth, sec)
        lines.append(" | ".join([s, sy] + [f"{k}={v!r}" for k, v in r.items() if k != "fps"]))
(out / "stress_table.txt").write_text("\n".join(lines) + "\n")
"""


def produce(root: Path, out: Path, scenes: str) -> None:
    root, out = root.resolve(), out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    (out / "root.txt").write_text(f"{root}\n{out}\n")  # paths in outputs: see `_normal`
    sample = root / "sample_data"
    demo = out / "demo"
    _run(root, ["demo", "--out", str(demo), "--sample-data", str(sample)], out)
    _run(root, ["track", str(sample / "orbit.mp4"), "-o", "poses_tum.csv", "--tum",
                "orbit.tum", "--kitti", "orbit.kitti"], demo)  # fmt: skip
    _run(root, ["track", str(sample / "orbit.mp4"), "-o", "poses_smooth0.csv", "--smooth",
                "0", "--method", "epnp", "--end", "300"], demo)  # fmt: skip
    _run(root, ["calibrate", str(sample / "calibration"), "--board", "9x6", "--square",
                "0.025", "-o", str(out / "camera_calib.yaml")], out)  # fmt: skip
    camp = out / "campaign"
    camp.mkdir(exist_ok=True)
    (camp / "campaign.yaml").write_text(
        f"defaults:\n  model: {demo / 'landmark.mirage'}\n  camera: {demo / 'camera.yaml'}\n"
        f"  path: {sample / 'desired_path.yaml'}\n  output: {camp / 'out'}\n"
        f"flights:\n  - video: {sample / 'orbit.mp4'}\n    name: first\n    end: 120\n"
        f"    truth: {sample / 'orbit_truth.csv'}\n"
        f"  - video: {sample / 'orbit.mp4'}\n    name: second\n    start: 400\n"
    )
    _run(root, ["batch", str(camp / "campaign.yaml"), "--workers", "1"], camp)
    if scenes:
        env = dict(os.environ, PYTHONPATH=str(root))
        subprocess.run(["nice", "-n", "5", sys.executable, "-c", STRESS, str(root), str(out),
                        scenes], check=True, env=env, cwd=root)  # fmt: skip


def _normal(text: str, roots: list[str]) -> str:
    """Outputs name their inputs by absolute path (a model's source, a campaign's files):
    the checkout and the output folder become placeholders."""
    for i, r in enumerate(roots):
        text = text.replace(r, f"<root{i}>")
    return text


def _csv_rows(path: Path, roots: list[str]) -> list[list[str]]:
    rows = list(csv.reader(io.StringIO(_normal(path.read_text(), roots))))
    for timing in TIMING_COLUMNS:
        if rows and timing in rows[0]:
            k = rows[0].index(timing)
            rows = [r[:k] + r[k + 1 :] for r in rows]
    return rows


def _same(a: Path, b: Path, ra_: list[str], rb_: list[str]) -> str | None:
    """None when equal, else a short description (`ra_`, `rb_`: the two sides' roots)."""
    if a.suffix == ".csv":
        ra, rb = _csv_rows(a, ra_), _csv_rows(b, rb_)
        if ra == rb:
            return None
        diff = [i for i, (x, y) in enumerate(zip(ra, rb, strict=False)) if x != y]
        return f"{len(ra)} vs {len(rb)} rows, {len(diff)} rows differ, first {diff[:3]}"
    if a.name == "done.json":  # batch's marker: its timing and the pose CSV's hash vary
        ja, jb = (json.loads(_normal(x.read_text(), r)) for x, r in ((a, ra_), (b, rb_)))
        for j in (ja, jb):
            j["result"].pop("seconds")
            j.pop("outputs")
            j["inputs"] = [i[0] for i in j["inputs"]]  # the files (compared on their own)
        return None if ja == jb else "marker differs (inputs, options or result)"
    if zipfile.is_zipfile(a) and zipfile.is_zipfile(b):
        za, zb = zipfile.ZipFile(a), zipfile.ZipFile(b)
        na, nb = sorted(za.namelist()), sorted(zb.namelist())
        if na != nb:
            return f"members {na} vs {nb}"
        bad = [n for n in na if _member(za, n, ra_) != _member(zb, n, rb_)]
        return f"members differ: {bad}" if bad else None
    if a.suffix in (".yaml", ".json", ".txt", ".tum", ".kitti"):
        same = _normal(a.read_text(), ra_) == _normal(b.read_text(), rb_)
    else:
        same = a.read_bytes() == b.read_bytes()
    return None if same else "bytes differ"


def _member(z: zipfile.ZipFile, name: str, roots: list[str]) -> bytes:
    data = z.read(name)
    return _normal(data.decode(), roots).encode() if name.endswith(".json") else data


def _roots(out: Path) -> list[str]:
    f = out / "root.txt"
    lines = f.read_text().split() if f.is_file() else []
    return sorted(lines + [str(out.resolve())], key=len, reverse=True)


def compare(old: Path, new: Path) -> int:
    fa = {p.relative_to(old) for p in old.rglob("*") if p.is_file()}
    fb = {p.relative_to(new) for p in new.rglob("*") if p.is_file()}
    fa = {p for p in fa if p.name not in SKIP_FILES and str(p) != "root.txt"}
    fb = {p for p in fb if p.name not in SKIP_FILES and str(p) != "root.txt"}
    roots_a, roots_b = (_roots(d) for d in (old, new))
    bad = 0
    for p in sorted(fa ^ fb):
        print(f"only in {'old' if p in fa else 'new'}: {p}")
        bad += 1
    for p in sorted(fa & fb):
        msg = _same(old / p, new / p, roots_a, roots_b)
        print(f"{'same' if msg is None else 'DIFFERS'}: {p}" + ("" if msg is None else f": {msg}"))
        bad += msg is not None
    print(f"{len(fa & fb)} files compared, {bad} differ or are missing")
    return 1 if bad else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("produce")
    p.add_argument("root", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--stress", default="", help="stress.py scenes, comma-separated")
    c = sub.add_parser("compare")
    c.add_argument("old", type=Path)
    c.add_argument("new", type=Path)
    args = ap.parse_args()
    if args.cmd == "produce":
        produce(args.root, args.out, args.stress)
        return 0
    return compare(args.old, args.new)


if __name__ == "__main__":
    sys.exit(main())
