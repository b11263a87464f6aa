"""SIGINT and SIGTERM as exceptions, so every `finally` and `with` cleans up.

Python turns SIGINT into KeyboardInterrupt but lets SIGTERM (timeout, kill, docker,
Slurm) end the process on the spot, leaving temporary files and a half-finished output.
`install()` makes SIGTERM raise `Terminated`, a KeyboardInterrupt, so the code that keeps
finished frames on Ctrl-C does the same on SIGTERM. This module imports nothing heavy: it
is installed before the rest of the program is imported.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}
_state = {"deferring": 0, "pending": None, "raised": None, "again": None}


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM."""

    signum = signal.SIGTERM


def _exception(signum: int) -> KeyboardInterrupt:
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _handler(signum, frame):
    if _state["deferring"]:
        _state["pending"] = _state["pending"] or signum
        return
    _state["raised"] = signum  # until `check` or the CLI's top level sees it
    if _in_import(frame):
        _again_soon(signum)
        return
    _state["again"] = None
    raise _exception(signum)


def _in_import(frame) -> bool:
    """The main thread is inside an import. One that C code started (a library's lazy
    import) hands our exception back to that C code, which may print its traceback and
    drop it (seen once in 50 interrupted start-ups: "Traceback ... _find_and_load ...
    KeyboardInterrupt" before the one line)."""
    for _ in range(64):
        if frame is None:
            return False
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _again_soon(signum: int) -> None:
    """The same signal again in 20 ms, raised then if the import is over (else again),
    unless it was raised meanwhile (`check`)."""
    _state["again"] = signum

    def again():
        if _state["again"] == signum:
            os.kill(os.getpid(), signum)

    t = threading.Timer(0.02, again)
    t.daemon = True
    t.start()


def check() -> None:
    """Raise a signal whose exception never surfaced: a compiled-code callback (numba's
    cache, llvmlite through ctypes) prints and drops an exception raised inside it, and
    the run would go on to finish and exit 0. Called where no interrupt can have been
    handled yet in this run (after the compiled code loads, before each frame), so a
    signal seen here was swallowed."""
    signum, _state["raised"] = _state["raised"], None
    if signum:
        _state["again"] = None
        raise _exception(signum)


def seen() -> None:
    """The interrupt reached the top level (or a caller that handles it): nothing pending."""
    _state["raised"] = _state["again"] = None


def _unraisable(unraisable) -> None:
    """Our interrupt raised inside a callback that cannot propagate it (a ctypes callback,
    a finaliser) is not printed as 'Exception ignored in ...': `check` raises it again
    where it can end the run. Anything else goes to Python's own hook."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        return
    sys.__unraisablehook__(unraisable)


def install() -> None:
    """Both signals raise; safe to call more than once (main thread only)."""
    _state.update(deferring=0, pending=None, raised=None)
    if sys.unraisablehook is sys.__unraisablehook__:
        sys.unraisablehook = _unraisable
    with contextlib.suppress(ValueError):  # not the main thread: leave the handlers alone
        signal.signal(signal.SIGINT, _handler)
        signal.signal(signal.SIGTERM, _handler)


def signal_of(exc: BaseException) -> int:
    return getattr(exc, "signum", signal.SIGINT)


def exit_code(exc: BaseException) -> int:
    return EXIT_CODES.get(signal_of(exc), 130)


def message(exc: BaseException) -> str:
    """'mirage: interrupted (SIGTERM); kept 42 frames in poses.csv'."""
    name = signal.Signals(signal_of(exc)).name
    note = getattr(exc, "mirage_note", None)
    return f"mirage: interrupted ({name})" + (f"; {note}" if note else "")


def note(exc: BaseException, text: str) -> None:
    """Say what the interrupted command kept (shown in the one interrupt line)."""
    with contextlib.suppress(AttributeError):
        exc.mirage_note = text


@contextlib.contextmanager
def deferred():
    """Hold SIGINT/SIGTERM while finishing outputs (rename into place, cleanup); a signal
    that came meanwhile is raised at the end, unless an exception already ends the run."""
    _state["deferring"] += 1
    try:
        yield
    except BaseException:
        _leave(raise_pending=False)
        raise
    _leave(raise_pending=True)


def _leave(raise_pending: bool) -> None:
    _state["deferring"] -= 1
    pending = _state["pending"]
    if pending and not _state["deferring"]:
        _state["pending"] = None
        if raise_pending:
            raise _exception(pending)


@contextlib.contextmanager
def through_compiled_code():
    """A signal that lands while numba-compiled code runs surfaces as SystemError ("returned
    a result with an exception set") caused by our KeyboardInterrupt, directly or through
    more such SystemErrors (a signal inside numba's unpickling of a constant chained four):
    re-raise the interrupt itself, so the code that keeps finished frames sees it."""
    try:
        yield
    except SystemError as e:
        seen, cause = set(), e.__context__
        while isinstance(cause, SystemError) and id(cause) not in seen:
            seen.add(id(cause))
            cause = cause.__context__
        if isinstance(cause, KeyboardInterrupt):
            raise cause from None
        raise


def worker_init() -> None:
    """For worker processes: the parent handles both signals and stops the pool."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
