"""Desired paths (brief, section 3) and per-frame path-following errors, vectorised.

Errors are measured in the horizontal plane first (the nearest path point is found in
x, y) so that cross-track and height error stay independent: a drone that flies too
high is not also reported as off to the side.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import InputError
from .fileio import read_csv, read_yaml, require_file

PATH_TYPES = ("circle", "polyline")


def wrap_deg(a) -> np.ndarray:
    """Angles wrapped to (-180, 180]."""
    a = np.asarray(a, dtype=float)
    w = np.mod(a + 180.0, 360.0) - 180.0
    return np.where(w == -180.0, 180.0, w)


@dataclass(frozen=True)
class PathErrors:
    """Per-frame errors against the desired path (NaN where the input position is NaN)."""

    path_s_m: np.ndarray  # arc length of the nearest path point
    nearest_m: np.ndarray  # (N, 3) nearest path point (z = desired height there)
    cross_track_m: np.ndarray  # horizontal, positive = left of the path direction
    height_error_m: np.ndarray  # z - desired z at the nearest point
    heading_error_deg: np.ndarray  # yaw - desired heading, in (-180, 180]
    along_track_m: np.ndarray | None  # timed paths: s(nearest) - s(where it should be)


@dataclass(frozen=True)
class CirclePath:
    """Horizontal circle; arc length runs from azimuth `start_deg` in the path direction."""

    center_m: tuple[float, float]
    radius_m: float
    height_m: float
    direction: str = "ccw"  # ccw | cw (seen from above, z up)
    look_at_m: tuple[float, float, float] | None = None  # None: heading along the tangent
    start_deg: float = 0.0

    timed = False

    @property
    def length_m(self) -> float:
        return 2 * np.pi * self.radius_m

    def errors(self, xyz, yaw_deg, time_s=None) -> PathErrors:
        P = np.asarray(xyz, dtype=float).reshape(-1, 3)
        sgn = 1.0 if self.direction == "ccw" else -1.0
        dx, dy = P[:, 0] - self.center_m[0], P[:, 1] - self.center_m[1]
        rho = np.hypot(dx, dy)
        theta = np.arctan2(dy, dx)  # the centre itself maps to theta 0: any point is nearest
        s = np.mod(sgn * (theta - np.radians(self.start_deg)), 2 * np.pi) * self.radius_m
        near = np.column_stack(
            [
                self.center_m[0] + self.radius_m * np.cos(theta),
                self.center_m[1] + self.radius_m * np.sin(theta),
                np.full(len(P), self.height_m),
            ]
        )
        near[np.isnan(rho)] = np.nan
        # ccw: the centre is on the left, so being outside (rho > R) is to the right
        cross = -sgn * (rho - self.radius_m)
        tangent = np.degrees(theta) + sgn * 90.0
        desired = _look_heading(P, self.look_at_m, tangent)
        return PathErrors(
            s, near, cross, P[:, 2] - self.height_m, _heading_err(yaw_deg, desired), None
        )

    def sample(self, n: int = 361) -> np.ndarray:
        """(n, 3) points along the path, for plots."""
        a = np.linspace(0, 2 * np.pi, n)
        return np.column_stack(
            [
                self.center_m[0] + self.radius_m * np.cos(a),
                self.center_m[1] + self.radius_m * np.sin(a),
                np.full(n, self.height_m),
            ]
        )


@dataclass(frozen=True)
class PolylinePath:
    """Waypoints joined by straight segments; optional `time_s` per waypoint makes it timed."""

    points_m: np.ndarray  # (K, 3)
    time_s: np.ndarray | None = None  # (K,), strictly increasing
    look_at_m: tuple[float, float, float] | None = None  # None: heading along the tangent

    @property
    def timed(self) -> bool:
        return self.time_s is not None

    @property
    def cum_s(self) -> np.ndarray:
        """Arc length (3D) at each waypoint."""
        seg = np.linalg.norm(np.diff(self.points_m, axis=0), axis=1)
        return np.r_[0.0, np.cumsum(seg)]

    @property
    def length_m(self) -> float:
        return float(self.cum_s[-1])

    def errors(self, xyz, yaw_deg, time_s=None, chunk: int = 4096) -> PathErrors:
        P = np.asarray(xyz, dtype=float).reshape(-1, 3)
        A, B = self.points_m[:-1], self.points_m[1:]
        d2 = (B - A)[:, :2]  # horizontal segment vectors
        L2 = np.einsum("ij,ij->i", d2, d2)
        usable = L2 > 1e-18  # vertical segments have no horizontal nearest point
        n = len(P)
        seg = np.zeros(n, dtype=int)
        u = np.zeros(n)
        seglen = np.linalg.norm(B - A, axis=1)
        start = self.cum_s[:-1]
        ties: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frame -> (segments, t)
        for lo in range(0, n, chunk):  # chunks bound the (frames x segments) memory
            Q = P[lo : lo + chunk, None, :2] - A[None, :, :2]
            t = np.clip(np.einsum("fsk,sk->fs", Q, d2) / np.where(usable, L2, 1.0), 0.0, 1.0)
            r = Q - t[..., None] * d2[None]
            dist = np.nan_to_num(np.einsum("fsk,fsk->fs", r, r), nan=np.inf)
            dist[:, ~usable] = np.inf
            k = np.argmin(dist, axis=1)
            seg[lo : lo + chunk] = k
            u[lo : lo + chunk] = t[np.arange(len(k)), k]
            # a path that passes the same place again (laps): equally near points of
            # several passes, which the arc length must choose between (below)
            dmin = np.sqrt(dist[np.arange(len(k)), k])
            same = dist <= ((dmin + SAME_PLACE_M) ** 2)[:, None]
            s_all = np.where(same, start[None] + t * seglen[None], np.nan)
            with np.errstate(invalid="ignore"):
                spread = np.nanmax(s_all, axis=1) - np.nanmin(s_all, axis=1)
            for f in np.flatnonzero(np.isfinite(dmin) & (spread > SAME_PLACE_M)):
                cols = np.flatnonzero(same[f])
                ties[lo + int(f)] = (cols, t[f, cols])
        if ties:
            seg, u = self._pass_of_each_tie(ties, seg, u, seglen, time_s)
        near = A[seg] + u[:, None] * (B - A)[seg]
        s = self.cum_s[seg] + u * np.linalg.norm((B - A)[seg], axis=1)
        dirs = d2[seg] / np.sqrt(np.where(usable[seg], L2[seg], 1.0))[:, None]
        v = P[:, :2] - near[:, :2]
        # distance to the path, signed by side (> 0: left); at a vertex or past an end the
        # offset is not perpendicular to the segment, and the distance is still what counts
        side = dirs[:, 0] * v[:, 1] - dirs[:, 1] * v[:, 0]
        cross = np.where(side < 0, -1.0, 1.0) * np.hypot(v[:, 0], v[:, 1])
        tangent = np.degrees(np.arctan2(dirs[:, 1], dirs[:, 0]))
        desired = _look_heading(P, self.look_at_m, tangent)
        bad = np.isnan(P).any(axis=1)
        for a in (s, cross, tangent):
            a[bad] = np.nan
        near[bad] = np.nan
        along = None
        if self.timed:
            t = np.full(n, np.nan) if time_s is None else np.asarray(time_s, float)
            expected = np.interp(t, self.time_s, self.cum_s)  # holds at the ends
            along = s - np.where(np.isnan(t), np.nan, expected)
        return PathErrors(
            s, near, cross, P[:, 2] - near[:, 2], _heading_err(yaw_deg, desired), along
        )

    def _pass_of_each_tie(self, ties, seg, u, seglen, time_s):
        """Frames equally near several passes of the path (a path of two laps): the pass
        whose arc length the timing expects (timed paths), else the one nearest the
        previous frame's (so the along-path distance does not jump by a lap)."""
        start = self.cum_s[:-1]
        expected = None
        if self.timed and time_s is not None:
            expected = np.interp(np.asarray(time_s, float), self.time_s, self.cum_s)
        seg, u = seg.copy(), u.copy()
        prev = None
        for i in range(len(seg)):
            if i in ties:
                cols, t = ties[i]
                cand = start[cols] + t * seglen[cols]
                ref = expected[i] if expected is not None and np.isfinite(expected[i]) else prev
                j = int(np.argmin(np.abs(cand - ref))) if ref is not None else int(np.argmin(cand))
                seg[i], u[i] = cols[j], t[j]
            s_i = start[seg[i]] + u[i] * seglen[seg[i]]
            if np.isfinite(s_i):
                prev = s_i
        return seg, u

    def sample(self, n: int = 0) -> np.ndarray:
        return self.points_m


