"""Fixed-lag smoothing of the tracked poses (`mirage track --smooth N`). Pure core.

A far camera sees one face of a small landmark: each frame's pose is honest but vague in
the direction where a sideways shift trades against a turn. The frames around it pin
that direction, because a camera on a drone or robot cannot jump between frames. Each
output frame is the maximum a-posteriori pose of a window of N frames before and after
it: every measured pose (ok or uncertain, with its 6x6 covariance) against a
constant-velocity prior (white-noise acceleration, second differences of rotation and
centre). An offline tool may look ahead; a record is yielded N frames late and never
changed afterwards, as `track.run` promises.

What keeps it honest:
- Flowed frames reuse the points of the detection they follow (their anchor), so their
  errors are correlated: the k frames of one anchor in the window count as one
  measurement (each covariance times k). Detections in a row are not independent either:
  they see the same few features of a far landmark from nearly the same place. On the
  far tuning scenes the mean of a window's detections varied 3x as much as independent
  errors would (whitened errors of consecutive detections correlate 0.25, still 0.11 ten
  apart: tools/detection_correlation.py), so every pose counts as at most 1/`min_run` of
  a measurement.
- The model's own error is shared by every frame that sees the same points; it is not
  averaged down but added back to the smoothed covariance. So is a share (`correlated`)
  of each frame's own covariance: detections in a row see the same features from nearly
  the same place and err alike (far frames smoothed as independent came out up to 3.6
  sigma off together).
- A pose that does not fit the others (Mahalanobis distance beyond `outlier_chi2`) is
  dropped from the window; if it is the output frame's own, that frame keeps its tracked
  values (a manoeuvre the prior does not expect, or a wrong pose the tracker's gate let
  through: the smoother does not decide which).
- More than `max_gap` frames without a pose split the trajectory: nothing is smoothed
  across a look-away or a lost stretch, and a frame with fewer than `min_side` poses
  before or after it in its stretch (its start and end) stays as tracked: there the
  prior extrapolates, and correlated errors of the first poses after a re-acquisition
  would swing it.
The smoothed pose is then gated like a tracked one (the measurement's own limits).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..pose import Pose, rodrigues_many, rotvecs
from ..records import FrameRecord, Measurement, Reason, Status
from ..solver import sigmas


@dataclass
class SmoothSettings:
    lag: int = 15  # frames before and after the output frame
    accel_m_s2: float = 3.5  # white-noise acceleration of the camera centre (1 sigma)
    ang_accel_deg_s2: float = 30.0  # ... and of its rotation: a far pose's error is mostly
    # a turn traded against a shift, which a camera that turns smoothly pins (far tuning
    # seeds 10-99: 60 -> 30 deg/s^2 with `correlated` 0.15, 16 -> 11 wrong poses, 58.0 ->
    # 59.4% of in-view frames ok); a faster turn fails `max_prior_excess` and stays as tracked
    max_gap: int = 3  # more frames in a row without a pose split the trajectory
    min_side: int = 3  # fewer poses than this before or after a frame: it stays as tracked
    outlier_chi2: float = 22.46  # chi-square, 6 dof, p = 0.999
    min_run: float = 3.0  # a pose counts as at most 1/min_run of a measurement: far
    # detections in a row err alike (see the module's docstring)
    correlated: float = 0.15  # share of a frame's own covariance its neighbours share,
    # not averaged down (random far scenes, tuning seeds: 0.1 ends 3.6-sigma runs; 0.15
    # with the tighter turn prior above)
    max_prior_excess: float = 25.0  # a window whose motion costs the prior more than this
    # per degree of freedom (5 sigma on average) is not what it describes: as tracked
    fps: float = 30.0  # frame rate when the records carry no times


def world_covariance(cov: np.ndarray, pose: Pose) -> np.ndarray:
    """The solver's (w, v) covariance (left perturbation of T_CW in the camera frame) as
    (theta, c) in W: R_WC' = exp(theta) R_WC and c' = c + dc, with theta = -R^T w and
    dc = -R^T v to first order."""
    B = np.zeros((6, 6))
    B[:3, :3] = B[3:, 3:] = -pose.R.T
    return B @ cov @ B.T


@dataclass
class WorldMeasurement:
    """A measurement prepared once: in W, with its information matrix."""

    R_wc: np.ndarray
    center: np.ndarray
    info: np.ndarray
    shared: np.ndarray  # the model's error in W: added back after smoothing
    own: np.ndarray  # this frame's own covariance in W (its correlated share is added back)
    anchor: int
    max_pos: float
    max_rot: float


def prepare(m: Measurement | None) -> WorldMeasurement | None:
    if m is None:
        return None
    C = world_covariance(m.cov, m.pose)
    if not np.all(np.isfinite(C)):
        return None
    try:
        info = np.linalg.inv(C + 1e-14 * np.eye(6))
    except np.linalg.LinAlgError:
        return None
    shared = world_covariance(m.cov_shared, m.pose)
    return WorldMeasurement(m.pose.R.T, m.pose.center, info, shared, C, m.anchor,
                            m.max_sigma_pos_m, m.max_sigma_rot_deg)  # fmt: skip


_A = np.hstack([np.eye(6), -2 * np.eye(6), np.eye(6)])  # second difference of 3 frames
GN_STEPS = 1  # corrections are millimetres and tenths of a degree: a second step moves
# the 4 m orbit's median error by 0.0003% of range and costs 1.2 ms a frame
_BAND = 17  # H couples frames two apart: 6 x 2 + 5 sub-diagonals


@lru_cache(maxsize=1)
def lapack_band_solvers():
    """LAPACK's banded Cholesky (dpbsv, dpbtrs), imported when first needed: importing
    scipy.linalg is 0.15 s of `mirage track`'s start, done on the warm-up thread
    (`pipelines.track.start_warm_up`) while the model loads."""
    from scipy.linalg import lapack

    return lapack.dpbsv, lapack.dpbtrs


@lru_cache(maxsize=64)  # one entry per window length (up to 2 lag + 1)
def _band_layout(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the lower triangle of H's blocks goes in LAPACK's lower band storage (row
    d, column i holds H[i + d, i]): the block (r + o, r) at blocks[r, o] (o = 0, 1, 2,
    frames apart), as flat (source, band row, band column) index arrays for n frames."""
    r, o, a, b = (x.ravel() for x in np.meshgrid(
        np.arange(n), np.arange(3), np.arange(6), np.arange(6), indexing="ij"))  # fmt: skip
    d = 6 * o + a - b
    keep = (r + o < n) & (d >= 0)
    src = np.ravel_multi_index((r, o, a, b), (n, 3, 6, 6))[keep]
    return src, d[keep], (6 * r + b)[keep]


