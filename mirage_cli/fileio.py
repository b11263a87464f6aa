"""Atomic file output: a failed or interrupted run never leaves a half-written file."""

from __future__ import annotations

import contextlib
import fnmatch
import glob
import os
import shutil
import stat
import tempfile
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path

from . import signals
from .errors import EnvironmentFailure, InputError, OutputError


def is_special(path: str | os.PathLike) -> bool:
    """An existing output that is not a regular file or a folder: a character device
    (/dev/null), a FIFO, a socket, /dev/stdout (through its link). Written through,
    never replaced by a renamed temporary file."""
    st = _stat(os.fspath(path))
    return st is not None and not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode))


def output_target(path: str | os.PathLike) -> Path:
    """The file an output path writes: a symlink's target (so the link stays a link and
    the file it points to is replaced atomically), else the path itself. Special files
    keep the path given (/dev/stdout is a link into /proc)."""
    p = Path(path)
    if p.is_symlink() and not is_special(p):
        return Path(os.path.realpath(p))
    return p


def check_writable(path: str | os.PathLike) -> Path:
    """Fail early, before hours of work, if `path` cannot be created."""
    p = Path(path)
    if is_special(p):
        if not os.access(p, os.W_OK):
            raise OutputError(f"cannot write {p}: permission denied")
        return p
    p = output_target(p)
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
    """A registered temporary file in the output's folder (so the rename is atomic); for a
    special file (/dev/null, a FIFO) in the temporary folder, since it is copied through."""
    folder = tempfile.gettempdir() if is_special(p) else (p.parent or ".")
    with signals.deferred():  # a signal between creating and registering would leak it
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=suffix, dir=folder)
        except OSError as e:
            raise write_failure(p, e) from None
        register_temp(tmp)
    return fd, Path(tmp)


def write_through(tmp: Path, p: Path) -> None:
    """Copy a finished temporary file into a special file (device, FIFO, /dev/stdout)."""
    with open(tmp, "rb") as src, open(p, "wb") as dst:
        shutil.copyfileobj(src, dst)


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
    special = is_special(p)
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
        if special:
            write_through(tmp, p)
        else:
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
    if isinstance(value, list | tuple | set):
        return [s for v in value for s in _paths(v)]
    return [str(getattr(value, "path", value))]  # a BagRef names its bag


_GLOB_CHARS = "*?["


def _stat(p: str):
    try:
        return os.stat(p)
    except (OSError, ValueError):
        return None


@dataclass
class _Input:
    """What one input option names: a file or folder (its real path and inode), or a glob
    (its pattern and what it matches now)."""

    name: str  # the option, e.g. 'INPUT' or '--truth'
    given: str  # as the user wrote it
    real: str
    st: os.stat_result | None
    pattern: str | None = None  # an absolute glob pattern
    members: list = dataclass_field(default_factory=list)  # (real path, stat) it stands for

    @classmethod
    def of(cls, name: str, given: str) -> _Input:
        p = os.path.expanduser(given)
        st = _stat(p)
        inp = cls(name, given, os.path.realpath(p), st)
        if st is None and any(c in p for c in _GLOB_CHARS):
            inp.pattern = os.path.abspath(p)
            hits = glob.glob(p, recursive=True)
            inp.members = [(os.path.realpath(h), _stat(h)) for h in hits]
        elif st is not None and stat.S_ISDIR(st.st_mode):
            inp.members = [(inp.real, st)]
        return inp

    def folders(self) -> list[tuple[str, os.stat_result]]:
        """The folders this input names (a folder, a ROS 2 bag, a glob's folders)."""
        items = [(self.real, self.st)] if self.pattern is None else self.members
        return [(r, s) for r, s in items if s is not None and stat.S_ISDIR(s.st_mode)]

    def files(self) -> list[tuple[str, os.stat_result | None]]:
        """The files this input names, a folder's direct entries included (for inodes)."""
        items = [(self.real, self.st)] if self.pattern is None else self.members
        out = []
        for r, s in items:
            if s is not None and stat.S_ISDIR(s.st_mode):
                with contextlib.suppress(OSError), os.scandir(r) as it:
                    out += [(e.path, _stat(e.path)) for e in it]
            else:
                out.append((r, s))
        return out


