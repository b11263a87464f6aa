"""`--rerun`: Rerun recordings of `track` and `inspect`, read back and checked against the
pose CSV and the model (mirage_cli/viewer.py)."""

import os
import subprocess
import sys
from collections import defaultdict
from types import SimpleNamespace

import cv2
import numpy as np
import pandas as pd
import pytest
from conftest import SAMPLE, assert_one_line_error, own_signal_handlers, small_tmpfs

from mirage_cli import cli, viewer
from mirage_cli.errors import EnvironmentFailure, InputError
from mirage_cli.model import LandmarkModel
from mirage_cli.pipelines import track as pipeline
from mirage_cli.pose import matrix_from_quat
from mirage_cli.records import FrameRecord, Status

try:  # through mirage, so that rerun starts as it does in the CLI (its Rust log quiet)
    rr = viewer.rerun_module()
except InputError:
    rr = None
# only the tests that write or read a recording need rerun; the others run without it
needs_rerun = pytest.mark.skipif(rr is None, reason="the [viz] extra (rerun-sdk) is not installed")

VIDEO = SAMPLE / "orbit.mp4"
N_FRAMES = 15
MISSING = "--rerun needs rerun-sdk: pip install -e '.[viz]' in the mirage-cli checkout"


def read_rrd(path) -> dict[str, list]:
    """Entity path -> its chunks' record batches (static and temporal)."""
    out = defaultdict(list)
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        out[chunk.entity_path].append(chunk.to_record_batch())
    return out


def column(batches, name, index="frame") -> tuple[list, list]:
    """(index values, component values) of one component over an entity's batches,
    sorted by the index (None for static rows)."""
    rows = []
    for b in batches:
        if name not in b.schema.names:
            continue
        idx = b.column(index).to_pylist() if index in b.schema.names else [None] * b.num_rows
        rows += zip(idx, b.column(name).to_pylist(), strict=True)
    rows.sort(key=lambda r: -1 if r[0] is None else r[0])
    return [r[0] for r in rows], [r[1] for r in rows]


def mirage_here(*args, capsys) -> SimpleNamespace:
    """Run the CLI in this process (no interpreter start-up): exit code, stdout, stderr."""
    capsys.readouterr()
    with own_signal_handlers(), pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    return SimpleNamespace(returncode=e.value.code, stdout=out, stderr=err)


