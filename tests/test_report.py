"""mirage report: exact errors on constructed trajectories, path files, CLI failures."""

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import assert_one_line_error

from mirage_cli.errors import InputError
from mirage_cli.path import CirclePath, load_path, path_from_dict, wrap_deg
from mirage_cli.pose import Pose, look_at, matrix_from_rpy
from mirage_cli.records import FrameRecord, Status
from mirage_cli.report import longest_run, make_report
from mirage_cli.trajectory import read_pose_csv, write_trajectory

LOOK = (0.0, 0.0, 0.28)


def circle_poses(radius, n=72, z=0.55, yaw_offset_deg=0.0, ccw=True, turns=1.0):
    """Cameras on a circle looking at LOOK, optionally turned by a yaw offset."""
    a = np.linspace(0, 2 * np.pi * turns, n, endpoint=False) * (1 if ccw else -1)
    out = []
    for ai in a:
        p = look_at([radius * np.cos(ai), radius * np.sin(ai), z], LOOK)
        r, pi, y = p.rpy_deg
        out.append(Pose.from_center_rpy(p.center, r, pi, y + yaw_offset_deg))
    return out


def write(tmp_path, name, poses, times=None, status=None):
    path = tmp_path / name
    times = [float("nan")] * len(poses) if times is None else times
    write_trajectory(
        path,
        [
            FrameRecord(Status.OK if p is not None else Status.LOST, p, i, t)
            for i, (p, t) in enumerate(zip(poses, times, strict=True))
        ],
    )
    if status is not None:
        df = pd.read_csv(path, dtype=str, keep_default_na=False)
        df["status"] = status
        for c in df.columns[3:]:
            df.loc[df["status"] != "ok", c] = ""
        df.to_csv(path, index=False)
    return path


def circle_yaml(tmp_path, direction="ccw", radius=1.5, **kw):
    d = {"type": "circle", "center_m": [0, 0], "radius_m": radius, "height_m": 0.55,
         "direction": direction, "look_at_m": list(LOOK), **kw}  # fmt: skip
    p = tmp_path / f"path_{direction}.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


# --------------------------------------------------------------------------------------
# exactness
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("direction,expected", [("ccw", -0.1), ("cw", 0.1)])
def test_circle_cross_track_exact(tmp_path, direction, expected):
    f = write(tmp_path, "p.csv", circle_poses(1.6, z=0.60, ccw=direction == "ccw"))
    rep = make_report(read_pose_csv(f), load_path(circle_yaml(tmp_path, direction)))
    t = rep.table
    assert np.abs(t["cross_track_m"] - expected).max() < 1e-6
    assert np.abs(t["height_error_m"] - 0.05).max() < 1e-6
    assert np.abs(t["heading_error_deg"]).max() < 1e-4  # looking exactly at look_at
    assert rep.summary["tracked_pct"] == 100.0
    e = rep.summary["errors"]["cross_track_m"]
    assert abs(e["rms"] - 0.1) < 1e-6 and abs(e["max"] - 0.1) < 1e-6


def test_circle_arc_length_follows_direction():
    c = CirclePath((0.0, 0.0), 2.0, 0.0, "cw")
    P = np.array([[2.0, 0, 0], [0, -2.0, 0], [-2.0, 0, 0], [0, 2.0, 0]])
    e = c.errors(P, np.zeros(4))
    np.testing.assert_allclose(e.path_s_m, np.pi * np.array([0, 1, 2, 3]), atol=1e-12)
    # heading tangent: cw at (2, 0) moves along -y -> desired -90; yaw 0 is 90 deg left
    np.testing.assert_allclose(e.heading_error_deg[0], 90.0, atol=1e-9)


@pytest.mark.parametrize("offset", [7.5, -30.0, 179.0])
def test_heading_error_known_rotation(tmp_path, offset):
    f = write(tmp_path, "p.csv", circle_poses(1.5, yaw_offset_deg=offset, n=36))
    rep = make_report(read_pose_csv(f), load_path(circle_yaml(tmp_path)))
    assert np.abs(rep.table["heading_error_deg"] - offset).max() < 1e-4
    assert np.abs(rep.table["cross_track_m"]).max() < 1e-6


def test_heading_error_wraps():
    np.testing.assert_allclose(wrap_deg([180, -180, 190, -190, 540, 0]),
                               [180, 180, -170, 170, 180, 0])  # fmt: skip