def _residuals(Rm, cm, R, c) -> np.ndarray:
    """(theta, c) of measurements (R_wc, centre) against the window's poses R, c at their
    frames: (len(Rm), 6)."""
    dR = Rm @ R.transpose(0, 2, 1)
    return np.concatenate([rotvecs(dR), cm - c], axis=1)


def _fits_prior(R, c, prior, max_excess: float) -> bool:
    """Does the window move the way the constant-velocity prior describes? The smoothed
    trajectory's second differences, in the prior's Mahalanobis terms, averaged over their
    degrees of freedom: about 1 where the prior holds, a few where the camera turns faster
    than it expects (the rendered orbits' look-aways: up to 5, and smoothing still helps
    there), and hundreds for stills taken apart (dtu_scan37's robot positions, 11 deg
    apart: 63-280), which smoothing would pull toward a motion that did not happen (0.82
    -> 1.07 mm median error). Beyond `max_excess` the frame stays as tracked."""
    if len(R) < 3:
        return True
    inc = rotvecs(R[1:] @ R[:-1].transpose(0, 2, 1))
    a = np.concatenate([inc[1:] - inc[:-1], c[2:] - 2 * c[1:-1] + c[:-2]], axis=1)
    cost = float(np.einsum("ni,ij,nj->", a, prior, a))
    return cost <= max_excess * a.size