DesiredPath = CirclePath | PolylinePath


def _look_heading(P: np.ndarray, look_at, tangent_deg: np.ndarray) -> np.ndarray:
    """Desired heading: toward `look_at` from where the camera actually is (so heading
    error measures pointing, not cross-track error again), or the path tangent."""
    if look_at is None:
        return tangent_deg
    return np.degrees(np.arctan2(look_at[1] - P[:, 1], look_at[0] - P[:, 0]))


def _heading_err(yaw_deg, desired_deg) -> np.ndarray:
    return wrap_deg(np.asarray(yaw_deg, dtype=float) - desired_deg)


# --------------------------------------------------------------------------------------
# reading path files
# --------------------------------------------------------------------------------------
def load_path(path) -> DesiredPath:
    """A desired path from YAML (circle or polyline) or a waypoint CSV."""
    p = require_file(path, "path file")
    if p.suffix.lower() == ".csv":
        return _polyline_csv(p)
    data = read_yaml(p, "path file")
    if not isinstance(data, dict):
        raise InputError(f"path file {p} must be a YAML mapping with 'type: circle|polyline'")
    return path_from_dict(data, str(p))


PATH_KEYS = ("type", "center_m", "radius_m", "height_m", "direction", "look_at_m", "heading",
             "start_deg", "points_m", "waypoints_m", "time_s")  # fmt: skip