@pytest.mark.parametrize("offset", [0.3, -0.25])
def test_straight_polyline_lateral_offset(tmp_path, offset):
    # path along +x at y = 1; a vehicle at y = 1 + offset is `offset` to the LEFT
    path = tmp_path / "line.csv"
    path.write_text("x_m,y_m,z_m\n-2,1,0.5\n0,1,0.5\n5,1,0.5\n")
    xs = np.linspace(-1.5, 4.5, 40)
    poses = [Pose.from_center_rpy([x, 1 + offset, 0.7], 0, 0, 12.0) for x in xs]
    rep = make_report(read_pose_csv(write(tmp_path, "p.csv", poses)), load_path(path))
    t = rep.table
    assert np.abs(t["cross_track_m"] - offset).max() < 1e-6
    assert np.abs(t["height_error_m"] - 0.2).max() < 1e-6
    assert np.abs(t["path_s_m"] - (xs + 2)).max() < 1e-6
    assert np.abs(t["heading_error_deg"] - 12.0).max() < 1e-6  # tangent heading is 0
    assert "along_track_m" not in t.columns


def test_diagonal_polyline_left_is_positive():
    p = path_from_dict({"type": "polyline", "points_m": [[0, 0, 0], [1, 1, 0], [2, 0, 0]]})
    # first leg heads north-east: its left is north-west
    e = p.errors(np.array([[0.5 - 0.1, 0.5 + 0.1, 0], [1.5 + 0.1, 0.5 + 0.1, 0]]), [0, 0])
    np.testing.assert_allclose(e.cross_track_m, [0.1 * np.sqrt(2), 0.1 * np.sqrt(2)])


def test_timed_polyline_along_track(tmp_path):
    # 10 m in 10 s; the vehicle is 0.5 m ahead of schedule all the way
    path = tmp_path / "timed.yaml"
    path.write_text(yaml.safe_dump({"type": "polyline", "heading": "tangent",
                                    "points_m": [[0, 0, 1, 0], [10, 0, 1, 10]]}))  # fmt: skip
    t = np.linspace(0, 9, 19)
    poses = [Pose.from_center_rpy([ti + 0.5, -0.2, 1.0], 0, 0, 0) for ti in t]
    rep = make_report(read_pose_csv(write(tmp_path, "p.csv", poses, times=t)), load_path(path))
    tab = rep.table
    assert np.abs(tab["along_track_m"] - 0.5).max() < 1e-6
    assert np.abs(tab["cross_track_m"] + 0.2).max() < 1e-6
    assert abs(rep.summary["errors"]["along_track_m"]["mean"] - 0.5) < 1e-6


def test_truth_errors_and_lost_frames(tmp_path):
    truth = circle_poses(1.6, n=50)
    est = [Pose.from_center(p.R_wc, p.center + [0.03, 0.0, -0.04]) for p in truth]
    rot = matrix_from_rpy(0, 0, np.radians(2.0))  # 2 deg about world z
    est = [Pose.from_center(rot @ p.R_wc, p.center) for p in est]
    status = ["ok"] * 50
    status[10:17] = ["lost"] * 7
    status[30:33] = ["lost"] * 3
    f = write(tmp_path, "est.csv", est, times=np.arange(50) / 10, status=status)
    ft = write(tmp_path, "truth.csv", truth, times=np.arange(50) / 10)
    rep = make_report(read_pose_csv(f), load_path(circle_yaml(tmp_path)), read_pose_csv(ft))
    ok = rep.table["status"] == "ok"
    assert np.abs(rep.table.loc[ok, "position_error_m"] - 0.05).max() < 1e-5
    assert np.abs(rep.table.loc[ok, "rotation_error_deg"] - 2.0).max() < 1e-3
    assert rep.table.loc[~ok, "position_error_m"].isna().all()
    s = rep.summary
    assert s["frames"] == 50 and s["tracked"] == 40 and s["tracked_pct"] == 80.0
    assert s["longest_lost"]["frames"] == 7
    assert abs(s["longest_lost"]["seconds"] - 0.7) < 1e-9
    assert s["longest_lost"]["first_frame"] == "10"


def test_tum_truth_is_matched_by_time(tmp_path, mirage):
    """A TUM truth (times, no frame ids, its own rate) gives the errors a CSV truth gives."""
    truth = circle_poses(1.6, n=100)
    est = [Pose.from_center(p.R_wc, p.center + [0.03, 0.0, -0.04]) for p in truth[::2]]
    f = write(tmp_path, "est.csv", est, times=np.arange(50) / 10)
    recs = [FrameRecord(Status.OK, p, i, i / 20 + 0.002) for i, p in enumerate(truth)]
    write_trajectory(tmp_path / "truth.txt", recs[::-1], "tum")  # any order
    out = tmp_path / "r.csv"
    proc = mirage("report", f, "--path", circle_yaml(tmp_path), "--truth", tmp_path / "truth.txt",
                  "-o", out)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    df = pd.read_csv(out)
    assert len(df) == 50 and np.abs(df["position_error_m"] - 0.05).max() < 1e-5
    assert df["rotation_error_deg"].abs().max() < 1e-3
    # truth 0.5 s away from every frame matches nothing: a one-line error
    write_trajectory(tmp_path / "late.txt", [FrameRecord(Status.OK, truth[0], 0, 100.0)], "tum")
    proc = mirage("report", f, "--path", circle_yaml(tmp_path), "--truth", tmp_path / "late.txt")
    assert_one_line_error(proc, 2, "overlap")