def _step(use, Rm, cm, W, R, c, prior, P):
    """Gauss-Newton step of the window (measurements at frames `use`, their information
    W): corrections (n, 6) and the Cholesky factor of the information H (None, None when
    H is not positive definite or not finite).

    H is assembled straight into LAPACK's band storage: each frame's block and its
    couplings to the next two frames, as far as the prior's second differences reach."""
    n = len(R)
    g2 = np.zeros((n, 6))
    z = _residuals(Rm, cm, R[use], c[use])
    blocks = np.zeros((n, 3, 6, 6))  # (frame r, o frames on): H's block (r + o, r)
    blocks[use, 0] += W
    g2[use] += np.einsum("nij,nj->ni", W, z)
    if n >= 3:
        inc = rotvecs(R[1:] @ R[:-1].transpose(0, 2, 1))  # (n-1, 3)
        a = np.concatenate([inc[1:] - inc[:-1], c[2:] - 2 * c[1:-1] + c[:-2]], axis=1)
        ga = (-(a @ prior) @ _A).reshape(-1, 3, 6)  # (n-2, 3 frames, 6)
        for u in range(3):
            g2[u : n - 2 + u] += ga[:, u]
        # each triple i, i+1, i+2 adds P[u, v] to the block (i + u, i + v); u >= v here
        for u, v in ((0, 0), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2)):
            blocks[v : n - 2 + v, u - v] += P[u, :, v, :]
    src, row, col = _band_layout(n)
    ab = np.zeros((_BAND + 1, 6 * n))
    ab[row, col] = blocks.ravel()[src]
    if not (np.all(np.isfinite(ab)) and np.all(np.isfinite(g2))):
        return None, None
    pbsv, _ = lapack_band_solvers()
    factor, d, err = pbsv(ab, g2.ravel(), lower=1)
    if err != 0:
        return None, None
    return d.reshape(n, 6), factor


def smooth_window(window: list[WorldMeasurement | None], k: int, dt: float, s: SmoothSettings):
    """MAP pose and 6x6 (theta, c) covariance in W of window[k], or None when it cannot be
    smoothed (its pose is an outlier, or the window has no other pose). `window` holds one
    entry per frame (None: no pose) and no gap longer than `s.max_gap`."""
    idx = [j for j, m in enumerate(window) if m is not None]
    if window[k] is None or len(idx) < 2:
        return None
    runs: dict[int, int] = {}
    for j in idx:
        runs[window[j].anchor] = runs.get(window[j].anchor, 0) + 1
    meas = [window[j] for j in idx]
    Rm = np.stack([m.R_wc for m in meas])
    cm = np.stack([m.center for m in meas])
    info_raw = np.stack([m.info for m in meas])
    count = np.array([max(runs[m.anchor], s.min_run) for m in meas], float)
    info = info_raw / count[:, None, None]
    # reference: the poses, frames without one interpolated between their neighbours
    n = len(window)
    R0 = np.zeros((n, 3, 3))
    c0 = np.zeros((n, 3))
    R0[idx] = Rm
    c0[idx] = cm
    for j in set(range(n)) - set(idx):  # the window starts and ends with a pose
        ia = int(np.searchsorted(idx, j))
        after, before = idx[ia], idx[ia - 1]
        f = (j - before) / (after - before)
        mb, ma = meas[ia - 1], meas[ia]
        R0[j] = rodrigues_many(f * rotvecs(ma.R_wc @ mb.R_wc.T)) @ mb.R_wc
        c0[j] = (1 - f) * mb.center + f * ma.center
    q_rot = np.radians(s.ang_accel_deg_s2) ** 2 * dt**3
    q_pos = s.accel_m_s2**2 * dt**3
    prior = np.diag([1 / q_rot] * 3 + [1 / q_pos] * 3)
    P = (_A.T @ prior @ _A).reshape(3, 6, 3, 6)
    kept = np.ones(len(idx), bool)  # measurements not dropped as outliers
    frames = np.array(idx)
    while True:  # drop outliers, the worst first, until every pose fits
        R, c = R0.copy(), c0.copy()
        use = frames[kept]
        for _it in range(GN_STEPS):
            d, factor = _step(use, Rm[kept], cm[kept], info[kept], R, c, prior, P)
            if d is None:
                return None
            R = rodrigues_many(d[:, :3]) @ R
            c = c + d[:, 3:]
        r = _residuals(Rm[kept], cm[kept], R[use], c[use])
        m2 = np.einsum("ni,nij,nj->n", r, info_raw[kept], r)
        worst = int(np.argmax(m2))
        if m2[worst] <= s.outlier_chi2:
            break
        if use[worst] == k or len(use) <= 2:
            return None
        kept[np.flatnonzero(kept)[worst]] = False
    if not _fits_prior(R, c, prior, s.max_prior_excess):
        return None
    E = np.zeros((6 * n, 6))
    E[6 * k : 6 * k + 6] = np.eye(6)
    _, pbtrs = lapack_band_solvers()
    cov, err = pbtrs(factor, E, lower=1)  # the step's factor: H did not change since
    if err != 0:
        return None
    cov = cov[6 * k : 6 * k + 6]
    R_cw = R[k].T
    return Pose(R_cw, -R_cw @ c[k]), (cov + cov.T) / 2


