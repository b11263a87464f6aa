"""The README's Python code runs verbatim (from a folder holding the sample data, as a
reader's project would) and does what its text says."""

import os
import re

import numpy as np
from conftest import ROOT, SAMPLE

from mirage_cli import Camera

README = (ROOT / "README.md").read_text(encoding="utf-8")


def python_blocks(heading: str) -> list[str]:
    """The ```python blocks between `heading` and the next heading of the same or a higher
    level."""
    level = len(heading) - len(heading.lstrip("#"))
    start = README.index(f"\n{heading}\n")
    nxt = re.compile(rf"\n#{{1,{level}}} ").search(README, start + len(heading) + 2)
    section = README[start : nxt.start() if nxt else len(README)]
    return re.findall(r"```python\n(.*?)```", section, re.S)


def run_blocks(heading: str, cwd) -> dict:
    """Execute the section's python blocks in order, in one namespace, from `cwd`."""
    blocks = python_blocks(heading)
    assert blocks, f"no python code under {heading!r}"
    ns: dict = {"__name__": "__readme__"}
    old = os.getcwd()
    os.chdir(cwd)
    try:
        for code in blocks:
            exec(compile(code, f"README.md ({heading})", "exec"), ns)
    finally:
        os.chdir(old)
    return ns


def test_python_api_examples_run_and_find_the_poses(sample_model, tmp_path, capsys):
    # a project folder as the README assumes: the sample data and a built model
    (tmp_path / "sample_data").symlink_to(SAMPLE, target_is_directory=True)
    (tmp_path / "landmark.mirage").symlink_to(sample_model)
    ns = run_blocks("## Python API", tmp_path)
    lines = capsys.readouterr().out.splitlines()
    tracked = [ln for ln in lines if ln.split()[0].isdigit()]
    assert len(tracked) == 30 and all(" ok " in ln for ln in tracked), tracked[:3]
    est, truth = ns["est"], ns["truth"]
    assert est.success, est.reason
    assert est.pose.distance_to(truth) < 0.005 and est.pose.angle_to(truth) < 0.2
    assert not est.inliers[:10].any() and est.inliers[10:].mean() >= 0.95  # outliers out
    assert est.rmse_px < 1.0 and 0 < est.sigma_pos_m < 0.01
    assert not any(ln.startswith("no pose") for ln in lines)


def test_camera_file_opencv_snippet_reads_the_camera():
    ns = run_blocks("### The camera file", ROOT)
    cam = Camera.load(SAMPLE / "camera_truth.yaml")
    assert ns["K"].shape == (3, 3) and np.allclose(ns["K"], cam.K)
    assert np.allclose(np.ravel(ns["dist"]), cam.dist)
