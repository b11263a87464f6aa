import contextlib
import io
import os
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

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


@contextlib.contextmanager
def own_signal_handlers():
    """cli.main installs its SIGINT / SIGTERM handlers; give pytest its own back afterwards."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in saved.items():
            signal.signal(s, h)


@contextlib.contextmanager
def small_tmpfs(mnt: Path, size: str = "256k"):
    """A tiny tmpfs mounted at `mnt` (a full disk on demand); the test is skipped where
    mounting is not allowed (not root, no mount)."""
    import shutil

    mnt.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("a full disk needs root to mount a small tmpfs")
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)], capture_output=True
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


def run_here(*args, cwd=None):
    """The CLI in this process, as `run_mirage` runs it in a subprocess (same returncode,
    stdout, stderr) but without an interpreter start-up and imports per call."""
    from mirage_cli import cli

    out, err, old = io.StringIO(), io.StringIO(), os.getcwd()
    try:
        if cwd is not None:
            os.chdir(cwd)
        with (
            own_signal_handlers(),
            contextlib.redirect_stdout(out),
            contextlib.redirect_stderr(err),
            pytest.raises(SystemExit) as e,
        ):
            cli.main([str(a) for a in args])
    finally:
        os.chdir(old)
    return SimpleNamespace(returncode=e.value.code, stdout=out.getvalue(), stderr=err.getvalue())


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


@pytest.fixture(autouse=True)
def _terminal_state_per_test():
    """Each test starts with `ui` as a fresh process has it: a CLI run in this process with
    --quiet or -v (a test, or a module's fixture) would leave it so for the next test."""
    from mirage_cli import ui

    ui._state.update(quiet=False, verbose=0)
    yield