def test_longest_run():
    assert longest_run(np.array([0, 1, 1, 0, 1, 1, 1], bool)) == (3, 4)
    assert longest_run(np.zeros(5, bool)) == (0, -1)
    assert longest_run(np.ones(4, bool)) == (4, 0)


@pytest.mark.parametrize(
    "data,contains",
    [
        ({"type": "spiral"}, "unknown path type"),
        ({"type": "circle", "radius_m": -1}, "radius_m must be > 0"),
        ({"type": "circle", "radius_m": 0}, "radius_m must be > 0"),
        ({"type": "circle"}, "missing 'radius_m'"),
        ({"type": "circle", "radius_m": 1, "direction": "up"}, "direction"),
        ({"type": "polyline", "points_m": [[0, 0, 0]]}, "at least 2 waypoints"),
        ({"type": "polyline", "points_m": [[0, 0, 0], [0, 0, 1]]}, "no direction"),
        ({"type": "polyline", "points_m": [[0, 0, 0, 1], [1, 0, 0, 1]]}, "increasing"),
        ({"type": "circle", "radius_m": 1, "heading": "north"}, "heading"),
    ],
)
def test_path_validation(data, contains):
    with pytest.raises(InputError, match=contains):
        path_from_dict(data)


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------
def test_cli_writes_outputs(tmp_path, mirage):
    est = circle_poses(1.6, n=40)
    f = write(tmp_path, "p.csv", est, times=np.arange(40) / 30)
    ft = write(tmp_path, "t.csv", est, times=np.arange(40) / 30)
    out = tmp_path / "r.csv"
    proc = mirage("report", f, "--path", circle_yaml(tmp_path), "--truth", ft, "-o", out,
                  "--summary", tmp_path / "s.yaml", "--plot", tmp_path / "r.png")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    df = pd.read_csv(out)
    assert list(df.columns) == [
        "frame", "time_s", "status", "x_m", "y_m", "z_m", "path_s_m", "cross_track_m",
        "height_error_m", "heading_error_deg", "position_error_m", "rotation_error_deg",
    ]  # fmt: skip
    assert np.allclose(df["cross_track_m"], -0.1, atol=1e-5)
    s = yaml.safe_load((tmp_path / "s.yaml").read_text())
    assert s["tracked_pct"] == 100.0 and s["errors"]["position_error_m"]["max"] < 1e-5
    assert (tmp_path / "r.png").stat().st_size > 10_000
    assert "cross_track_m" in proc.stdout and "100.0%" in proc.stdout


def test_cli_all_lost(tmp_path, mirage):
    f = write(tmp_path, "p.csv", circle_poses(1.6, n=10), status=["lost"] * 10)
    proc = mirage("report", f, "--path", circle_yaml(tmp_path), "-o", tmp_path / "r.csv",
                  "--summary", tmp_path / "s.yaml", "--plot", tmp_path / "r.png")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    s = yaml.safe_load((tmp_path / "s.yaml").read_text())
    assert s["tracked_pct"] == 0.0 and s["tracked"] == 0
    assert s["longest_lost"]["frames"] == 10
    assert s["errors"]["cross_track_m"]["n"] == 0
    assert "0.0%" in proc.stdout
    assert (tmp_path / "r.png").exists()


def test_cli_missing_column(tmp_path, mirage):
    f = write(tmp_path, "p.csv", circle_poses(1.6, n=5))
    df = pd.read_csv(f).drop(columns=["qz"])
    df.to_csv(f, index=False)
    proc = mirage("report", f, "--path", circle_yaml(tmp_path), "-o", tmp_path / "r.csv")
    assert_one_line_error(proc, 2, "missing column(s) qz")
    assert not (tmp_path / "r.csv").exists()


def test_cli_empty_pose_csv(tmp_path, mirage):
    f = tmp_path / "p.csv"
    f.write_text("")
    proc = mirage("report", f, "--path", circle_yaml(tmp_path), "-o", tmp_path / "r.csv")
    assert_one_line_error(proc, 2, "empty")
    f.write_text("frame,time_s,status,x_m,y_m,z_m,qw,qx,qy,qz\n")
    proc = mirage("report", f, "--path", circle_yaml(tmp_path), "-o", tmp_path / "r.csv")
    assert_one_line_error(proc, 2, "no rows")


