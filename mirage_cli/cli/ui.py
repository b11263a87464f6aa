"""Terminal output for people: warnings, summaries and progress bars (silent when quiet)."""

from __future__ import annotations

import contextlib
import sys

import click

from .. import logs
from ..errors import EnvironmentFailure
from ..logs import log

_state = {"quiet": False, "verbose": 0}


def setup(verbose: int = 0, quiet: bool = False) -> None:
    _state.update(quiet=quiet, verbose=verbose)
    logs.setup(verbose, quiet)


def detail(msg: str, level: int = 1) -> None:
    """A line for -v (level 1: stages, timings, refusals) or -vv (level 2: every frame),
    on stderr so that it never mixes with data written to standard output."""
    if _state["verbose"] >= level and not _state["quiet"]:
        log.info(msg)


def verbose(level: int = 1) -> bool:
    return _state["verbose"] >= level and not _state["quiet"]


@contextlib.contextmanager
def stage(name: str):
    """Time a stage of a command; -v prints 'stage NAME: 1.23 s'."""
    import time

    t0 = time.perf_counter()
    yield
    detail(f"stage {name}: {time.perf_counter() - t0:.2f} s")


def echo(msg: str = "") -> None:
    """A line of the human-readable summary (stdout; suppressed by --quiet)."""
    if not _state["quiet"]:
        try:
            click.echo(msg)
        except OSError as e:  # a closed pipe, /dev/full: the machine's failure, exit 1
            import os

            with contextlib.suppress(OSError):  # so the exit's own flush stays quiet
                null = os.open(os.devnull, os.O_WRONLY)
                os.dup2(null, 1)
                os.close(null)
            raise EnvironmentFailure(
                f"cannot write to standard output: {e.strerror or e}"
            ) from None


def progress_enabled() -> bool:
    try:
        return not _state["quiet"] and sys.stdout.isatty()
    except (AttributeError, ValueError, OSError):  # closed or replaced stdout
        return False


@contextlib.contextmanager
def progress(length: int | None, label: str):
    """A click progress bar when stdout is a terminal, else a no-op with the same API."""
    if progress_enabled():
        with click.progressbar(
            length=length,
            label=label,
            show_pos=True,
            show_eta=True,
            item_show_func=lambda item: item,  # callers may pass e.g. "42 fps"
        ) as bar:
            yield bar
    else:

        class _Null:
            def update(self, n, current_item=None):
                pass

        yield _Null()