class _Guard:
    """Everything the inputs name, indexed once (by real path and by inode), so that
    checking many outputs against many inputs (a campaign) stays cheap."""

    def __init__(self, inputs: list[_Input]):
        self.files: dict = {}  # real path or (dev, ino) -> input
        self.folders: dict = {}
        self.patterns = [i for i in inputs if i.pattern is not None]
        for inp in inputs:
            for r, s in inp.files():
                self.files.setdefault(r, inp)
                if s is not None:
                    self.files.setdefault((s.st_dev, s.st_ino), inp)
            for r, s in inp.folders():
                self.folders.setdefault(r, inp)
                self.folders.setdefault((s.st_dev, s.st_ino), inp)

    def clash(self, out: str) -> tuple[str, _Input] | None:
        """How writing `out` would touch an input (None: it would not)."""
        o = os.path.expanduser(out)
        real, st = os.path.realpath(o), _stat(o)
        hit = self.files.get(real) or (st and self.files.get((st.st_dev, st.st_ino)))
        if hit:
            return "is the same file as", hit
        parent = os.path.dirname(real)  # also a folder reached another way (bind mount)
        while parent and parent != os.path.dirname(parent):
            ps = _stat(parent)
            hit = self.folders.get(parent) or (ps and self.folders.get((ps.st_dev, ps.st_ino)))
            if hit:
                return "is inside", hit
            parent = os.path.dirname(parent)
        for inp in self.patterns:
            if fnmatch.fnmatch(os.path.abspath(o), inp.pattern) or fnmatch.fnmatch(
                real, inp.pattern
            ):
                return "matches", inp
        return None


# Inputs every command reads besides its own options (the config file), set by the CLI.
GUARDED_INPUTS: dict[str, str | None] = {}


def refuse_overwrite(outputs: dict, inputs: dict) -> None:
    """An output that is, or is inside, anything an input names, would destroy data: refuse.

    `outputs` and `inputs` map an option name (e.g. '-o', '--poses') to a path, a list of
    paths or None. An input may be a file, a folder (an output anywhere inside it is
    refused), a glob (an output it matches, or inside a folder it matches) or a bag.
    Compared by real path and by inode (symlinks, '..', hard links, bind mounts). Two
    outputs that are the same file are refused too, unless it is a device or a FIFO
    (`-o /dev/null --tum /dev/null` is fine).
    """
    named = {**{k: v for k, v in GUARDED_INPUTS.items() if v}, **inputs}
    guard = _Guard([_Input.of(name, p) for name, v in named.items() for p in _paths(v)])
    done: dict = {}  # real path or inode of an output -> (option, path)
    for name, v in outputs.items():
        for o in _paths(v):
            found = guard.clash(o)
            if found is not None:
                how, inp = found
                if how == "is the same file as":
                    raise InputError(
                        f"{name} {o} is the same file as {inp.name} {inp.given}: it would "
                        "overwrite the input; choose another output name"
                    )
                raise InputError(
                    f"{name} {o} {how} {inp.name} {inp.given}: it would write among the "
                    "inputs; choose an output outside them"
                )
            real, st = os.path.realpath(os.path.expanduser(o)), _stat(os.path.expanduser(o))
            keys = [real] + ([(st.st_dev, st.st_ino)] if st is not None else [])
            if not is_special(o):
                for k in keys:
                    if k in done:
                        other, p = done[k]
                        raise InputError(
                            f"{name} {o} is the same file as {other} {p}: it would be "
                            "written twice; choose another output name"
                        )
            for k in keys:
                done.setdefault(k, (name, o))


def require_file(path: str | os.PathLike, what: str = "file") -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError(f"{what} {p} not found")
    if p.is_dir():
        raise InputError(f"{what} {p} is a folder, expected a file")
    if not os.access(p, os.R_OK):
        raise InputError(f"{what} {p} is not readable (permission denied)")
    return p


class _DuplicateKey(Exception):
    def __init__(self, key, first: int, again: int):
        super().__init__(key)
        self.key, self.first, self.again = key, first, again


_LOADER: list = []


def _unique_keys_loader():
    """yaml.SafeLoader that refuses a key given twice in one mapping (plain YAML keeps the
    last silently: a config's first `track:` section would vanish)."""
    if _LOADER:
        return _LOADER[0]
    import yaml

    class UniqueKeys(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            seen: dict = {}
            for key_node, _ in node.value:
                if isinstance(key_node, yaml.ScalarNode):
                    key = key_node.value
                    line = key_node.start_mark.line + 1
                    if key in seen and key != "<<":
                        raise _DuplicateKey(key, seen[key], line)
                    seen[key] = line
            return super().construct_mapping(node, deep)

    _LOADER.append(UniqueKeys)
    return UniqueKeys


def read_yaml(path: Path, what: str):
    """Parsed YAML of a user's file; bad syntax or a binary file is one clear line."""
    import yaml  # here, not at the top: `mirage --version` must not pay for it

    try:
        return yaml.load(Path(path).read_text(), Loader=_unique_keys_loader())  # noqa: S506
    except _DuplicateKey as e:
        raise InputError(
            f"{what} {path}: '{e.key}' appears twice (line {e.first} and line {e.again}); "
            "YAML keeps only the last, so merge them into one"
        ) from None
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