SAME_PLACE_M = 1e-6  # m: passes of a path this close are one place (laps over each other)
MAX_M = 1.0e7  # m: any coordinate or radius beyond is a unit mix-up (the Earth is 6.4e6 m)


def path_from_dict(data: dict, where: str = "path") -> DesiredPath:
    import difflib

    for k in data:
        if str(k) not in PATH_KEYS:
            close = difflib.get_close_matches(str(k), PATH_KEYS, n=1, cutoff=0.6)
            hint = f"did you mean '{close[0]}'?" if close else f"valid keys: {', '.join(PATH_KEYS)}"
            raise InputError(f"{where}: unknown key '{k}' ({hint})")
    kind = str(data.get("type", "")).strip().lower()
    if kind not in PATH_TYPES:
        got = data.get("type")
        raise InputError(
            f"{where}: unknown path type {got!r} (use 'type: circle' or 'type: polyline')"
        )
    look = _heading(data, where)
    if kind == "circle":
        center = _vec(data.get("center_m", [0.0, 0.0]), (2, 3), "center_m", where)[:2]
        radius = _num(data, "radius_m", where, required=True)
        if not radius > 0:
            raise InputError(f"{where}: radius_m must be > 0, got {radius:g}")
        direction = str(data.get("direction", "ccw")).strip().lower()
        if direction not in ("ccw", "cw"):
            raise InputError(f"{where}: direction must be ccw or cw, got {direction!r}")
        return CirclePath(
            tuple(center),
            radius,
            _num(data, "height_m", where, default=0.0),
            direction,
            look,
            _num(data, "start_deg", where, default=0.0),
        )
    pts = data.get("points_m", data.get("waypoints_m"))
    if not isinstance(pts, list):
        raise InputError(f"{where}: a polyline needs 'points_m: [[x, y, z], ...]'")
    rows = [_vec(q, (2, 3, 4), f"points_m[{i}]", where) for i, q in enumerate(pts)]
    if any(len(r) != len(rows[0]) for r in rows):
        raise InputError(f"{where}: every point of points_m needs the same number of values")
    arr = np.array(rows, dtype=float).reshape(len(rows), -1)
    if arr.shape[1] == 2:  # x, y: height 0
        arr = np.column_stack([arr, np.zeros(len(arr))])
    times = data.get("time_s")
    if times is not None:
        times = _vec(times, (len(arr),), "time_s", where)
    elif arr.shape[1] == 4:
        times = arr[:, 3]
    return _polyline(arr[:, :3], times, look, where)


