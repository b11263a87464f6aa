"""The evo round trip: `mirage track --tum` and the truth as TUM go through `evo_ape`
unaligned, and evo's translation and rotation APE are the position and rotation errors
that `mirage report --truth` gives, frame by frame. So the TUM file is camera-to-world
(what evo compares) and the two tools measure the same thing."""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import SAMPLE

pytest.importorskip("evo", reason="evo is not installed (the [test] extra installs it)")
# evo's command next to this interpreter (the venv's bin/, found without activating the
# venv: `venv/bin/pytest`), else on PATH
_HERE = Path(sys.executable).parent / "evo_ape"
EVO_APE = str(_HERE) if _HERE.is_file() else shutil.which("evo_ape")
if EVO_APE is None:
    pytest.skip("evo_ape is neither next to python nor on PATH", allow_module_level=True)
END = 20  # two thirds of a second of the orbit


def evo_ape(ref, est, relation: str, out, home) -> tuple[dict, np.ndarray]:
    """evo_ape's statistics and per-pose errors (from its --save_results zip)."""
    subprocess.run(
        [EVO_APE, "tum", ref, est, "--pose_relation", relation, "--save_results", out,
         "--no_warnings"],
        check=True, capture_output=True, env={**os.environ, "HOME": str(home)}, timeout=120,
    )  # fmt: skip
    with zipfile.ZipFile(out) as z:
        stats = json.loads(z.read("stats.json"))
        errors = np.load(io.BytesIO(z.read("error_array.npy")))
    return stats, errors


def test_evo_ape_equals_mirage_report(sample_model, tmp_path):
    est, tum = tmp_path / "est.csv", tmp_path / "est.tum"
    track = [sys.executable, "-m", "mirage_cli", "-q", "track", SAMPLE / "orbit.mp4",
             "--model", sample_model, "--end", END, "-o", est, "--tum", tum]  # fmt: skip
    subprocess.run(list(map(str, track)), check=True, timeout=300)
    report = [sys.executable, "-m", "mirage_cli", "-q", "report", est,
              "--path", SAMPLE / "desired_path.yaml", "--truth", SAMPLE / "orbit_truth.csv",
              "-o", tmp_path / "report.csv"]  # fmt: skip
    subprocess.run(list(map(str, report)), check=True, timeout=300)
    rep = pd.read_csv(tmp_path / "report.csv")
    ok = rep["status"] == "ok"
    assert ok.sum() == END  # every frame of this stretch is tracked

    # the truth as TUM, at its own times (camera-to-world, qw last)
    truth = pd.read_csv(SAMPLE / "orbit_truth.csv").iloc[:END]
    cols = ["time_s", "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]
    truth_tum = tmp_path / "truth.tum"
    truth[cols].to_csv(truth_tum, sep=" ", header=False, index=False, float_format="%.9f")

    trans, e_trans = evo_ape(truth_tum, tum, "trans_part", tmp_path / "t.zip", tmp_path)
    rot, e_rot = evo_ape(truth_tum, tum, "angle_deg", tmp_path / "r.zip", tmp_path)
    pos = rep["position_error_m"][ok].to_numpy()
    ang = rep["rotation_error_deg"][ok].to_numpy()
    assert len(e_trans) == len(pos) == END
    # no alignment: evo compares the raw poses, as the report does
    np.testing.assert_allclose(e_trans, pos, atol=1e-6)
    assert abs(trans["rmse"] - np.sqrt(np.mean(pos**2))) < 1e-6
    assert abs(trans["median"] - np.median(pos)) < 1e-6
    np.testing.assert_allclose(e_rot, ang, atol=1e-4)
    assert abs(rot["median"] - np.median(ang)) < 1e-4
    assert 0 < trans["rmse"] < 0.01  # and the poses are good: under a centimetre
