"""mirage demo end to end on sample_data/ (slow: runs the whole pipeline once)."""

import numpy as np
import pandas as pd
import yaml
from conftest import SAMPLE, assert_one_line_error

from mirage_cli.report import quat_angle_deg
from mirage_cli.trajectory import read_pose_csv


def test_demo_missing_sample_data(tmp_path, mirage):
    proc = mirage("demo", "--out", tmp_path / "d", "--sample-data", tmp_path / "nope")
    assert_one_line_error(proc, 2, "--sample-data")
    (tmp_path / "half").mkdir()
    proc = mirage("demo", "--out", tmp_path / "d", "--sample-data", tmp_path / "half")
    assert_one_line_error(proc, 2, "lacks calibration")


def test_demo_end_to_end(tmp_path, mirage):
    out = tmp_path / "demo"
    proc = mirage("demo", "--out", out)
    assert proc.returncode == 0, proc.stderr
    for step in ("calibrate", "build-model", "track", "report"):
        assert f"mirage {step}" in proc.stdout
    for name in ("camera.yaml", "landmark.mirage", "report.png", "mirage.yaml"):
        assert (out / name).stat().st_size > 0
    poses = pd.read_csv(out / "poses.csv")
    report = pd.read_csv(out / "report.csv")
    assert len(poses) == len(report) == len(pd.read_csv(SAMPLE / "orbit_truth.csv"))
    s = yaml.safe_load((out / "summary.yaml").read_text())
    assert s["frames"] == len(poses)
    assert s["tracked"] == int((poses["status"] == "ok").sum())

    # the summary's position error, recomputed straight from poses.csv and the truth
    est, truth = read_pose_csv(out / "poses.csv"), read_pose_csv(SAMPLE / "orbit_truth.csv")
    m = est.merge(truth, on="frame", suffixes=("", "_t"))
    m = m[(m["status"] == "ok") & (m["status_t"] == "ok")]
    d = np.linalg.norm(
        m[["x_m", "y_m", "z_m"]].to_numpy() - m[["x_m_t", "y_m_t", "z_m_t"]].to_numpy(), axis=1
    )
    pe = s["errors"]["position_error_m"]
    assert pe["n"] == len(d)
    assert abs(pe["mean"] - d.mean()) < 1e-6
    assert abs(pe["median"] - np.median(d)) < 1e-6
    q, qt = m[["qw", "qx", "qy", "qz"]].to_numpy(), m[["qw_t", "qx_t", "qy_t", "qz_t"]].to_numpy()
    assert abs(s["errors"]["rotation_error_deg"]["mean"] - quat_angle_deg(q, qt).mean()) < 1e-5

    # the folder is a project: mirage.yaml supplies every report option
    again = mirage("report", "poses.csv", "-o", "again.csv", cwd=out)
    assert again.returncode == 0, again.stderr
    pd.testing.assert_frame_equal(pd.read_csv(out / "again.csv"), report)
