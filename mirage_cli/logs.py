"""The `mirage` logger: warnings as one line `mirage: warning: ...` on stderr, and its
level (quiet: errors only; verbose: info). Core modules warn through `log`; the command
line's presentation (summaries, progress bars) is cli/ui.py."""

from __future__ import annotations

import logging
import sys

log = logging.getLogger("mirage")


class _Formatter(logging.Formatter):
    def format(self, record):
        if record.levelno >= logging.WARNING:
            return f"mirage: {record.levelname.lower()}: {record.getMessage()}"
        return record.getMessage()


def setup(verbose: int = 0, quiet: bool = False) -> None:
    """The logger's handler and level; OpenCV's own console warnings only with -vv."""
    log.handlers.clear()
    h = logging.StreamHandler(sys.stderr)
    h.setFormatter(_Formatter())
    log.addHandler(h)
    log.propagate = False
    log.setLevel(logging.ERROR if quiet else logging.DEBUG if verbose else logging.WARNING)
    try:
        import cv2

        cv2.utils.logging.setLogLevel(
            cv2.utils.logging.LOG_LEVEL_INFO if verbose >= 2 else cv2.utils.logging.LOG_LEVEL_ERROR
        )
    except (ImportError, AttributeError):
        pass
