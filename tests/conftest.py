import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data"


def run_mirage(*args, cwd=None):
    """Run the CLI in a subprocess, as a user would; returns CompletedProcess."""
    return subprocess.run(
        [sys.executable, "-m", "mirage_cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
    )


@pytest.fixture
def mirage():
    return run_mirage


def assert_one_line_error(proc, code=2, contains=None):
    assert proc.returncode == code, (proc.returncode, proc.stderr)
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("mirage: error: "), lines[0]
    assert "Traceback" not in proc.stderr
    if contains:
        assert contains.lower() in lines[0].lower(), lines[0]


@pytest.fixture(scope="session")
def sample_model(tmp_path_factory):
    """The sample landmark model, built once per test session with the CLI."""
    path = tmp_path_factory.mktemp("model") / "landmark.mirage"
    p = run_mirage(
        "-q",
        "build-model",
        SAMPLE / "keyframes",
        "--camera",
        SAMPLE / "camera_truth.yaml",
        "--poses",
        SAMPLE / "keyframes" / "poses.csv",
        "-o",
        path,
    )
    assert p.returncode == 0, p.stderr
    return path
