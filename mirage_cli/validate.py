"""Checks of numbers from users, without click: frame positions, finite numbers, frame
ranges and input tables.

Python's float() accepts 'nan', 'inf' and 'infs'-like spellings, and NaN compares False
with every bound (a NaN threshold silently disables a filter or loses every frame): the
command line's option types (cli/options.py) and the campaign file refuse them; every pose
table read from a file goes through `pose_table`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError, OptionError

if TYPE_CHECKING:  # pandas loads when a table is read, not with `mirage track`
    import pandas as pd

QUAT_TOL = 0.01  # |norm - 1| up to this is rounding in a hand-written file: normalised


@dataclass(frozen=True)
class When:
    """A position in a video: a frame number, or seconds (needs the frame rate)."""

    value: float
    seconds: bool

    def frame(self, fps: float) -> int:
        return int(round(self.value * (fps or 30.0))) if self.seconds else int(self.value)

    def __str__(self) -> str:
        return f"{self.value:g}s" if self.seconds else str(int(self.value))


_WHEN = re.compile(r"\s*(\d+)\s*|\s*(\d+(?:\.\d*)?|\.\d+)\s*s\s*", re.IGNORECASE)


def parse_when(value) -> When:
    """'120' (frame number) or '4s' / '2.5s' (seconds); never negative, NaN or infinite.
    Raises ValueError with the message for the user."""
    if isinstance(value, When):
        return value
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise ValueError(f"{value!r}: use a frame number (120) or seconds (4s)")
    if isinstance(value, int | float):
        value = (
            str(value) if not (isinstance(value, float) and value.is_integer()) else str(int(value))
        )
    m = _WHEN.fullmatch(value)
    if not m:
        raise ValueError(f"{value!r}: use a frame number (120) or seconds (4s)")
    if m.group(1) is not None:
        return When(float(int(m.group(1))), False)
    return When(float(m.group(2)), True)


def finite_float(value, min: float | None = None, min_open: bool = False) -> float:
    """A finite number from a file (a campaign YAML), at least (above) `min`; raises
    ValueError with the message the command line's FiniteFloat option gives."""
    if isinstance(value, bool) or isinstance(value, list | dict | tuple):
        raise ValueError(f"{value!r} is not a number")
    try:
        rv = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{value!r} is not a valid float.") from None
    if not math.isfinite(rv):
        raise ValueError(f"{value!r} is not a finite number")
    if min is not None and (rv <= min if min_open else rv < min):
        raise ValueError(f"{rv} is not in the range x{'>' if min_open else '>='}{min}.")
    return rv


def frame_range(start: When | None, end: When | None, fps: float) -> tuple[int, int | None]:
    """First frame and the frame to stop before; an empty range is a usage error."""
    first = start.frame(fps) if start is not None else 0
    last = end.frame(fps) if end is not None else None
    if last is not None and last <= first:
        raise OptionError(
            f"--end {end} (frame {last}) must come after --start {start or 0} (frame {first})",
            "--end",
        )
    return first, last


# --------------------------------------------------------------------------------------
# tables
# --------------------------------------------------------------------------------------
def _where(path, df: pd.DataFrame, i: int, col: str | None = None) -> str:
    frame = df["frame"].iloc[i] if "frame" in df.columns else "?"
    c = f"column '{col}' " if col else ""
    return f"pose file {path}: {c}row {i + 2} (frame {str(frame).strip()})"


def unique_frames(df: pd.DataFrame, path, keys: pd.Series | None = None) -> None:
    """A frame listed twice would be used at one of two poses or counted twice: refuse."""
    if keys is None:  # '7' and '7.0' are the same video frame
        import pandas as pd

        text = df["frame"].astype(str).str.strip()
        num = pd.to_numeric(text, errors="coerce")
        integral = (num.notna() & (num == np.round(num))).to_numpy()
        keys = text.copy()
        keys[integral] = num[integral].astype("int64").astype(str)
    k = keys.reset_index(drop=True)
    dup = k.duplicated(keep="first").to_numpy()
    if dup.any():
        i = int(np.flatnonzero(dup)[0])
        first = int(np.flatnonzero((k == k.iloc[i]).to_numpy())[0])
        raise InputError(
            f"{_where(path, df, i)} repeats the frame of row {first + 2}; "
            "each frame may appear once"
        )


def finite_columns(df: pd.DataFrame, path, columns) -> None:
    """Numeric pose columns hold finite numbers (NaN only where a cell was empty)."""
    for col in columns:
        if col not in df.columns:
            continue
        v = df[col].to_numpy(dtype=float)
        bad = np.isinf(v)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"{_where(path, df, i, col)} is {v[i]}, expected a finite number")


def unit_quaternions(df: pd.DataFrame, path, ok: np.ndarray, tol: float = QUAT_TOL) -> None:
    """Normalise quaternions of `ok` rows in place when |norm - 1| <= tol; refuse beyond,
    since a far-off norm means a wrong column order or a unit mix-up, not rounding."""
    cols = ["qw", "qx", "qy", "qz"]
    q = df.loc[ok, cols].to_numpy(dtype=float)
    if not len(q):
        return
    n = np.linalg.norm(q, axis=1)
    bad = ~(np.abs(n - 1.0) <= tol)
    if bad.any():
        i = int(np.flatnonzero(ok)[np.argmax(bad)])
        norm = n[np.argmax(bad)]
        what = "a zero quaternion" if norm < 1e-6 else f"a quaternion of norm {norm:.4g}"
        raise InputError(
            f"{_where(path, df, i, 'qw..qz')} has {what}; expected a unit quaternion "
            f"(norm 1 +- {tol:g})"
        )
    df.loc[ok, cols] = q / n[:, None]


def pose_table(df: pd.DataFrame, path, require_pose: bool = True) -> None:
    """Checks of a parsed pose table (columns already numeric): finite values, one row per
    frame and unit quaternions. Raises InputError naming the file, row and column."""
    ok = (df["status"] == "ok").to_numpy()
    finite_columns(df, path, ["time_s", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"])
    unique_frames(df, path)
    if require_pose:
        unit_quaternions(df, path, ok)


def unit_quaternion_rows(q: np.ndarray, path, what: str, tol: float = QUAT_TOL) -> np.ndarray:
    """Rows (w, x, y, z) of a headerless file (TUM) normalised; a norm off 1 by more than
    `tol` is refused naming the data row (a zero quaternion would divide by zero)."""
    n = np.linalg.norm(q, axis=1)
    bad = ~(np.abs(n - 1.0) <= tol)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(
            f"{what} file {path}: data row {i + 1} has a quaternion of norm {n[i]:.4g}; "
            f"expected a unit quaternion (norm 1 +- {tol:g})"
        )
    return q / n[:, None]


def rotation_rows(R: np.ndarray, path, what: str, tol: float = 1e-3) -> None:
    """(N,3,3) rotation matrices: orthonormal with determinant +1 (scipy would silently
    turn any matrix into some rotation)."""
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = ~(err <= tol) | ~(np.linalg.det(R) > 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(
            f"{what} file {path}: data row {i + 1} is not a rotation (R^T R != I or det <= 0)"
        )


def unique_times(t: np.ndarray, path, what: str) -> None:
    """A timestamp listed twice makes matching by time ambiguous: refuse it."""
    _, first, counts = np.unique(t, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup = t[first[np.argmax(counts > 1)]]
        rows = np.flatnonzero(t == dup)[:2] + 1
        raise InputError(
            f"{what} file {path}: data rows {rows[0]} and {rows[1]} have the same "
            f"timestamp {dup:g}; each time may appear once"
        )
