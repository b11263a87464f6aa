import numpy as np
import pandas as pd
import pytest

from mirage_cli.errors import InputError
from mirage_cli.pose import Pose
from mirage_cli.records import FrameRecord, Status
from mirage_cli.trajectory import (
    FORMATS,
    POSE_COLUMNS,
    TrajectoryWriter,
    read_pose_csv,
    read_trajectory,
    row_pose,
    write_trajectory,
)


def some_poses(n=5):
    rng = np.random.default_rng(3)
    return [Pose.from_center_rpy(rng.uniform(-2, 2, 3), *rng.uniform(-60, 60, 3)) for _ in range(n)]


def test_round_trip(tmp_path):
    poses = some_poses()
    path = tmp_path / "p.csv"
    with TrajectoryWriter(path, "csv", ["inliers"]) as w:
        for i, p in enumerate(poses):
            w.write(FrameRecord(Status.OK, p, i, i / 30, inliers=10 + i))
        w.write(FrameRecord(Status.LOST, None, 5, 5 / 30))
    raw = pd.read_csv(path)
    assert list(raw.columns) == POSE_COLUMNS + ["inliers"]
    df = read_pose_csv(path)
    assert len(df) == 6 and df["status"].tolist() == ["ok"] * 5 + ["lost"]
    for (_, row), p in zip(df.iloc[:5].iterrows(), poses, strict=True):
        q = row_pose(row)
        assert q.distance_to(p) < 2e-6 and q.angle_to(p) < 1e-5
        assert np.allclose([row.roll_deg, row.pitch_deg, row.yaw_deg], p.rpy_deg, atol=1e-3)
    assert np.isnan(df.loc[5, "x_m"]) and row_pose(df.iloc[5]) is None


def test_rows_are_flushed_before_close(tmp_path):
    path = tmp_path / "p.csv"
    w = TrajectoryWriter(path)
    w.write(FrameRecord(Status.OK, some_poses(1)[0], 0, 0.0))
    # the partial file already holds the row; the final path appears on close
    assert len(w.tmp.read_text().splitlines()) == 2
    assert not path.exists()
    w.close()
    assert len(path.read_text().splitlines()) == 2 and not w.tmp.exists()


def test_interrupt_keeps_rows(tmp_path):
    path = tmp_path / "p.csv"
    with pytest.raises(KeyboardInterrupt), TrajectoryWriter(path) as w:
        w.write(FrameRecord(Status.OK, some_poses(1)[0], 0, 0.0))
        raise KeyboardInterrupt
    assert len(path.read_text().splitlines()) == 2


