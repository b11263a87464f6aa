"""The `mirage` command line: a thin layer over the core modules.

Every user-caused failure is a MirageError -> `mirage: error: ...`, exit 2. Anything
unexpected is one line and exit 1; `--debug` shows the traceback.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import importlib
import os
import sys
import threading
import traceback
from collections.abc import Mapping

from ..runtime import blas_in_calling_thread

blas_in_calling_thread()  # before numpy is imported (runtime.py says why)

import click  # noqa: E402

from .. import __version__, fileio, signals  # noqa: E402
from ..errors import EnvironmentFailure, MirageError  # noqa: E402
from . import ui  # noqa: E402
from .config import check_config, read_config  # noqa: E402

_debug = {"on": False}
GLOBAL = ("-v", "--verbose", "-q", "--quiet", "--debug", "--config", "-V", "--version")
# an OS error the user can fix (a path or a permission), as opposed to a failing machine
_USER_ERRNOS = {errno.EACCES, errno.EPERM, errno.ENOENT, errno.ENOTDIR, errno.EISDIR,
                errno.ELOOP, errno.ENAMETOOLONG}  # fmt: skip


# name -> (module, command object, the first paragraph of its help for `mirage --help`).
# A command's module (and with it OpenCV, numba, pandas, ...) is imported only when that
# command runs or shows its help, so `mirage --version` and `mirage --help` stay instant;
# tests/test_cli.py checks the summaries against the commands' own help.
COMMANDS = {
    "batch": (
        "batch",
        "batch_cmd",
        "Track and report every flight of a campaign YAML, in parallel; re-runs resume.",
    ),
    "build-model": (
        "build_model",
        "build_model_cmd",
        "Build a 360-degree landmark model from images (a folder or glob) or a video.",
    ),
    "calibrate": (
        "calibrate",
        "calibrate",
        "Calibrate the camera from chessboard or ChArUco images, a folder, a glob or a video.",
    ),
    "demo": (
        "demo",
        "demo_cmd",
        "Run calibrate -> build-model -> track -> report on the sample data.",
    ),
    "inspect": (
        "build_model",
        "inspect_cmd",
        "Print a landmark model's summary; optionally plot it from above.",
    ),
    "report": (
        "report",
        "report_cmd",
        "Path-following errors of a pose CSV against the desired path (and the truth).",
    ),
    "synth": (
        "synth",
        "synth_cmd",
        "Render a synthetic data set with exact ground truth into OUTDIR.",
    ),
    "track": (
        "track",
        "track_cmd",
        "Estimate the camera pose in every frame of VIDEO (a video file, or images).",
    ),
}


class _LazyCommands(Mapping):
    """The commands by name, each imported on first access (`cli.commands["track"]`)."""

    def __init__(self, table: dict[str, tuple[str, str, str]]):
        self._table = table
        self._loaded: dict[str, click.Command] = {}

    def __getitem__(self, name: str) -> click.Command:
        if name not in self._loaded:
            module, attr, _ = self._table[name]  # KeyError: no such command
            self._loaded[name] = getattr(importlib.import_module(f".{module}", __package__), attr)
        return self._loaded[name]

    def __iter__(self):
        return iter(self._table)

    def __len__(self) -> int:
        return len(self._table)


class _LazyGroup(click.Group):
    """A group whose `commands` import lazily and whose command list comes from the
    table's summaries (the same text click would derive from each command's help)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, commands=_LazyCommands(COMMANDS), **kwargs)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        names = self.list_commands(ctx)
        limit = formatter.width - 6 - max(len(n) for n in names)
        # a bare Command with the same help text: click's own shortening, any click version
        rows = [(n, click.Command(n, help=COMMANDS[n][2]).get_short_help_str(limit)) for n in names]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(
    cls=_LazyGroup,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
)
@click.version_option(__version__, "-V", "--version", prog_name="mirage")
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False),
    help="YAML config (default: ./mirage.yaml if present).",
)
@click.option("-v", "--verbose", count=True, help="More detail (repeat for more).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors; no progress bars or summaries.")
@click.option("--debug", is_flag=True, help="Show tracebacks of unexpected errors.")
@click.pass_context
def cli(ctx, config_path, verbose, quiet, debug):
    """mirage: camera pose around a known landmark, from one video.

    Typical project: calibrate -> build-model -> track -> report.
    Options can also come from ./mirage.yaml (section per command).
    """
    _debug["on"] = debug
    ui.setup(verbose, quiet)
    raw, src = read_config(config_path)
    # the config is an input of every command: no output may overwrite it
    fileio.GUARDED_INPUTS.clear()
    fileio.GUARDED_INPUTS["--config"] = str(src) if src is not None else None
    ctx.default_map = check_config(raw, cli.commands, src) if src is not None else {}
    ctx.obj = {"config": ctx.default_map, "config_path": src}


