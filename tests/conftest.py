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


def _checkout_state() -> dict:
    """Size and modification time of every file in the checkout outside build / cache
    folders: tests write only under tmp_path, never here."""
    skip = {".git", "build", ".venv", ".venv-ci", "__pycache__", ".pytest_cache", ".ruff_cache",
            ".hypothesis", "mutants"}  # fmt: skip
    rendered = ROOT / "benchmarks" / ".cache"  # benchmarks render here, gitignored
    out = {}
    for dirpath, dirnames, filenames in os.walk(ROOT):
        dirnames[:] = [
            d
            for d in dirnames
            if d not in skip and not d.endswith(".egg-info") and Path(dirpath, d) != rendered
        ]
        for f in filenames:
            st = os.stat(os.path.join(dirpath, f))
            out[os.path.join(dirpath, f)] = (st.st_size, st.st_mtime_ns)
    return out


@pytest.fixture(scope="session", autouse=True)
def _checkout_untouched():
    """The suite leaves the checkout as it found it (sample_data/ above all: a broken
    output guard once overwrote sample_data/orbit.mp4). Not in mutmut's copy (mutants/),
    which mutmut itself writes into while the tests run."""
    if ROOT.name == "mutants":
        yield
        return
    before = _checkout_state()
    yield
    after = _checkout_state()
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert not changed, f"tests wrote into the checkout: {changed[:10]}"


@pytest.fixture(autouse=True)
def _terminal_state_per_test():
    """Each test starts with `ui` as a fresh process has it: a CLI run in this process with
    --quiet or -v (a test, or a module's fixture) would leave it so for the next test."""
    from mirage_cli.cli import ui

    ui._state.update(quiet=False, verbose=0)
    yield


# --- skips: visible, and only the allowed ones -------------------------------------------
# `pytest -rs --skip-allowlist tests/skip_allowlist.txt` (what .ci/run runs) fails the run
# on any skip whose reason contains none of the file's lines: a skip hides a test, so each
# one there says why it may happen (see the file).
_SKIPPED: list[tuple[str, str]] = []


def pytest_addoption(parser):
    parser.addoption(
        "--skip-allowlist", metavar="FILE", default=None,
        help="fail the run on a skip whose reason contains no line of FILE",
    )  # fmt: skip


def _skip_reason(report) -> str:
    longrepr = report.longrepr
    if isinstance(longrepr, tuple) and len(longrepr) == 3:
        return str(longrepr[2]).removeprefix("Skipped: ")
    return str(longrepr)


def pytest_runtest_logreport(report):
    if report.skipped and not hasattr(report, "wasxfail"):
        _SKIPPED.append((report.nodeid, _skip_reason(report)))


def pytest_collectreport(report):
    if report.skipped:  # a whole module skipped
        _SKIPPED.append((report.nodeid, _skip_reason(report)))


def allowed_skips(path: Path) -> list[str]:
    lines = (ln.strip() for ln in path.read_text().splitlines())
    return [ln for ln in lines if ln and not ln.startswith("#")]


def pytest_sessionfinish(session, exitstatus):
    path = session.config.getoption("--skip-allowlist")
    if not path:
        return
    allowed = allowed_skips(Path(path))
    bad = [(n, r) for n, r in _SKIPPED if not any(a in r for a in allowed)]
    tr = session.config.pluginmanager.get_plugin("terminalreporter")
    if tr is not None:
        tr.write_line(f"skips: {len(_SKIPPED)}, of which not in {path}: {len(bad)}")
        for nodeid, reason in bad:
            tr.write_line(f"SKIP NOT ALLOWED {nodeid}: {reason}", red=True)
    if bad and session.exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