def test_error_keeps_previous_good_file(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("previous")
    with pytest.raises(RuntimeError), TrajectoryWriter(path) as w:
        w.write(FrameRecord(Status.OK, some_poses(1)[0], 0, 0.0))
        raise RuntimeError("boom")
    assert path.read_text() == "previous"


def test_image_column_and_minimal_input(tmp_path):
    p = tmp_path / "in.csv"
    p.write_text(
        "image,x_m,y_m,z_m,qw,qx,qy,qz\na.jpg,1,2,3,1,0,0,0\nb.jpg,1,2,3,0.7071,0,0,0.7071\n"
    )
    df = read_pose_csv(p)
    assert df["frame"].tolist() == ["a.jpg", "b.jpg"]
    assert np.isclose(np.hypot(df.loc[1, "qw"], df.loc[1, "qz"]), 1.0, atol=1e-12)  # normalised
    assert (df["status"] == "ok").all()


@pytest.mark.parametrize(
    "text, msg",
    [
        ("", "empty"),
        ("frame,x_m,y_m,z_m,qw,qx,qy\n0,1,2,3,1,0,0\n", "missing column(s) qz"),
        (
            "frame,x_m,y_m,z_m,qw,qx,qy,qz\n0,1,2,3,1,0,0,0\n1,1,abc,3,1,0,0,0\n",
            "column 'y_m' row 3",
        ),
        ("frame,x_m,y_m,z_m,qw,qx,qy,qz\n0,1,,3,1,0,0,0\n", "column 'y_m' row 2"),
        ("x_m,y_m,z_m,qw,qx,qy,qz\n1,2,3,1,0,0,0\n", "no 'frame' or 'image'"),
        ("frame,x_m,y_m,z_m,qw,qx,qy,qz\n", "no rows"),
        ("frame,x_m,y_m,z_m,qw,qx,qy,qz\n0,1,2,3,0,0,0,0\n", "zero quaternion"),
        ("frame,x_m,y_m,z_m,qw,qx,qy,qz\n0,1,2,3,2,0,0,0\n", "column 'qw..qz' row 2 (frame 0)"),
        ("frame,x_m,y_m,z_m,qw,qx,qy,qz\n0,1,2,3,1,0,0,0\n1,inf,2,3,1,0,0,0\n", "'x_m' row 3"),
        (
            "frame,x_m,y_m,z_m,qw,qx,qy,qz\n7,1,2,3,1,0,0,0\n7.0,1,2,3,1,0,0,0\n",
            "row 3 (frame 7.0) repeats the frame of row 2",
        ),
    ],
)
def test_clear_errors(tmp_path, text, msg):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        read_pose_csv(p)
    assert msg in str(e.value)


def test_lost_rows_may_be_empty(tmp_path):
    p = tmp_path / "in.csv"
    p.write_text("frame,status,x_m,y_m,z_m,qw,qx,qy,qz\n0,ok,1,2,3,1,0,0,0\n1,lost,,,,,,,\n")
    df = read_pose_csv(p)
    assert df["status"].tolist() == ["ok", "lost"]


def test_vectorised_angles_match_pose():
    from mirage_cli.trajectory import derived_angles

    poses = some_poses(200)
    got = derived_angles(
        np.array([p.center for p in poses]), np.array([p.quat_wxyz for p in poses])
    )
    want = np.array([[*p.rpy_deg, p.azimuth_deg] for p in poses])
    assert np.allclose(got, want, atol=1e-9)


# --- records, statuses and the formats -------------------------------------------------
def test_status_words_are_the_file_strings():
    words = [s.value for s in Status]
    assert {"ok", "lost", "decode_error", "size_mismatch"} <= set(words)
    assert len(set(words)) == len(words) and all(w == w.lower().strip() for w in words)
    assert Status.OK == "ok" and f"{Status.DECODE_ERROR}" == "decode_error"
    assert str(Status.LOST) == "lost" and Status("size_mismatch") is Status.SIZE_MISMATCH
    rec = FrameRecord(Status.OK, some_poses(1)[0], 7, 0.25, inliers=40)
    assert rec.ok and not FrameRecord().ok and FrameRecord().status is Status.LOST


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_every_format_round_trips(tmp_path, fmt):
    """Write ok and lost records, read them back: same poses (and times where kept)."""
    poses = some_poses(6)
    recs = [FrameRecord(Status.OK, p, i, 10 + i / 30) for i, p in enumerate(poses)]
    recs.insert(2, FrameRecord(Status.DECODE_ERROR, None, 99, 99.0))
    path = tmp_path / f"t.{fmt}"
    write_trajectory(path, recs, fmt)
    df = read_trajectory(path, fmt)
    ok = df[df["status"] == Status.OK]
    assert len(ok) == len(poses)
    for (_, row), p in zip(ok.iterrows(), poses, strict=True):
        q = row_pose(row)
        assert q.distance_to(p) < 2e-6 and q.angle_to(p) < 1e-5
        assert np.allclose([row.roll_deg, row.pitch_deg, row.yaw_deg], p.rpy_deg, atol=1e-3)
    if fmt != "kitti":  # KITTI poses carry no times
        assert ok["time_s"].to_numpy() == pytest.approx(10 + np.arange(6) / 30, abs=1e-6)


def test_kitti_line_is_camera_to_world_row_major(tmp_path):
    p = some_poses(1)[0]
    write_trajectory(tmp_path / "k.txt", [FrameRecord(Status.OK, p, 0)], "kitti")
    T = np.loadtxt(tmp_path / "k.txt").reshape(3, 4)
    assert np.allclose(T[:, :3], p.R.T, atol=1e-8) and np.allclose(T[:, 3], p.center, atol=1e-6)


@pytest.mark.parametrize("fmt, text", [("tum", "1 2 3\n"), ("kitti", "1 2 x 4\n"), ("tum", "")])
def test_format_read_errors(tmp_path, fmt, text):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(InputError, match=fmt.upper()):
        read_trajectory(p, fmt)


def test_a_new_format_is_one_entry_and_one_row_function(tmp_path, monkeypatch, capsys):
    """Issue 11: a format registered in FORMATS (here camera centres, `x y z` a line) is
    written by TrajectoryWriter, recognised by guess_format, gets its `mirage track FLAG
    FILE` option and is written by track's one output loop beside the pose CSV and TUM."""
    from types import SimpleNamespace

    import click

    from mirage_cli import trajectory
    from mirage_cli.cli import track as track_cli
    from mirage_cli.pipelines import track as pipeline

    def xyz_row(rec, index, extra):  # the one function
        return " ".join(f"{v:.6f}" for v in rec.pose.center) + "\n" if rec.ok else None

    def read_xyz(path):  # only to read it back here
        c = np.loadtxt(path, ndmin=2)
        return pd.DataFrame({"x_m": c[:, 0], "y_m": c[:, 1], "z_m": c[:, 2]})

    xyz = trajectory.Format(
        lambda extra: "# x y z\n", xyz_row, read_xyz, flag="--xyz",
        help="Also write the camera centres.", suffixes=(".xyz",), fields=3,
    )  # fmt: skip
    monkeypatch.setitem(trajectory.FORMATS, "xyz", xyz)  # the one entry

    # the option: after --tum and --kitti, with its help, parameter named by the format
    cmd = click.command("t")(track_cli.format_options(lambda **kw: None))
    assert [p.opts for p in cmd.params] == [["--tum"], ["--kitti"], ["--xyz"]]
    help_text = " ".join(cmd.get_help(click.Context(cmd)).split())
    assert "--xyz FILE Also write the camera centres." in help_text

    # track's output loop, fed three records (one lost) instead of a real tracker
    poses = some_poses(2)
    recs = [
        FrameRecord(Status.OK, poses[0], 0, 0.0),
        FrameRecord(Status.LOST, None, 1, 1 / 30),
        FrameRecord(Status.OK, poses[1], 2, 2 / 30),
    ]
    monkeypatch.setattr(pipeline, "track_frames", lambda frames, tracker, keep_images: iter(recs))
    monkeypatch.setattr(pipeline, "warm_up", lambda: None)
    src = SimpleNamespace(count=3, fps=30.0, frames=lambda first, last, every, **kw: iter(()))
    tracker = SimpleNamespace(model=SimpleNamespace(points=np.zeros((0, 3))), camera=None)
    also = {"tum": tmp_path / "p.tum", "xyz": tmp_path / "p.xyz"}
    job = pipeline.TrackJob(src, tracker, tmp_path / "p.csv", formats=also)
    track_cli.print_summary(pipeline.track(job))
    assert "track: 3 frames, 2 ok" in capsys.readouterr().out

    assert len(read_pose_csv(tmp_path / "p.csv")) == 3
    assert len(read_trajectory(tmp_path / "p.tum")) == 2
    lines = (tmp_path / "p.xyz").read_text().splitlines()
    assert lines[0] == "# x y z" and len(lines) == 3
    assert trajectory.guess_format(tmp_path / "p.xyz") == "xyz"  # by suffix
    (tmp_path / "centres.txt").write_text("\n".join(lines[1:]) + "\n")
    assert trajectory.guess_format(tmp_path / "centres.txt") == "xyz"  # by fields a line
    back = read_trajectory(tmp_path / "p.xyz")
    assert np.allclose(back[["x_m", "y_m", "z_m"]], [p.center for p in poses], atol=1e-6)


@pytest.mark.parametrize(
    "name, text, fmt",
    [
        ("a.csv", "frame,x_m\n", "csv"),
        ("a.TUM", "", "tum"),
        ("a.kitti", "1 2 3\n", "kitti"),  # the suffix decides
        ("a.txt", "# c\n\n0 1 2 3 4 5 6 7\n", "tum"),
        ("a.txt", " ".join("0" * 12) + "\n", "kitti"),
        ("a.txt", "1 2 3\n", "csv"),
        ("missing.txt", None, "csv"),
    ],
)
def test_guess_format(tmp_path, name, text, fmt):
    from mirage_cli.trajectory import guess_format

    if text is not None:
        (tmp_path / name).write_text(text)
    assert guess_format(tmp_path / name) == fmt