def main(argv: list[str] | None = None) -> None:
    """Run one command and exit with its code: 0 done, 2 a user error, 1 the machine failed
    (full disk, closed stdout) or a bug, 130/143 interrupted by SIGINT/SIGTERM.

    Whatever happens, stderr gets at most one line, and no temporary file is left behind.
    """
    signals.install()  # first: from here on a signal is an exception that cleans up
    try:
        argv = sys.argv[1:] if argv is None else list(argv)
        if "--debug" in argv:
            _debug["on"] = True
        _check_std_streams(quiet="-q" in argv or "--quiet" in argv)
        code = _invoke(argv)
        if code == 0:
            signals.check()  # a swallowed signal still ends the run as interrupted
    except BaseException as e:  # noqa: BLE001 - every outcome becomes one line and a code
        code = _report(e)
    try:
        with signals.deferred():
            fileio.cleanup_temps()
    except KeyboardInterrupt as e:
        code = _report(e)
    sys.exit(code)


EXIT_GRACE_S = 20.0


def end_within_grace(code) -> None:
    """The process is ending after an interrupt (`__main__.run`, never an in-process
    caller of `main`): it has kept what it could and said so, and must now end. Python's
    exit joins every thread a library started (a worker finishing its job, or one that
    never returns: a CI run once printed its interrupt line and hung), so past
    `EXIT_GRACE_S` the process ends with the interrupt's code, without waiting for them."""
    if code not in signals.EXIT_CODES.values():
        return

    def force() -> None:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)

    timer = threading.Timer(EXIT_GRACE_S, force)
    timer.daemon = True
    timer.start()


def exit_without_teardown(code) -> None:
    """End the process (`__main__.run`, never an in-process caller of `main`) as Python's
    exit would, less its last step. Python joins the threads, runs the atexit callbacks,
    then frees every module's objects one by one: after `mirage track` that last step
    (numba's and LLVM's tables, OpenCV, the model) took 0.3 s of a 1.5 s run to a first
    pose, for nothing the command needs done. The first two are done here as Python does
    them; the rest is the OS's. Commands close what they write (atomic writes, released
    video writers, Rerun flushed), so nothing waits on a destructor. Where this Python has
    no thread-shutdown hook, or under a profiler or debugger (`python -m cProfile -m
    mirage_cli` writes its results once the program returns), it returns, and the exit is
    Python's own."""
    shutdown = getattr(threading, "_shutdown", None)
    watched = sys.getprofile() is not None or sys.gettrace() is not None
    if not isinstance(code, int) or shutdown is None or watched:
        return
    try:
        shutdown()  # joins the worker threads (their executors' exit hooks first)
    except KeyboardInterrupt as e:  # a second signal while threads finish
        print(signals.message(e), file=sys.stderr)
        code = signals.exit_code(e)
    atexit._run_exitfuncs()  # (it reports a callback's error itself, and goes on)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):  # closed or gone: as Python's exit
            code = code or 1
    os._exit(code)


def _invoke(argv: list[str]) -> int:
    """click's main() without its Ctrl-C handling (it prints a blank line and forgets
    which signal it was) and without dropping exit codes (standalone_mode=False)."""
    try:
        with cli.make_context("mirage", argv) as ctx:
            cli.invoke(ctx)
    except click.exceptions.Exit as e:
        return e.exit_code
    return 0


def _interrupt_behind(e: BaseException) -> BaseException:
    """The interrupt an exception was raised while handling, if any: a library that turns
    whatever stopped its import into its own error (numba: 'numba._devicearray failed to
    import' when SIGINT lands in it) must not make a Ctrl-C an 'unexpected' error, exit 1."""
    seen, cause = set(), e
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return e


