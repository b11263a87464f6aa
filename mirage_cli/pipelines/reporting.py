"""What a pipeline tells a person while it runs, as an object the caller passes in.

The command line passes its `ui` module (summaries on stdout, -v details and progress bars);
`demo` the same; `batch` and the benchmarks the `SILENT` reporter. A pipeline's result is
returned, never printed: the command prints it."""

from __future__ import annotations

import contextlib
from typing import Protocol


class Reporter(Protocol):
    def echo(self, msg: str = "") -> None: ...  # a line for people (stdout)

    def detail(self, msg: str, level: int = 1) -> None: ...  # -v / -vv (stderr)

    def verbose(self, level: int = 1) -> bool: ...

    def stage(self, name: str) -> contextlib.AbstractContextManager: ...  # timed with -v

    def progress(self, length: int | None, label: str) -> contextlib.AbstractContextManager: ...


class _NullBar:
    def update(self, n, current_item=None) -> None:
        pass


class Silent:
    """Says nothing (batch flights, benchmarks, library use)."""

    def echo(self, msg: str = "") -> None:
        pass

    def detail(self, msg: str, level: int = 1) -> None:
        pass

    def verbose(self, level: int = 1) -> bool:
        return False

    def stage(self, name: str):
        return contextlib.nullcontext()

    def progress(self, length: int | None, label: str):
        return contextlib.nullcontext(_NullBar())


SILENT = Silent()
