"""Atomic file output: a failed or interrupted run never leaves a half-written file."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import yaml

from .errors import InputError, OutputError


def check_writable(path: str | os.PathLike) -> Path:
    """Fail early, before hours of work, if `path` cannot be created."""
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise OutputError(f"output path {p} is a directory; give a file name")
    if not parent.is_dir():
        raise OutputError(f"cannot write {p}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise OutputError(f"cannot write {p}: folder {parent} is not writable")
    return p


def ensure_dir(path: str | os.PathLike) -> Path:
    """Create an output folder, or fail with one clear line."""
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create folder {p}: {e.strerror or e}") from None
    if not os.access(p, os.W_OK):
        raise OutputError(f"cannot write into folder {p}: permission denied")
    return p


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path next to `path`; rename it over `path` only on success.

    Writers that need a file name (cv2.FileStorage, cv2.imwrite, np.savez) write to the
    yielded path; the extension is kept so such writers pick the right format.
    """
    p = check_writable(path)
    suffix = p.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=f".tmp{suffix}", dir=p.parent or ".")
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; finished files get the usual mode
    try:
        yield Path(tmp)
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **kw):
    """Open a temporary file for writing; it replaces `path` only when the block succeeds."""
    with atomic_path(path) as tmp, open(tmp, mode, **kw) as f:
        yield f
        f.flush()
        os.fsync(f.fileno())


def require_file(path: str | os.PathLike, what: str = "file") -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError(f"{what} {p} not found")
    if p.is_dir():
        raise InputError(f"{what} {p} is a folder, expected a file")
    if not os.access(p, os.R_OK):
        raise InputError(f"{what} {p} is not readable (permission denied)")
    return p


def read_yaml(path: Path, what: str):
    """Parsed YAML of a user's file; bad syntax or a binary file is one clear line."""
    try:
        return yaml.safe_load(Path(path).read_text())
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise InputError(f"{what} {path} is not valid YAML{where}") from None
    except UnicodeDecodeError:
        raise InputError(f"{what} {path} is not a text file") from None


def read_csv(path: Path, what: str, expected: str, **kw):
    """pandas.read_csv with the project's one-line errors (empty file, unreadable CSV) and
    stripped column names; `expected` says what the header should be."""
    import pandas as pd

    try:
        df = pd.read_csv(path, skipinitialspace=True, **kw)
    except pd.errors.EmptyDataError:
        raise InputError(f"{what} {path} is empty (expected {expected})") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as e:
        raise InputError(f"{what} {path} is not a readable CSV: {str(e).strip()}") from None
    df.columns = [str(c).strip() for c in df.columns]
    return df
