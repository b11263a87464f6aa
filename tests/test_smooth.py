"""The fixed-lag smoother against known truth: it must shrink the error where frames are
independent, stay honest where they are not, ignore a pose that does not fit, never smooth
across a gap, and give every frame back once, in order."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import scipy.linalg

from mirage_cli.pose import Pose, look_at, rodrigues, rodrigues_many, rotvec, rotvecs
from mirage_cli.records import FrameRecord, Measurement, Status
from mirage_cli.solver import sigmas
from mirage_cli.tracking.smooth import (
    _BAND,
    Smoother,
    SmoothSettings,
    _band_layout,
    smoothed,
    world_covariance,
)

FPS = 30.0
SIG_W, SIG_V = np.radians(0.3), 0.02  # per-frame 1-sigma: rotation (rad), translation (m)


def _orbit(n, radius=4.0, turns_per_s=0.15, start=0.0):
    """Camera poses on a circle looking at the origin, at constant speed."""
    out = []
    for i in range(n):
        a = start + 2 * np.pi * turns_per_s * i / FPS
        out.append(look_at([radius * np.cos(a), radius * np.sin(a), 0.6], [0, 0, 0.3]))
    return out


def _measure(truth, rng, anchors=None, scale=1.0, repeat_error=False, rho=0.0):
    """Records whose poses carry the noise their covariance states (left perturbation
    exp([w, v]) T_CW, as the solver's); `anchors[i]`: the detection frame i flows from;
    `rho`: each new error's correlation with the one before (AR(1), same variance)."""
    cov = np.diag([SIG_W**2] * 3 + [SIG_V**2] * 3) * scale**2
    recs, e = [], None
    for i, T in enumerate(truth):
        if e is None or not repeat_error or anchors[i] == i:
            new = rng.multivariate_normal(np.zeros(6), cov)
            e = new if e is None else rho * e + np.sqrt(1 - rho**2) * new
        R = cv2.Rodrigues(e[:3])[0]
        noisy = Pose(R @ T.R, R @ T.t + e[3:])
        m = Measurement(noisy, cov, np.zeros((6, 6)), anchors[i] if anchors else i)
        recs.append(
            FrameRecord(
                Status.OK, noisy, frame=i, time_s=i / FPS,
                sigma_pos_m=float(np.sqrt(3) * SIG_V * scale),
                sigma_rot_deg=float(np.degrees(np.sqrt(3) * SIG_W * scale)), measurement=m,
            )
        )  # fmt: skip
    return recs


def _errors(recs, truth):
    pe = np.array([r.pose.distance_to(t) for r, t in zip(recs, truth, strict=True)])
    re = np.array([r.pose.angle_to(t) for r, t in zip(recs, truth, strict=True)])
    return pe, re


def test_rotation_log_and_exp_invert_each_other_near_zero_and_pi():
    rng = np.random.default_rng(1)
    w = np.vstack([rng.normal(size=(20, 3)), [[1e-9, 0, 0], [np.pi - 1e-7, 0, 0], [0, 0, 0]]])
    R = np.array([cv2.Rodrigues(v)[0] for v in w])
    assert np.allclose(rodrigues_many(w), R, atol=1e-9)
    assert np.allclose(rodrigues_many(rotvecs(R)), R, atol=1e-7)
    # the stacks agree with the one-matrix versions
    assert np.allclose(rodrigues_many(w), [rodrigues(v) for v in w], atol=1e-12)
    assert np.allclose(rodrigues_many(rotvecs(R)), [rodrigues(rotvec(m)) for m in R], atol=1e-8)
    # the solver's camera-frame covariance in W keeps its traces (sigmas are unchanged)
    C = np.diag([1.0, 2, 3, 4, 5, 6])
    Cw = world_covariance(C, look_at([2, 1, 1], [0, 0, 0]))
    assert np.isclose(np.trace(Cw[:3, :3]), 6) and np.isclose(np.trace(Cw[3:, 3:]), 15)


def test_independent_frames_get_more_accurate_and_stay_honest():
    """Told that its frames err independently (`min_run=1`), the smoother averages them
    down by the full square root of the window."""
    truth = _orbit(150)
    recs = _measure(truth, np.random.default_rng(2))
    raw_pe, raw_re = _errors(recs, truth)
    out = list(smoothed(recs, SmoothSettings(min_run=1)))
    assert [r.frame for r in out] == list(range(150))
    assert all(r.status == Status.OK for r in out)
    pe, re = _errors(out, truth)
    assert np.median(pe) < 0.7 * np.median(raw_pe), (np.median(pe), np.median(raw_pe))
    assert np.median(re) < 0.7 * np.median(raw_re), (np.median(re), np.median(raw_re))
    sp = np.array([r.sigma_pos_m for r in out])
    sr = np.radians([r.sigma_rot_deg for r in out])
    honesty_pos = np.sqrt(np.mean(pe**2)) / np.sqrt(np.mean(sp**2))
    honesty_rot = np.sqrt(np.mean(np.radians(re) ** 2)) / np.sqrt(np.mean(sr**2))
    assert 0.6 < honesty_pos < 1.3 and 0.6 < honesty_rot < 1.3, (honesty_pos, honesty_rot)


def test_detections_that_err_alike_are_not_averaged_down_as_independent():
    """Every frame a detection, each error correlated 0.9 with the one before (far
    detections in a row see the same few features: their window means varied 3x as much
    as independent ones). Counted as independent, the smoothed sigma is too small; with
    each pose at most 1/min_run of a measurement it covers the error."""
    truth = _orbit(150)
    honesty = {}
    for min_run in (1, SmoothSettings.min_run):
        pe, sp = [], []
        for seed in range(8):
            recs = _measure(truth, np.random.default_rng(40 + seed), rho=0.9)
            out = list(smoothed(recs, SmoothSettings(min_run=min_run)))
            pe.append(_errors(out, truth)[0])
            sp.append([r.sigma_pos_m for r in out])
        pe, sp = np.concatenate(pe), np.concatenate(sp)
        honesty[min_run] = np.sqrt(np.mean(pe**2)) / np.sqrt(np.mean(sp**2))
    assert honesty[1] > 1.15, honesty
    assert 0.8 < honesty[SmoothSettings.min_run] < 1.15, honesty


def test_a_flowed_run_counts_as_one_measurement():
    """Five frames flowed from one detection repeat its error: smoothing them as five
    independent poses would claim sqrt(5) too small a sigma. Counted as one, the error
    stays within the stated sigma."""
    truth = _orbit(150)
    anchors = [i - i % 5 for i in range(150)]
    recs = _measure(truth, np.random.default_rng(3), anchors, repeat_error=True)
    out = list(smoothed(recs, SmoothSettings()))
    pe, _ = _errors(out, truth)
    sp = np.array([r.sigma_pos_m for r in out])
    assert np.sqrt(np.mean(pe**2)) / np.sqrt(np.mean(sp**2)) < 1.3


def test_a_pose_that_does_not_fit_neither_moves_its_neighbours_nor_is_changed():
    truth = _orbit(61)
    recs = _measure(truth, np.random.default_rng(4))
    bad = recs[30]
    wrong = Pose(bad.pose.R, bad.pose.t + np.array([0.8, 0.0, 0.0]))  # 0.8 m off
    bad.pose = wrong
    bad.measurement = Measurement(wrong, bad.measurement.cov, np.zeros((6, 6)), 30)
    out = list(smoothed(recs, SmoothSettings()))
    assert out[30].pose is wrong  # as tracked: the smoother does not decide it
    pe, _ = _errors(out[:30] + out[31:], truth[:30] + truth[31:])
    assert pe.max() < 0.05, pe.max()


def test_nothing_is_smoothed_across_a_gap():
    """Two stretches 10 frames apart (more than max_gap without a pose), the second one
    displaced by 1 m: each is smoothed on its own, nothing pulls across the gap."""
    s = SmoothSettings(max_gap=3)
    a, b = _orbit(20), _orbit(20, radius=5.0, start=1.0)
    rng = np.random.default_rng(5)
    recs = _measure(a + b, rng)
    for i, r in enumerate(recs[20:], start=20):
        r.frame, r.time_s = i + 10, (i + 10) / FPS
    gap = [FrameRecord(Status.LOST, frame=20 + j, time_s=(20 + j) / FPS) for j in range(10)]
    stream = recs[:20] + gap + recs[20:]
    alone = [r.pose for r in smoothed([_copy(r) for r in recs[:20]], s)]
    out = list(smoothed(stream, s))
    assert [r.frame for r in out] == list(range(50))
    assert all(r.status == Status.LOST for r in out[20:30])
    for r, p in zip(out[:20], alone, strict=True):
        assert np.allclose(r.pose.t, p.t, atol=1e-9)
    pe, _ = _errors(out[30:], b)
    assert pe.max() < 0.08  # 2.3 sigma of a raw pose; pulled across the gap: ~1 m
    # the first and last 3 frames of each stretch stay as tracked (no extrapolation)
    for j in (0, 1, 2, 17, 18, 19, 30, 31, 32, 47, 48, 49):
        assert out[j].pose is out[j].measurement.pose, j
    assert all(out[j].pose is not out[j].measurement.pose for j in (3, 16, 33, 46))


def _copy(r: FrameRecord) -> FrameRecord:
    return FrameRecord(
        r.status, r.pose, frame=r.frame, time_s=r.time_s, sigma_pos_m=r.sigma_pos_m,
        sigma_rot_deg=r.sigma_rot_deg, measurement=r.measurement,
    )  # fmt: skip


@pytest.mark.parametrize("lag", [0, 1, 7])
def test_every_frame_comes_back_once_in_order_lag_frames_late(lag):
    truth = _orbit(25)
    recs = _measure(truth, np.random.default_rng(6))
    recs[12] = FrameRecord(Status.LOST, frame=12, time_s=12 / FPS)
    sm = Smoother(SmoothSettings(lag=lag))
    got = []
    for i, r in enumerate(recs):
        out = sm.push(r)
        assert len(out) == (1 if i >= lag else 0)
        got += out
    got += sm.flush()
    assert [r.frame for r in got] == list(range(25))
    assert got[12].status == Status.LOST and got[12].pose is None
    if lag == 0:  # unsmoothed: the tracker's poses
        assert all(g.pose is r.pose for g, r in zip(got, recs, strict=True) if r.pose)


def test_an_uncertain_pose_becomes_ok_when_its_neighbours_pin_it():
    """A vague pose (sigma above its gate) between good ones is smoothed below the gate."""
    truth = _orbit(41)
    recs = _measure(truth, np.random.default_rng(7))
    vague = _measure(truth[20:21], np.random.default_rng(8), scale=3.0)[0]
    limit = 0.6 * vague.sigma_pos_m  # 1.8x its neighbours' (each a third of a measurement)
    m = vague.measurement
    vague.measurement = Measurement(m.pose, m.cov, m.cov_shared, 20, max_sigma_pos_m=limit)
    vague.status, vague.pose, vague.frame, vague.time_s = Status.UNCERTAIN, None, 20, 20 / FPS
    recs[20] = vague
    out = list(smoothed(recs, SmoothSettings()))
    assert out[20].status == Status.OK and out[20].sigma_pos_m <= limit
    assert out[20].pose.distance_to(truth[20]) < 3 * out[20].sigma_pos_m


def test_an_interrupt_writes_the_frames_the_smoother_held(sample_model, tmp_path, monkeypatch):
    """Ctrl-C after 30 tracked frames: the 15 the smoother still held are written too
    (smoothed with what came), so the CSV has every tracked frame; exit 130."""
    from conftest import SAMPLE, run_here

    from mirage_cli.pipelines import track
    from mirage_cli.trajectory import read_pose_csv

    real_run = track.track_frames

    def thirty_then_interrupt(frames, tracker, **kw):
        for i, rec in enumerate(real_run(frames, tracker, **kw)):
            yield rec
            if i == 29:
                raise KeyboardInterrupt

    monkeypatch.setattr(track, "track_frames", thirty_then_interrupt)
    out = tmp_path / "p.csv"
    r = run_here("track", SAMPLE / "orbit.mp4", "--model", sample_model, "-o", out)
    assert r.returncode == 130 and "kept 30 frames in" in r.stderr, r.stderr
    rows = read_pose_csv(out)
    assert rows["frame"].astype(int).tolist() == list(range(30))
    assert (rows["status"] == "ok").all()


@pytest.mark.parametrize("n", [2, 3, 31])
def test_the_band_layout_puts_each_block_where_the_dense_matrix_has_it(n):
    """The smoother assembles its information matrix straight into LAPACK's lower band
    storage (row d, column i: H[i + d, i]); the same blocks placed in a dense matrix give
    the same band, and the band's solve the dense solve."""
    rng = np.random.default_rng(n)
    blocks = rng.normal(size=(n, 3, 6, 6))
    blocks[:, 0] = blocks[:, 0] @ blocks[:, 0].transpose(0, 2, 1) + 40 * np.eye(6)
    H = np.zeros((6 * n, 6 * n))
    for r in range(n):
        for o in range(3):
            if r + o < n:
                H[6 * (r + o) : 6 * (r + o) + 6, 6 * r : 6 * r + 6] = blocks[r, o]
    H = np.tril(H) + np.tril(H, -1).T
    src, row, col = _band_layout(n)
    ab = np.zeros((_BAND + 1, 6 * n))
    ab[row, col] = blocks.ravel()[src]
    for d in range(_BAND + 1):
        want = np.diagonal(H, -d) if d < 6 * n else []
        np.testing.assert_array_equal(ab[d, : len(want)], want)
        assert not ab[d, len(want) :].any()
    g = rng.normal(size=6 * n)
    np.testing.assert_allclose(scipy.linalg.solveh_banded(ab, g, lower=True),
                               np.linalg.solve(H, g), rtol=1e-9)  # fmt: skip


@pytest.mark.parametrize(
    "anchors, ks",
    [([0, 1, 1, 3, None, 5, 6, 7, 8], (1, 3, 5, 8)), ([0, 1, 2], (0, 1, 2))],
    ids=["9 frames", "3 frames"],
)
def test_a_window_is_the_dense_map_of_its_linear_gaussian_problem(anchors, ks):
    """Every orientation the identity, so the problem is linear: the smoothed pose and
    covariance of each frame are the MAP and the inverse information of the whole window
    written out densely here: each pose's information (divided by the frames of its
    anchor, at least min_run), plus a second difference of each frame triple weighted by
    the white-noise acceleration prior, q = sigma_a^2 dt^3 (rotation in rad). In the 9
    frames one has no pose and two share an anchor (a flowed frame); 3 frames are the
    shortest with a prior."""
    from mirage_cli.tracking.smooth import WorldMeasurement, smooth_window

    rng = np.random.default_rng(5)
    n, dt = len(anchors), 1 / 30
    s = SmoothSettings(accel_m_s2=3.0, ang_accel_deg_s2=40.0, min_run=1.5)  # (3: 3^2 != 2 * 3)
    window = []
    for i, anchor in enumerate(anchors):
        if anchor is None:
            window.append(None)
            continue
        B = rng.normal(size=(6, 6))
        scale = np.sqrt([1e-6] * 3 + [1e-5] * 3)  # about a mrad and 3 mm
        cov = scale[:, None] * (B @ B.T + np.eye(6)) * scale[None, :]
        center = np.array([0.1, 0.02, 0.0]) * i * dt + rng.multivariate_normal(
            np.zeros(3), cov[3:, 3:] / 10
        )
        window.append(WorldMeasurement(np.eye(3), center, np.linalg.inv(cov), np.zeros((6, 6)),
                                       cov, anchor, 1.0, 10.0))  # fmt: skip
    q = np.array([np.radians(40.0) ** 2] * 3 + [3.0**2] * 3) * dt**3
    H, b = np.zeros((6 * n, 6 * n)), np.zeros(6 * n)
    for i, m in enumerate(window):
        if m is not None:
            runs = max(sum(x is not None and x.anchor == m.anchor for x in window), s.min_run)
            H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += m.info / runs
            b[6 * i : 6 * i + 6] += m.info / runs @ np.r_[0, 0, 0, m.center]
    for i in range(n - 2):
        A = np.zeros((6, 6 * n))
        for j, w in enumerate((1.0, -2.0, 1.0)):
            A[:, 6 * (i + j) : 6 * (i + j) + 6] = w * np.eye(6)
        H += A.T @ np.diag(1 / q) @ A
    x, C = np.linalg.solve(H, b).reshape(n, 6), np.linalg.inv(H)
    for k in ks:
        pose, cov = smooth_window(window, k, dt, s)
        np.testing.assert_allclose(pose.center, x[k, 3:], rtol=0, atol=1e-9)
        np.testing.assert_allclose(rotvec(pose.R.T), x[k, :3], rtol=0, atol=1e-12)  # R_WC
        np.testing.assert_allclose(cov, C[6 * k : 6 * k + 6, 6 * k : 6 * k + 6], rtol=1e-7,
                                   atol=1e-15)  # fmt: skip
    if None in window:
        assert smooth_window(window, window.index(None), dt, s) is None  # no pose of its own
    assert smooth_window([None, window[1], None], 1, dt, s) is None  # no other pose
    # two poses and no prior (it needs three frames): each keeps its own pose, and its
    # covariance is its own times min_run (a pose counts as 1/min_run of a measurement)
    pose, cov = smooth_window(window[:2], 0, dt, s)
    np.testing.assert_allclose(pose.center, window[0].center, atol=1e-12)
    np.testing.assert_allclose(cov, s.min_run * np.linalg.inv(window[0].info), rtol=1e-7,
                               atol=1e-15)  # fmt: skip


def _M_of(pose, sig_w=SIG_W, sig_v=SIG_V):
    from mirage_cli.tracking.smooth import prepare

    cov = np.diag([sig_w**2] * 3 + [sig_v**2] * 3)
    return prepare(Measurement(pose, cov, np.zeros((6, 6))))


def test_a_frame_between_poses_at_a_constant_rate_is_on_the_path():
    """Noise-free poses turning 20 deg a frame at a constant rate, one frame without a pose:
    the MAP is the path itself (no residual, no second difference), reached in one step
    only from a start on it (the missing frame interpolated halfway, at the right rate)."""
    from mirage_cli.tracking.smooth import smooth_window

    n, dt = 7, 1 / 30
    truth = []
    for i in range(n):  # R_WC turning about W's z; the centre at a constant velocity
        R_wc = rodrigues([0, 0, np.radians(20) * i]) @ rodrigues([1.2, 0.3, 0.1])
        c = np.array([0.3, -0.1, 2.0]) + [0.05 * i, 0.01 * i, 0]
        truth.append(Pose(R_wc.T, -R_wc.T @ c))
    window = [None if i == 3 else _M_of(T) for i, T in enumerate(truth)]
    for k in (2, 4):
        pose, _ = smooth_window(window, k, dt, SmoothSettings())
        assert pose.angle_to(truth[k]) < 1e-5 and pose.distance_to(truth[k]) < 1e-9  # deg, m


def test_outliers_are_dropped_down_to_two_poses():
    """A wild pose is dropped while two others remain (3 poses: the frame keeps its
    smoothed pose). (Two poses always fit a constant-velocity path: none is ever wild.)"""
    from mirage_cli.tracking.smooth import smooth_window

    truth = _orbit(3)
    window = [_M_of(T) for T in truth]
    wild = Pose(truth[2].R, truth[2].t + [0.5, 0, 0])
    window[2] = _M_of(wild)
    got = smooth_window(window, 0, 1 / 30, SmoothSettings())
    assert got is not None and got[0].distance_to(truth[0]) < 1e-6


def _records(truth, times, shared=None, max_pos=np.inf, max_rot=np.inf, seed=3):
    rng = np.random.default_rng(seed)
    recs = _measure(truth, rng)
    for r, t in zip(recs, times, strict=True):
        r.time_s = t
        m = r.measurement
        r.measurement = Measurement(m.pose, m.cov, shared if shared is not None else m.cov_shared,
                                    m.anchor, max_pos, max_rot)  # fmt: skip
    return recs


@pytest.mark.parametrize("fps", [20.0, None])
def test_the_smoother_windows_the_stretch_and_times_the_prior(fps):
    """A frame's window is every pose within `lag` frames that no gap longer than
    `max_gap` separates from it (a gap of exactly 3 frames is bridged, 4 split), the
    prior's dt is the median step of the stamps (or 1 / fps without stamps), and the
    model's shared error is added back to the smoothed covariance."""
    from mirage_cli.tracking.smooth import prepare, smooth_window

    n, k, lag = 30, 14, 12
    truth = _orbit(n)
    times = [i / fps if fps else float("nan") for i in range(n)]
    shared = np.diag([1e-8] * 3 + [1e-6] * 3)
    recs = _records(truth, times, shared)
    # 4 frames without a pose split (3-6, 23-26), 3 are bridged (11-13, 15-17, next to the
    # frame): its window is frames 7-22
    for i in (3, 4, 5, 6, 11, 12, 13, 15, 16, 17, 23, 24, 25, 26):
        recs[i] = FrameRecord(Status.LOST, frame=i, time_s=times[i])
    s = SmoothSettings(lag=lag, fps=30.0)
    got = {r.frame: r for r in smoothed([copy_record(r) for r in recs], s)}[k]
    window = [prepare(r.measurement) if r.measurement else None for r in recs[7:23]]
    dt = 1 / fps if fps else 1 / 30
    pose, cov = smooth_window(window, k - 7, float(f"{dt:.4g}"), s)
    assert got.status == Status.OK
    assert got.pose.distance_to(pose) < 1e-12 and got.pose.angle_to(pose) < 1e-5
    m = recs[k].measurement
    own = world_covariance(m.cov, m.pose)  # its correlated share is added back too
    pos, rot = sigmas(cov + world_covariance(shared, m.pose) + s.correlated * own)
    assert got.sigma_pos_m == pytest.approx(min(pos, recs[k].sigma_pos_m), rel=1e-9)
    assert got.sigma_rot_deg == pytest.approx(min(rot, recs[k].sigma_rot_deg), rel=1e-9)


def copy_record(r):
    import copy

    return copy.copy(r)


def test_the_smoothed_pose_is_gated_like_a_tracked_one():
    """ok only when both sigmas are within the frame's own limits (at the limit: ok)."""
    truth = _orbit(9)
    base = {r.frame: r for r in smoothed(_records(truth, [i / 30 for i in range(9)]),
                                    SmoothSettings(lag=4))}[4]  # fmt: skip
    pos, rot = base.sigma_pos_m, base.sigma_rot_deg
    for max_pos, max_rot, want in ((pos, rot, Status.OK), (pos * 0.99, 10 * rot, Status.UNCERTAIN),
                                   (10 * pos, rot * 0.99, Status.UNCERTAIN)):  # fmt: skip
        recs = _records(truth, [i / 30 for i in range(9)], max_pos=max_pos, max_rot=max_rot)
        got = {r.frame: r for r in smoothed(recs, SmoothSettings(lag=4))}[4]
        assert got.status == want, (max_pos, max_rot, got.status)
        assert (got.pose is None) == (want == Status.UNCERTAIN)


def test_a_lag_of_one_smooths_with_min_side_one():
    truth = _orbit(5)
    recs = _records(truth, [i / 30 for i in range(5)])
    tracked = recs[2].pose
    got = list(smoothed(recs, SmoothSettings(lag=1, min_side=1)))
    assert got[2].status == Status.OK and got[2].pose.distance_to(tracked) > 1e-6


def test_the_smoothing_time_is_added_to_the_frame_time():
    """`ms` of a smoothed frame is the tracker's time plus the smoothing (a few ms)."""
    recs = _measure(_orbit(20), np.random.default_rng(8))
    for r in recs:
        r.ms = 5.0
    got = list(smoothed(recs, SmoothSettings(lag=5)))
    timed = [g for g in got[5:15] if g.ms != 5.0]
    assert len(timed) == 10  # every frame with 3 poses either side took some time
    assert all(5.0 < g.ms < 5.0 + 1000 for g in timed), [g.ms for g in timed]
