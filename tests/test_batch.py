"""`mirage batch`: a campaign of short flights gives the same files serially and on a Dask
cluster, reports a corrupt flight while the others finish, resumes without redoing
finished flights, and refuses a bad campaign file with one line."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pandas as pd
import pytest
from conftest import SAMPLE, own_signal_handlers

from mirage_cli import cli
from mirage_cli.frames import FrameSource
from mirage_cli.pipelines.campaign import OUTPUTS, load_campaign

try:
    import distributed
except ImportError:
    distributed = None
# only the Dask run needs distributed; serial batches and campaign files are tested without
needs_distributed = pytest.mark.skipif(
    distributed is None, reason="mirage batch --scheduler needs distributed (the [batch] extra)"
)

N = 5  # frames a flight
STARTS = {"north": 0, "west": 150, "south": 300}  # three stretches of the sample orbit


@pytest.fixture(scope="module")
def campaign(sample_model, tmp_path_factory):
    """Three short flights cut from the sample orbit (with their truth, renumbered), a
    corrupt one, and the campaign YAML naming them."""
    d = tmp_path_factory.mktemp("campaign")
    (d / "flights").mkdir()
    truth = pd.read_csv(SAMPLE / "orbit_truth.csv", dtype=str, keep_default_na=False)
    src = FrameSource([SAMPLE / "orbit.mp4"])
    for name, s in STARTS.items():
        w = cv2.VideoWriter(str(d / "flights" / f"{name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"),
                            30.0, src.size)  # fmt: skip
        for f in src.frames(s, s + N):
            w.write(f.image)
        w.release()
        t = truth.iloc[s : s + N].copy()
        t["frame"] = [str(i) for i in range(N)]
        t["time_s"] = [f"{i / 30:.6f}" for i in range(N)]
        t.to_csv(d / "flights" / f"{name}_truth.csv", index=False)
    (d / "flights" / "corrupt.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(4000))
    flights = "".join(
        f"  - {{video: flights/{n}.mp4, truth: flights/{n}_truth.csv}}\n" for n in STARTS
    )
    (d / "campaign.yaml").write_text(
        f"defaults:\n  model: {sample_model}\n  path: {SAMPLE / 'desired_path.yaml'}\n"
        f"flights:\n{flights}  - video: flights/corrupt.mp4\n"
    )
    return d / "campaign.yaml"


@pytest.fixture(scope="module")
def cluster():
    """Two worker processes, which load OpenCV and the compiled solver in the background
    while the serial run goes on (as a long-running cluster would have)."""
    from mirage_cli.solver import warm_up

    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as c,
        distributed.Client(c) as client,
    ):
        warm = [
            client.submit(warm_up, pure=False, workers=[w])
            for w in client.scheduler_info()["workers"]
        ]
        yield c
        del warm


def batch(capsys, *args) -> tuple[int, str, str]:
    """`mirage batch ...` in this process (the model and solver load once for all)."""
    capsys.readouterr()
    with own_signal_handlers(), pytest.raises(SystemExit) as e:
        cli.main(["batch", *map(str, args)])
    out, err = capsys.readouterr()
    return e.value.code, out, err


def one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("mirage: error: "), err
    return lines[0]


def without_ms(path) -> list[list[str]]:
    rows = [ln.split(",") for ln in path.read_text().splitlines()]
    k = rows[0].index("ms")
    return [r[:k] + r[k + 1 :] for r in rows]


@needs_distributed
def test_serial_and_dask_agree_and_a_campaign_resumes(campaign, cluster, tmp_path, capsys):
    serial, dask = tmp_path / "serial", tmp_path / "dask"
    code, out, err = batch(capsys, campaign, "--workers", 1, "--out", serial)
    # the corrupt flight fails on its own: one line in the summary, exit 2 at the end
    assert code == 2
    assert "1 of 4 flights failed (corrupt)" in one_error_line(err)
    assert "corrupt: failed: cannot open video" in out
    code, out, err = batch(capsys, campaign, "--scheduler", cluster.scheduler_address,
                           "--out", dask)  # fmt: skip
    assert code == 2 and "(corrupt)" in one_error_line(err), out

    for name in STARTS:
        a, b = serial / name, dask / name
        assert without_ms(a / "poses.csv") == without_ms(b / "poses.csv")
        assert len(without_ms(a / "poses.csv")) == N + 1
        for f in ("report.csv", "summary.yaml"):
            assert (a / f).read_bytes() == (b / f).read_bytes(), f
    tables = [pd.read_csv(d / "campaign.csv") for d in (serial, dask)]
    for t in tables:
        assert list(t["flight"]) == [*STARTS, "corrupt"]
        assert list(t["status"]) == ["ok", "ok", "ok", "failed"]
        assert "cannot open video" in t["reason"].iloc[3]
        ok = t.iloc[:3]
        assert (ok["frames"] == N).all() and (ok["tracked_pct"] == 100).all()
        assert (ok["position_error_median_m"] < 0.01).all()  # against the truth
        assert (ok["rotation_error_p95_deg"] < 0.5).all()
        assert (ok["path_error_p95_m"] >= ok["path_error_median_m"]).all()
    numbers = [c for c in tables[0].columns if c not in ("seconds", "reason")]
    pd.testing.assert_frame_equal(tables[0][numbers], tables[1][numbers])
    assert (dask / "campaign.png").stat().st_size > 10_000

    # an interrupted run: one flight's output cut short (its marker still there), another
    # stopped before its marker; the re-run redoes just these two, on the local pool
    kept = [(dask / "north" / f).stat().st_mtime_ns for f in OUTPUTS]
    poses = dask / "west" / "poses.csv"
    poses.write_text("".join(poses.read_text().splitlines(keepends=True)[:3]))
    (dask / "south" / "done.json").unlink()
    code, out, err = batch(capsys, campaign, "--workers", 2, "--out", dask)
    assert code == 2, err
    assert "north: complete from an earlier run, skipped" in out
    assert "west: ok" in out and "south: ok" in out
    assert [(dask / "north" / f).stat().st_mtime_ns for f in OUTPUTS] == kept  # not redone
    for name in ("west", "south"):  # the pool's files are the serial run's too
        assert without_ms(serial / name / "poses.csv") == without_ms(dask / name / "poses.csv")
        assert (serial / name / "report.csv").read_bytes() == (
            dask / name / "report.csv"
        ).read_bytes()
    t = pd.read_csv(dask / "campaign.csv")
    assert list(t["resumed"]) == [True, False, False, False]
    assert list(t["status"]) == ["ok", "ok", "ok", "failed"]


BAD = [
    ("flights:\n  - {vidoe: a.mp4}\n", "unknown key 'vidoe' (did you mean 'video'?)"),
    ("flights:\n  - {video: nothere.mp4}\n", "nothere.mp4 not found"),
    ("flights:\n  - {video: a.mp4, model: m.mirage}\n", "has no 'path'"),
    ("defaluts: {}\nflights: [a.mp4]\n", "did you mean 'defaults'?"),
    ("flights: [a.mp4, sub/a.mp4]\n", "are both named 'a'"),
    ("videos: 'none/*.mp4'\n", "matches no file"),
    ("flights:\n  - {video: a.mp4, start: 9, end: 3}\n", "'end' 3 must come after 'start' 9"),
    ("flights: [a.mp4\n", "not valid YAML"),
    ("flights: []\n", "lists no flights"),
]


@pytest.mark.parametrize("text,message", BAD)
def test_bad_campaign_is_one_line(text, message, tmp_path, capsys):
    (tmp_path / "sub").mkdir()
    for f in ("a.mp4", "sub/a.mp4", "m.mirage", "p.yaml"):
        (tmp_path / f).write_bytes(b"x")
    if "model" not in text and "vidoe" not in text:
        text = "defaults: {model: m.mirage, path: p.yaml}\n" + text
    (tmp_path / "c.yaml").write_text(text)
    code, out, err = batch(capsys, tmp_path / "c.yaml")
    assert code == 2 and message in one_error_line(err), err
    assert not (tmp_path / "c_out").exists()  # checked before anything is written


def test_scheduler_without_distributed_is_one_line(campaign, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails
    code, _, err = batch(capsys, campaign, "--scheduler", "tcp://127.0.0.1:1", "--out", tmp_path)
    assert code == 2
    want = "needs distributed: pip install -e '.[batch]' in the mirage-cli checkout"
    assert want in one_error_line(err)


def test_campaign_file_globs_defaults_and_relative_paths(tmp_path):
    for f in ("v/f10.mp4", "v/f2.mp4", "imgs/0001.png", "m.mirage", "other.mirage", "p.yaml"):
        (tmp_path / f).parent.mkdir(exist_ok=True)
        (tmp_path / f).write_bytes(b"x")
    (tmp_path / "c.yaml").write_text(
        "defaults: {model: m.mirage, path: p.yaml, output: results, end: 4s}\n"
        "flights:\n  - {video: imgs/, name: stills, model: other.mirage, start: 2}\n"
        "videos: 'v/*.mp4'\n"
    )
    c = load_campaign(tmp_path / "c.yaml")
    assert c.output == tmp_path / "results"
    assert [f.name for f in c.flights] == ["stills", "f2", "f10"]  # natural order
    stills, f2 = c.flights[0], c.flights[1]
    assert stills.model == str(tmp_path / "other.mirage") and stills.video == str(tmp_path / "imgs")
    assert f2.model == str(tmp_path / "m.mirage") and f2.path == str(tmp_path / "p.yaml")
    assert (str(stills.start), str(stills.end), f2.start) == ("2", "4s", None)
    assert (
        load_campaign(tmp_path / "c.yaml", tmp_path / "elsewhere").output == tmp_path / "elsewhere"
    )


def test_campaign_truth_from_tum_with_offset_and_transform(campaign, tmp_path, capsys):
    """A flight's truth options are `mirage report`'s: a TUM file of a motion-capture body,
    its clock 0.5 s off and the camera 4 cm from the body, gives the pose-CSV truth's errors."""
    from mirage_cli.pose import Pose, matrix_from_quat, quat_from_matrix
    from mirage_cli.trajectory import read_pose_csv, row_pose

    flights = campaign.parent / "flights"
    q_bc = np.array([0.5, -0.5, 0.5, -0.5])  # camera looking along the body's x axis
    T_bc = Pose(matrix_from_quat(q_bc), np.array([0.04, 0.0, -0.02]))  # camera -> body
    truth = read_pose_csv(flights / "north_truth.csv")
    rows = []
    for i in range(len(truth)):
        T_wb = row_pose(truth.iloc[i]).inverse() @ T_bc.inverse()  # body -> W
        q = quat_from_matrix(T_wb.R)
        rows.append([truth["time_s"].iloc[i] - 0.5, *T_wb.t, *q[[1, 2, 3, 0]]])
    np.savetxt(tmp_path / "mocap.tum", np.array(rows), fmt="%.17g")
    head = campaign.read_text().split("flights:")[0]  # the defaults: model, path
    text = head.replace("\n  path:", "\n  t_offset: 0.5\n  path:") + (
        f"flights:\n  - {{video: {flights / 'north.mp4'}, name: csv,\n"
        f"     truth: {flights / 'north_truth.csv'}, t_offset: 0}}\n"
        f"  - {{video: {flights / 'north.mp4'}, name: tum, truth: {tmp_path / 'mocap.tum'},\n"
        f"     truth_transform: '0.04 0 -0.02 {' '.join(map(str, q_bc))}'}}\n"
    )
    (tmp_path / "c.yaml").write_text(text)
    code, out, err = batch(capsys, tmp_path / "c.yaml", "--workers", 1, "--out", tmp_path / "o")
    assert code == 0, err
    cols = ["position_error_m", "rotation_error_deg"]
    ref = pd.read_csv(tmp_path / "o" / "csv" / "report.csv")[cols]
    got = pd.read_csv(tmp_path / "o" / "tum" / "report.csv")[cols]
    assert ref.notna().all().all() and len(ref) == N
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    for value in (".inf", "abc"):  # one line, exit 2, as report's --t-offset
        bad = text.replace("t_offset: 0.5", f"t_offset: {value}")
        (tmp_path / "bad.yaml").write_text(bad)
        code, _, err = batch(capsys, tmp_path / "bad.yaml", "--out", tmp_path / "b")
        assert code == 2 and "'t_offset' must be a finite number" in one_error_line(err)