@pytest.mark.parametrize(
    "text,contains",
    [
        ("type: spiral\nradius_m: 1\n", "unknown path type 'spiral'"),
        ("type: circle\nradius_m: -1.5\n", "radius_m must be > 0"),
        ("type: circle\nradius_m: [1, \n", "not valid YAML"),
        ("- 1\n- 2\n", "must be a YAML mapping"),
        ("type: polyline\npoints_m: [[0, 0, 0]]\n", "at least 2 waypoints"),
    ],
)
def test_cli_bad_path_file(tmp_path, mirage, text, contains):
    f = write(tmp_path, "p.csv", circle_poses(1.6, n=5))
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    proc = mirage("report", f, "--path", bad, "-o", tmp_path / "r.csv")
    assert_one_line_error(proc, 2, contains)


def test_cli_truth_without_overlap(tmp_path, mirage):
    f = write(tmp_path, "p.csv", circle_poses(1.6, n=5))
    t = tmp_path / "t.csv"
    pd.read_csv(f).assign(frame=lambda d: d["frame"] + 100).to_csv(t, index=False)
    proc = mirage("report", f, "--path", circle_yaml(tmp_path), "--truth", t,
                  "-o", tmp_path / "r.csv")  # fmt: skip
    assert_one_line_error(proc, 2, "do not overlap")


def test_cli_waypoint_csv_bad(tmp_path, mirage):
    f = write(tmp_path, "p.csv", circle_poses(1.6, n=5))
    w = tmp_path / "w.csv"
    w.write_text("x_m,y_m\n0,0\n1,1\n")
    proc = mirage("report", f, "--path", w, "-o", tmp_path / "r.csv")
    assert_one_line_error(proc, 2, "missing waypoint column(s) z_m")


def test_polyline_matches_brute_force():
    """Vectorised nearest point = dense sampling of the path, on random zigzags."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        pts = np.column_stack([np.cumsum(rng.uniform(0.2, 1.0, 6)), rng.normal(0, 1, 6),
                               rng.uniform(0, 1, 6)])  # fmt: skip
        p = path_from_dict({"type": "polyline", "points_m": pts.tolist()})
        P = np.column_stack([rng.uniform(-1, 6, 200), rng.uniform(-3, 3, 200), np.zeros(200)])
        e = p.errors(P, np.zeros(200))
        u = np.linspace(0, 1, 2001)[:, None]
        dense = np.concatenate([a + u * (b - a) for a, b in zip(pts[:-1], pts[1:], strict=True)])[
            :, :2
        ]
        dmin = np.sqrt(((P[:, None, :2] - dense[None]) ** 2).sum(-1)).min(axis=1)
        assert np.abs(np.abs(e.cross_track_m) - dmin).max() < 2e-3


def test_visibility_summary(tmp_path):
    poses = circle_poses(1.6, n=20)
    status = ["ok"] * 20
    status[5:10] = ["lost"] * 5
    f = write(tmp_path, "p.csv", poses, status=status)
    ft = write(tmp_path, "t.csv", poses)
    t = read_pose_csv(ft)
    t["landmark_visible"] = ["1.0"] * 4 + ["0.0"] * 7 + ["0.8"] * 9  # frames 4..10 hidden
    rep = make_report(read_pose_csv(f), load_path(circle_yaml(tmp_path)), t)
    v = rep.summary["visibility"]
    assert v == {"frames_in_view": 13, "tracked_in_view_pct": 100.0,
                 "frames_out_of_view": 7, "ok_out_of_view": 2}  # fmt: skip


@pytest.mark.parametrize("timed", [True, False])
def test_two_lap_polyline_keeps_the_along_path_distance_of_its_lap(timed):
    """A desired path that circles twice passes every place twice: a frame on the second
    lap took the first lap's nearest point (the along-track error jumped by a lap).
    The pass the timing expects (or, untimed, the one after the previous frame) is used."""
    a = np.linspace(0, 4 * np.pi, 241)  # two laps, waypoints every 3 deg
    pts = np.column_stack([np.cos(a), np.sin(a), np.full_like(a, 0.5)])
    lap = 120 * 2 * np.sin(np.radians(1.5))  # the polyline's length of one lap (6.28 m)
    times = np.linspace(0.0, 20.0, len(a))
    data = {"type": "polyline", "points_m": pts.tolist()}
    if timed:
        data["time_s"] = times.tolist()
    p = path_from_dict(data)
    ft = np.linspace(0.05, 19.95, 400)  # the camera 2 cm outside, on time
    fa = np.interp(ft, times, a)
    xyz = np.column_stack([1.02 * np.cos(fa), 1.02 * np.sin(fa), np.full_like(fa, 0.5)])
    e = p.errors(xyz, np.zeros(len(fa)), ft)
    assert np.all(np.diff(e.path_s_m) > 0), "the arc length goes on into the second lap"
    assert e.path_s_m[-1] > 1.9 * lap
    if timed:
        assert np.abs(e.along_track_m).max() < 0.01