def _report(e: BaseException) -> int:
    """Print the one line for an exception that ended the run; return the exit code."""
    if not isinstance(e, KeyboardInterrupt | SystemExit):
        e = _interrupt_behind(e)
        try:  # a signal raised that never surfaced as itself (numba's C import code
            signals.check()  # reports it as ImportError with no chain): it ended the run
        except KeyboardInterrupt as intr:
            e = intr
    try:
        with signals.deferred():
            return _describe(e)
    except KeyboardInterrupt as again:  # a second signal while reporting the first
        return signals.exit_code(again)


def _say(line: str) -> None:
    with contextlib.suppress(OSError, ValueError, AttributeError):
        click.echo(line, err=True)


def _describe(e: BaseException) -> int:
    if isinstance(e, SystemExit):
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    if isinstance(e, MemoryError):
        _say(
            "mirage: error: out of memory (an input or option asks for more than this machine "
            "has: check image sizes and counts)"
        )
        return 1
    if isinstance(e, KeyboardInterrupt | click.exceptions.Abort):
        signals.seen()
        # a signal that cut a library's object in half (llvmlite while numba loads) makes
        # its finaliser fail at exit: "Exception ignored in ...", a second line; the one
        # line below says what happened
        sys.unraisablehook = lambda unraisable: None
        cause = e.__cause__ if isinstance(e, click.exceptions.Abort) else e
        _say(signals.message(cause or e))
        return signals.exit_code(cause or e)
    if isinstance(e, MirageError):
        if _debug["on"]:
            traceback.print_exc()
        _say(f"mirage: error: {e}")
        return e.exit_code
    if isinstance(e, click.exceptions.NoArgsIsHelpError):
        with contextlib.suppress(OSError):
            click.echo(e.ctx.get_help() if e.ctx else str(e))
        return 2
    if isinstance(e, click.UsageError):
        hint = (
            f" (see 'mirage {e.ctx.info_name} --help')"
            if e.ctx and e.ctx.parent
            else " (see 'mirage --help')"
        )
        name = getattr(e, "option_name", None)
        if isinstance(e, click.NoSuchOption) and e.ctx and e.ctx.parent and name in GLOBAL:
            hint = (
                f" ({name} is a global option: it goes before the command, "
                f"'mirage {name} {e.ctx.info_name} ...')"
            )
        _say(f"mirage: error: {e.format_message()}{hint}")
        return 2
    if isinstance(e, click.ClickException):
        _say(f"mirage: error: {e.format_message()}")
        return e.exit_code or 2
    if isinstance(e, OSError):  # the machine: I/O error, full disk, no permission
        if _debug["on"]:
            traceback.print_exc()
        if e.filename:  # writes are named by their writers; this is mostly a read
            _say(f"mirage: error: {e.filename}: {e.strerror or e}")
            return 2 if e.errno in _USER_ERRNOS else 1
        _stdout_gone()
        if e.errno in (errno.EPIPE, errno.ENOSPC, errno.EIO, errno.EBADF):
            _say(f"mirage: error: cannot write to standard output: {e.strerror or e}")
        else:
            _say(f"mirage: error: {e.strerror or e}")
        return 1
    if _debug["on"]:
        traceback.print_exc()
    msg = str(e).strip().splitlines()[-1] if str(e).strip() else ""
    _say(
        f"mirage: error: unexpected {type(e).__name__}: {msg} "
        f"(rerun with --debug for the traceback)"
    )
    return 1


def _check_std_streams(quiet: bool) -> None:
    """A closed stdout/stderr (`mirage ... >&-`): keep fds 1 and 2 taken (else the next
    file opened would become fd 1 and receive any library's console output), and fail
    at once unless -q says nothing is to be printed."""
    closed = []
    for fd, name in ((1, "stdout"), (2, "stderr")):
        try:
            os.fstat(fd)
        except OSError:
            closed.append(name)
            null = os.open(os.devnull, os.O_WRONLY)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
            setattr(sys, name, open(fd, "w", closefd=False))  # noqa: SIM115
    if "stdout" in closed and not quiet:
        raise EnvironmentFailure(
            "cannot write to standard output: it is closed (use -q to run without output)"
        )


def _stdout_gone() -> None:
    """After stdout failed (closed pipe, /dev/full), point it at /dev/null so that the
    interpreter's final flush does not print a second error."""
    with contextlib.suppress(OSError, ValueError):
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 1)
        os.close(null)