def _polyline_csv(p: Path) -> PolylinePath:
    df = read_csv(p, "path file", "a header x_m,y_m,z_m[,time_s]")
    missing = [c for c in ("x_m", "y_m", "z_m") if c not in df.columns]
    if missing:
        raise InputError(f"path file {p}: missing waypoint column(s) {', '.join(missing)}")
    cols = ["x_m", "y_m", "z_m"] + (["time_s"] if "time_s" in df.columns else [])
    num = df[cols].apply(pd.to_numeric, errors="coerce")
    if num.isna().any().any():
        i, c = np.argwhere(num.isna().to_numpy())[0]
        raise InputError(f"path file {p}: column '{cols[c]}' row {i + 2} is not a number")
    arr = num.to_numpy(float)
    times = arr[:, 3] if arr.shape[1] == 4 else None
    return _polyline(arr[:, :3], times, None, str(p))


def _polyline(pts: np.ndarray, times, look, where: str) -> PolylinePath:
    if len(pts) < 2:
        raise InputError(f"{where}: a polyline needs at least 2 waypoints, got {len(pts)}")
    if not np.isfinite(pts).all():
        raise InputError(f"{where}: waypoints must be finite numbers")
    if (np.abs(pts) > MAX_M).any():
        raise InputError(f"{where}: waypoints beyond {MAX_M:g} m (metres expected)")
    seg = np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1)
    if not (seg > 0).any():
        raise InputError(f"{where}: all waypoints have the same x, y; the path has no direction")
    if times is not None:
        times = np.asarray(times, dtype=float)
        if not np.isfinite(times).all() or np.any(np.diff(times) <= 0):
            raise InputError(f"{where}: waypoint time_s must be finite and strictly increasing")
    return PolylinePath(pts, times, look)


def _heading(data: dict, where: str):
    if "look_at_m" in data and data["look_at_m"] is not None:
        v = _vec(data["look_at_m"], (2, 3), "look_at_m", where)
        return tuple(float(x) for x in np.r_[v, 0.0][:3])
    heading = str(data.get("heading", "tangent")).strip().lower()
    if heading != "tangent":
        raise InputError(f"{where}: heading must be 'tangent' (or give look_at_m: [x, y, z])")
    return None


def _num(data: dict, key: str, where: str, default=None, required=False) -> float:
    if key not in data or data[key] is None:
        if required:
            raise InputError(f"{where}: missing '{key}'")
        return float(default)
    try:
        v = float(data[key])
    except (TypeError, ValueError):
        raise InputError(f"{where}: {key} must be a number, got {data[key]!r}") from None
    if not np.isfinite(v):
        raise InputError(f"{where}: {key} must be finite")
    if key.endswith("_m") and abs(v) > MAX_M:
        raise InputError(f"{where}: {key} {v:g} is beyond {MAX_M:g} m (metres expected)")
    return v


def _vec(value, sizes: tuple[int, ...], key: str, where: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {key} must be a list of numbers, got {value!r}") from None
    if len(v) not in sizes or not np.isfinite(v).all():
        want = " or ".join(str(s) for s in sizes)
        raise InputError(f"{where}: {key} must be {want} finite numbers, got {value!r}")
    if key != "time_s" and (np.abs(v) > MAX_M).any():
        raise InputError(f"{where}: {key} {value!r} is beyond {MAX_M:g} m (metres expected)")
    return v