@pytest.fixture(scope="module")
def tracked(sample_model, tmp_path_factory):
    d = tmp_path_factory.mktemp("rerun")
    p = subprocess.run(
        [sys.executable, "-m", "mirage_cli", "track", VIDEO, "--model", sample_model,
         "--end", str(N_FRAMES), "-o", d / "poses.csv", "--rerun", d / "out.rrd"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "rerun " in p.stdout  # the summary says how to view it
    assert rr.chunk.RrdReader(d / "out.rrd").blueprints()  # the layout comes along
    return pd.read_csv(d / "poses.csv"), read_rrd(d / "out.rrd"), d


@needs_rerun
def test_track_recording_holds_every_frame_as_the_csv_says(tracked, sample_model):
    csv, ent, _ = tracked
    assert len(csv) == N_FRAMES and (csv.status == "ok").sum() >= N_FRAMES - 2
    frames, blobs = column(ent["/world/camera/image"], "EncodedImage:blob")
    assert frames == csv.frame.tolist()  # one image per frame, on the frame timeline
    img = cv2.imdecode(np.asarray(blobs[0][0], np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (480, 640, 3)  # a real JPEG of the frame
    _, t = column(ent["/world/camera/image"], "time")  # the time_s timeline
    assert np.allclose([x.total_seconds() for x in t], csv.time_s, atol=1e-6)

    ok = csv[csv.status == "ok"]
    f, centre = column(ent["/world/camera"], "Transform3D:translation")
    assert f == ok.frame.tolist()  # a camera pose only where the pose is ok
    assert np.allclose(np.array(centre)[:, 0], ok[["x_m", "y_m", "z_m"]], atol=2e-6)
    _, mats = column(ent["/world/camera"], "Transform3D:mat3x3")
    R = np.array(mats)[:, 0].reshape(-1, 3, 3).transpose(0, 2, 1)  # column-major in Rerun
    want = np.array([matrix_from_quat(q) for q in ok[["qw", "qx", "qy", "qz"]].to_numpy()])
    assert np.allclose(R, want, atol=1e-5)  # camera-to-world: R_WC, as the CSV's quaternion

    f, px = column(ent["/world/camera/image/inliers"], "Points2D:positions")
    assert f == csv.frame.tolist()
    counts = np.array([len(p) for p in px])
    assert np.array_equal(counts, np.where(csv.status == "ok", csv.inliers, 0))
    inl = np.array(px[0])
    assert ((inl >= 0) & (inl < [640, 480])).all()
    _, scal = column(ent["/track/inliers"], "Scalars:scalars")
    assert np.array_equal(np.ravel(scal), csv.inliers)
    _, sig = column(ent["/track/sigma_pos_m"], "Scalars:scalars")
    assert np.allclose(np.ravel(sig), ok.sigma_pos_m, rtol=1e-5)

    # the path so far: at the last frame, the ok centres in order
    _, strips = column(ent["/world/trajectory/0000"], "LineStrips3D:strips")
    last = np.concatenate([np.array(s) for s in strips[-1]])
    assert np.allclose(last, ok[["x_m", "y_m", "z_m"]], atol=2e-6)

    model = LandmarkModel.load(sample_model)
    _, pts = column(ent["/world/model/points"], "Points3D:positions", index=None)
    assert len(pts) == 1 and len(pts[0]) == len(model.points)  # static, once
    kfs = [e for e in ent if e.startswith("/world/model/keyframes/") and e.count("/") == 4]
    assert len(kfs) == len(model.keyframes)


@needs_rerun
def test_inspect_recording_holds_the_model(sample_model, tmp_path, capsys):
    out = tmp_path / "model.rrd"
    p = mirage_here("inspect", sample_model, "--rerun", out, capsys=capsys)
    assert p.returncode == 0, p.stderr
    assert f"rerun {out}" in p.stdout
    ent = read_rrd(out)
    model = LandmarkModel.load(sample_model)
    _, pts = column(ent["/world/model/points"], "Points3D:positions", index=None)
    assert np.allclose(np.array(pts[0]), model.points, atol=1e-5)
    _, colours = column(ent["/world/model/points"], "Points3D:colors", index=None)
    assert len(colours[0]) == len(model.points)
    for i, kf in enumerate(model.keyframes):
        e = f"/world/model/keyframes/{i:03d}"
        _, t = column(ent[e], "Transform3D:translation", index=None)
        assert np.allclose(t[0][0], kf.pose.center, atol=1e-6)
        _, blob = column(ent[f"{e}/image"], "EncodedImage:blob", index=None)
        thumb = cv2.imdecode(np.asarray(blob[0][0], np.uint8), cv2.IMREAD_GRAYSCALE)
        assert thumb.shape == kf.thumbnail.shape  # the frustum shows the keyframe's view
    assert not any(e.startswith("/world/camera") for e in ent)  # nothing per frame


def test_unwritable_recording_is_one_line(sample_model, tmp_path, capsys):
    p = mirage_here("track", VIDEO, "--model", sample_model, "-o", tmp_path / "p.csv",
                    "--rerun", tmp_path / "no" / "out.rrd", capsys=capsys)  # fmt: skip
    assert_one_line_error(p, 2, "does not exist")
    assert not (tmp_path / "p.csv").exists()  # refused before any work
    p = mirage_here("inspect", sample_model, "--rerun", tmp_path, capsys=capsys)
    assert_one_line_error(p, 2, "is a directory")


@pytest.mark.parametrize("command", ["track", "inspect"])
def test_recording_over_an_input_is_refused(command, sample_model, tmp_path, capsys):
    before = sample_model.read_bytes()
    args = {
        "track": ["track", VIDEO, "--model", sample_model, "-o", tmp_path / "p.csv"],
        "inspect": ["inspect", sample_model],
    }[command]
    p = mirage_here(*args, "--rerun", sample_model, capsys=capsys)
    assert_one_line_error(p, 2, "same file")
    assert sample_model.read_bytes() == before


def test_without_rerun_sdk_is_one_line(sample_model, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` raises ImportError
    monkeypatch.chdir(tmp_path)
    for args in (["inspect", sample_model], ["track", VIDEO, "--model", sample_model]):
        p = mirage_here(*args, "--rerun", "m.rrd", capsys=capsys)
        assert_one_line_error(p, 2)
        assert p.stderr.strip() == f"mirage: error: {MISSING}"
        assert not list(tmp_path.iterdir())  # refused before any work or output


def test_mirage_imports_rerun_only_for_a_recording():
    code = "import sys, mirage_cli.cli.track, mirage_cli.cli.build_model as m; "
    code += "print('rerun' in sys.modules)"
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.stdout.strip() == "False", p.stderr


def fake_track(monkeypatch, recs, stop=KeyboardInterrupt):
    """track's output loop fed `recs` instead of a real tracker, then `stop` raised."""

    def run(frames, tracker, keep_images):
        assert keep_images  # the recording needs the frames
        yield from recs
        if stop is not None:
            raise stop

    monkeypatch.setattr(pipeline, "track_frames", run)
    monkeypatch.setattr(pipeline, "warm_up", lambda: None)


def track_to(model, csv, rrd):
    src = SimpleNamespace(count=10, fps=10.0, frames=lambda first, last, every, **kw: iter(()))
    tracker = SimpleNamespace(model=model, camera=model.camera)
    result = pipeline.track(pipeline.TrackJob(src, tracker, csv, rerun=rrd))
    if result.interrupted is not None:
        raise result.interrupted  # as the command does, once the outputs are in place


@needs_rerun
def test_interrupt_keeps_the_recording_of_finished_frames(sample_model, tmp_path, monkeypatch):
    """track's output loop fed five records (one lost) and then Ctrl-C: the recording is
    in place with exactly those frames; the path breaks at the lost frame and its blocks
    join up (two poses a block here)."""
    model = LandmarkModel.load(sample_model)
    cam = model.camera
    poses = [kf.pose for kf in model.keyframes[:4]]
    img = np.full((cam.height, cam.width, 3), 90, np.uint8)
    px = np.array([[10.0, 20.0], [30.0, 40.0], [50.5, 60.5]])
    recs = [
        FrameRecord(Status.OK, poses[0], 0, 0.0, inliers=3, inlier_px=px, image=img),
        FrameRecord(Status.LOST, None, 1, 0.1, inliers=1, image=img),
        FrameRecord(Status.OK, poses[1], 2, 0.2, inliers=2, inlier_px=px[:2], image=img),
        FrameRecord(Status.OK, poses[2], 3, 0.3, inliers=3, inlier_px=px, image=img),
        FrameRecord(Status.OK, poses[3], 4, 0.4, inliers=3, inlier_px=px, image=img),
    ]

    fake_track(monkeypatch, recs)
    monkeypatch.setattr(viewer, "TRAJECTORY_BLOCK", 2)
    out = tmp_path / "out.rrd"
    with pytest.raises(KeyboardInterrupt):
        track_to(model, tmp_path / "p.csv", out)
    ent = read_rrd(out)
    frames, _ = column(ent["/world/camera/image"], "EncodedImage:blob")
    assert frames == [0, 1, 2, 3, 4]
    f, centre = column(ent["/world/camera"], "Transform3D:translation")
    assert f == [0, 2, 3, 4]
    c = np.array([p.center for p in poses])
    assert np.allclose(np.array(centre)[:, 0], c, atol=1e-6)
    _, inl = column(ent["/world/camera/image/inliers"], "Points2D:positions")
    assert [len(p) for p in inl] == [3, 0, 2, 3, 3]
    assert np.allclose(inl[0], px, atol=1e-4)
    _, b0 = column(ent["/world/trajectory/0000"], "LineStrips3D:strips")
    _, b1 = column(ent["/world/trajectory/0001"], "LineStrips3D:strips")
    assert [len(s) for s in b0[-1]] == [1, 1]  # the lost frame broke the line
    assert np.allclose(np.concatenate(b0[-1]), c[:2], atol=1e-6)
    assert np.allclose(b1[-1][0], c[1:], atol=1e-6)  # the next block joins the last pose
    assert len(b0) == 2 and len(b1) == 2  # each frame logs its block only
    assert len(pd.read_csv(tmp_path / "p.csv")) == 5
    assert not list(tmp_path.glob(".*"))  # no temporary file left


@pytest.fixture
def small_disk(tmp_path):
    """A 256 KiB tmpfs: a recording fills it within a few frames."""
    with small_tmpfs(tmp_path / "small") as mnt:
        yield mnt


@needs_rerun
def test_full_disk_is_one_line_and_leaves_nothing(sample_model, small_disk, capsys):
    """rerun's file writer does not survive a full disk (closing the recording can hang):
    mirage stops first, with one line naming the file, exit 1 and no temporary file."""
    out = small_disk / "out.rrd"
    for args in (["inspect", sample_model], ["track", VIDEO, "--model", sample_model]):
        p = mirage_here("-q", *args, "-o" if args[0] == "track" else "--plot",
                        small_disk.parent / "x.out", "--rerun", out, capsys=capsys)  # fmt: skip
        assert_one_line_error(p, 1, f"cannot write {out}: less than 16 MB left")
        assert not list(small_disk.iterdir())


@needs_rerun
def test_disk_filling_up_stops_the_recording_cleanly(sample_model, tmp_path, monkeypatch):
    """Room runs out after two frames: the run stops there with one line, the recording
    is closed (no hang) and removed, like the pose CSV on any error."""
    model = LandmarkModel.load(sample_model)
    img = np.zeros((480, 640, 3), np.uint8)
    recs = [FrameRecord(Status.LOST, None, i, i / 10, image=img) for i in range(5)]
    fake_track(monkeypatch, recs, stop=None)
    calls = {"n": 0}
    real = os.statvfs

    def statvfs(path):  # plenty of room for the header and two frames, then none
        calls["n"] += 1
        st = real(path)
        free = 1 << 30 if calls["n"] <= 3 else 0
        return SimpleNamespace(f_bavail=free // st.f_frsize, f_frsize=st.f_frsize)

    monkeypatch.setattr(viewer.os, "statvfs", statvfs)
    out = tmp_path / "out.rrd"
    with pytest.raises(EnvironmentFailure, match=f"cannot write {out}: less than 16 MB"):
        track_to(model, tmp_path / "p.csv", out)
    assert calls["n"] == 4  # the header, frames 0 and 1, then frame 2 found no room
    assert not out.exists() and not (tmp_path / "p.csv").exists()
    assert not list(tmp_path.glob(".*"))
