"""Atomic file output: a failed or interrupted run never leaves a half-written file."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

from . import signals
from .errors import EnvironmentFailure, InputError, OutputError


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


# Every temporary file we create, until it is renamed into place or removed: the CLI's top
# level removes what is left on any exit path (an error, Ctrl-C, SIGTERM).
_TEMPS: set[Path] = set()


def register_temp(path: str | os.PathLike) -> Path:
    p = Path(path)
    _TEMPS.add(p)
    return p


def forget_temp(path: str | os.PathLike) -> None:
    _TEMPS.discard(Path(path))


def cleanup_temps() -> None:
    """Remove every temporary file still registered (idempotent)."""
    for p in list(_TEMPS):
        with contextlib.suppress(OSError):
            p.unlink()
        _TEMPS.discard(p)


def write_failure(path, e: OSError) -> EnvironmentFailure:
    """One line naming the file, for an OS error while writing it (full disk, I/O error)."""
    return EnvironmentFailure(f"cannot write {path}: {e.strerror or e}")


def mkstemp_near(p: Path, suffix: str) -> tuple[int, Path]:
    """A registered temporary file in the output's folder (so the rename is atomic)."""
    with signals.deferred():  # a signal between creating and registering would leak it
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=suffix, dir=p.parent or ".")
        except OSError as e:
            raise write_failure(p, e) from None
        register_temp(tmp)
    return fd, Path(tmp)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None, verify=None):
    """Yield a temporary path next to `path`; rename it over `path` only on success.

    Writers that need a file name (cv2.FileStorage, cv2.imwrite, np.savez) write to the
    yielded path; the extension is kept so such writers pick the right format. Before the
    rename the file must be non-empty and pass `verify(tmp)` (True when the content reads
    back): OpenCV's FileStorage and VideoWriter do not report write errors, so a full disk
    shows only here. Any OS error is one line naming the file; the temporary file is gone
    on every exit path.
    """
    p = check_writable(path)
    suffix = p.suffix if suffix is None else suffix
    fd, tmp = mkstemp_near(p, f".tmp{suffix}")
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; finished files get the usual mode
        yield tmp
        if os.path.getsize(tmp) == 0:
            raise EnvironmentFailure(f"cannot write {p}: nothing was written (disk full?)")
        if verify is not None:
            try:
                ok = verify(tmp)
            except Exception:  # noqa: BLE001 - any failure to read back is a bad file
                ok = False
            if not ok:
                raise EnvironmentFailure(
                    f"cannot write {p}: the written file does not read back (disk full?)"
                )
        _fsync(tmp)
        os.replace(tmp, p)
    except OSError as e:
        raise write_failure(p, e) from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
        forget_temp(tmp)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **kw):
    """Open a temporary file for writing; it replaces `path` only when the block succeeds."""
    with atomic_path(path) as tmp, open(tmp, mode, **kw) as f:
        yield f
        f.flush()


def video_frames_written(path: str | os.PathLike) -> int:
    """Frames a written video holds (0 when it does not open). cv2.VideoWriter reports no
    write error, so a video counts as written only when it reads back."""
    import cv2

    try:
        cap = cv2.VideoCapture(str(path))
    except cv2.error:
        return 0
    try:
        return max(0, int(cap.get(cv2.CAP_PROP_FRAME_COUNT))) if cap.isOpened() else 0
    finally:
        cap.release()


def copy_file(src: str | os.PathLike, dest: str | os.PathLike) -> None:
    """Copy atomically; a full disk is one line naming `dest`."""
    with atomic_path(dest) as tmp:
        shutil.copyfile(src, tmp)


def _paths(value) -> list[str]:
    if value is None or value == "":
        return []
    if isinstance(value, list | tuple):
        return [str(v) for v in value if v not in (None, "")]
    return [str(value)]


def _same_file(a: str, b: str) -> bool:
    try:
        if os.path.exists(a) and os.path.exists(b):
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.realpath(a) == os.path.realpath(b)


def refuse_overwrite(outputs: dict, inputs: dict) -> None:
    """An output that is an input (or another output) would destroy data: refuse it.

    `outputs` and `inputs` map an option name (e.g. '-o', '--poses') to a path, a list of
    paths or None. Compares by os.path.samefile where both exist (hard links, symlinks).
    """
    seen = [(name, p, "input") for name, v in inputs.items() for p in _paths(v)]
    for name, v in outputs.items():
        for o in _paths(v):
            for other, p, kind in seen:
                if _same_file(o, p):
                    what = "overwrite the input" if kind == "input" else "be written twice"
                    raise InputError(
                        f"{name} {o} is the same file as {other} {p}: it would {what}; "
                        "choose another output name"
                    )
            seen.append((name, o, "output"))


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
    import yaml  # here, not at the top: `mirage --version` must not pay for it

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