class Smoother:
    """Feed records in order with `push`; each comes back `s.lag` frames later, its pose
    smoothed; `flush` returns the frames still held (at the end, or on an interrupt: the
    frames the tracker finished are never lost)."""

    def __init__(self, s: SmoothSettings):
        self.settings = s
        self.held: deque[FrameRecord] = deque()  # lag past, the next output, lag future
        self.prepared: deque[WorldMeasurement | None] = deque()  # their measurements, in W
        self.out_at = 0  # index in `held` of the next frame to give back

    def push(self, rec: FrameRecord) -> list[FrameRecord]:
        m = prepare(rec.measurement)  # first: an interrupt here leaves both queues alike
        self.held.append(rec)
        self.prepared.append(m)
        return self._ready(self.settings.lag)

    def flush(self) -> list[FrameRecord]:
        # an interrupt between the two appends of `push` held a record without its
        # measurement ('deque index out of range' in the frames kept on Ctrl-C)
        while len(self.prepared) < len(self.held):
            self.prepared.append(prepare(self.held[len(self.prepared)].measurement))
        return self._ready(0)

    def _ready(self, future: int) -> list[FrameRecord]:
        """The held frames with `future` frames after them, smoothed. They count as given
        back only once all are computed: an interrupt meanwhile loses none (`flush`)."""
        n = max(len(self.held) - future - self.out_at, 0)
        done = [self._smoothed(k) for k in range(self.out_at, self.out_at + n)]
        self.out_at += n
        self._trim()
        return done

    def _trim(self) -> None:
        while self.out_at > self.settings.lag:
            self.held.popleft()
            self.prepared.popleft()
            self.out_at -= 1

    def _smoothed(self, k: int) -> FrameRecord:
        t0 = time.perf_counter()
        rec = self._smooth(k)
        rec.ms = round(rec.ms + (time.perf_counter() - t0) * 1000, 2)
        return rec

    def _smooth(self, k: int) -> FrameRecord:
        s, rec, m = self.settings, self.held[k], self.prepared[k]
        if m is None or s.lag <= 0:
            return rec
        # the window: the stretch around k without a gap longer than max_gap
        lo, hi, gap = k, k, 0
        for j in range(k - 1, max(k - s.lag, 0) - 1, -1):  # at most lag frames either way
            gap = 0 if self.prepared[j] is not None else gap + 1
            if gap > s.max_gap:
                break
            if gap == 0:
                lo = j
        gap = 0
        for j in range(k + 1, min(k + s.lag + 1, len(self.held))):
            gap = 0 if self.prepared[j] is not None else gap + 1
            if gap > s.max_gap:
                break
            if gap == 0:
                hi = j
        window = [self.prepared[j] for j in range(lo, hi + 1)]
        before = sum(w is not None for w in window[: k - lo])
        if min(before, sum(w is not None for w in window) - 1 - before) < s.min_side:
            return rec  # the end of a stretch: a smoother extrapolates there, keep it
        steps = np.diff([self.held[j].time_s for j in range(lo, hi + 1)])
        dt = float(np.median(steps)) if len(steps) and np.all(np.isfinite(steps)) else 0.0
        dt = dt if dt > 0 else 1.0 / s.fps
        # 4 digits: stamps that jitter by microseconds (bags) do not change the poses
        got = smooth_window(window, k - lo, float(f"{dt:.4g}"), s)
        if got is None:  # nothing to smooth with, or the frame does not fit its
            return rec  # neighbours (a manoeuvre the prior does not expect): as tracked
        pose, cov = got
        cov = cov + m.shared + s.correlated * m.own
        # with this frame's own evidence in it, the smoothed pose is not worse than the
        # tracked one; a larger sigma only comes from counting a flowed run as one
        # measurement, which is cautious
        pos, rot = sigmas(cov)
        rec.sigma_pos_m, rec.sigma_rot_deg = min(rec.sigma_pos_m, pos), min(rec.sigma_rot_deg, rot)
        if rec.sigma_pos_m <= m.max_pos and rec.sigma_rot_deg <= m.max_rot:
            rec.status, rec.pose, rec.reason = Status.OK, pose, ""
        else:
            rec.status, rec.pose, rec.reason = Status.UNCERTAIN, None, Reason.UNCERTAIN
        return rec


def smoothed(records: Iterable[FrameRecord], s: SmoothSettings) -> Iterator[FrameRecord]:
    """The records in order, each `s.lag` frames late with its pose smoothed (only frames
    with a pose, ok or uncertain, change)."""
    sm = Smoother(s)
    for rec in records:
        yield from sm.push(rec)
    yield from sm.flush()
