"""Per-frame camera pose against a landmark model (brief, section 4.3). Pure core.

Each frame is either *detected* (features matched to the model's keyframes, RANSAC,
Mirage-S from the best keyframe's or the predicted pose) or *flowed* (the last detection's
inliers followed with pyramidal Lucas-Kanade from the frame they were detected in, keeping
their 3D points, then Mirage-S from the previous pose). Flow costs a few milliseconds where
detection costs tens, so detection runs only every `redetect_every` frames, when the flow
weakens or when a flowed pose leaves the prediction. The costly part of a detection, the
features, is mostly known in advance and runs on the second core: once a frame is
detected, the features of the frame `redetect_every` + 1 later (in the box its pose
predicts), while the frames between are flowed; and while lost, the coming frames'
searches while this one is matched. What is detected, and where, depends on the frames alone,
never on timing, so a run gives the same poses however the threads are scheduled. Every
pose ends in the same gate, so a frame without enough consistent evidence on the landmark
itself, or whose honest uncertainty is too large, is not `ok`: never a guess.
"""

from __future__ import annotations

import os
import time
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from . import signals
from .camera import Camera
from .evidence import chance_inlier_probability, is_evidence, search_area
from .features import detect, guided_match, make_detector, to_gray
from .frames import Frame
from .model import LandmarkModel, ground_points, point_twins
from .pose import Pose
from .signals import through_compiled_code
from .solver import (
    PoseEstimate,
    RansacOptions,
    RefineOptions,
    sandwich_covariance,
    sigmas,
    solve_pose,
)
from .solver import warm_up as _warm_up_solver
from .tilt import ABOVE_DEG, elevation_deg
from .trajectory import FrameRecord, Measurement, Reason, Status

RANSAC_HYPOTHESES = RansacOptions.iterations  # how many poses RANSAC tries at most


@dataclass
class TrackSettings:
    method: str = "mirage-s"
    redetect_every: int = 5  # frames between full detections while flow holds
    detect_ahead: bool = True  # the next regular detection's features are detected on
    # the second core while the frames before it are flowed (False: in its own frame)
    min_inliers: int = 15  # fewer consistent points without a prediction: lost
    min_track_inliers: int = 6  # while tracking (a prediction to match around and start
    # Mirage-S from) the pose's uncertainty decides, so a few well-spread points suffice
    max_false_alarms: float = 1e-3  # the inliers must rule out chance: at most this many
    # of RANSAC's hypotheses would gather as much support from wrong matches (evidence.py)
    min_landmark_inliers: int = 10  # inliers on the landmark itself, not the ground
    max_rmse_px: float = 2.0
    ransac_px: float = 3.0
    reject_px: float = 2.0  # the fit drops points beyond max(this, 5 sigma)
    huber_px: float = 0.5  # Mirage-S's Huber floor: residuals beyond max(this, 2.5 sigma)
    # weigh less (a model point or keypoint that is off by a pixel pulls the pose less)
    ratio: float = 0.8
    flow: bool = True
    min_flow_points: int = 30
    flow_fb_px: float = 0.7  # forward-backward consistency of Lucas-Kanade
    flow_window_px: int = 7  # Lucas-Kanade window: small, so it stays on one surface
    flow_levels: int = 1  # pyramid levels above the image: each point starts where the
    # predicted pose puts it (forward) or at its anchor (backward), so one suffices
    flow_keep: float = 0.5  # fewer of the detected points still followed: detect afresh
    flow_max_dev_sigma: float = 4.0  # flowed pose this many sigmas off the prediction: detect
    flow_max_rmse_px: float = 1.0  # a worse flowed fit (large motion, drift) -> detect
    flow_gain_tol: float = 0.05  # the exposure changed more since the anchor: flow again
    # in the frame scaled to the anchor's brightness (Lucas-Kanade assumes it constant)
    local_keyframes: int = 4  # keyframes near the previous pose to match against
    global_keyframes: int = 3  # keyframes proposed by recognition when lost
    relocalise_every: int = 3  # while lost: the whole frame every N frames, a half-size
    # probe between (1: the whole frame every time)
    long_lost: int = 12  # lost longer than this (a look-away, not a dropout): the whole
    # frame every 2N frames, the probe every other frame between
    max_jump_m: float = 0.5  # a pose this far from the previous ok pose (per frame)...
    max_jump_deg: float = 30.0  # ...or turned this much is distrusted (needs detection)
    guided_radius_px: float = 40.0  # while tracking: match only near the predicted pixel
    detect_margin_px: int = 32  # while tracking: detect only in the predicted box of the
    # model's points plus this margin (-1: always the whole frame)
    upsample_below_px: int = 320  # a smaller detection box (longer side, px; 0: never)...
    upsample_to_px: int = 480  # ...is upsampled to this size before detection
    shrink_above: float = 1.5  # the landmark looks this many times larger than from its
    # nearest keyframe (a sharper camera than the model's, or nearer): the detection box
    # is shrunk by that factor / SHRINK_MARGIN first (the keyframes hold no finer
    # features; SIFT's time goes with the pixels)
    second_hypothesis: float = 0.5  # relocalisation: a distinct pose with this share of the
    # first's inliers makes the frame ambiguous (lost)
    distinct_m: float = 0.10  # two poses further apart than this (or distinct_deg) are
    distinct_deg: float = 5.0  # different hypotheses
    model_error_points: float = 300.0  # model/keypoint errors average like this many points
    max_sigma_pos_m: float = 0.10  # a larger 1-sigma uncertainty is `uncertain`, not ok
    max_sigma_rot_deg: float = 1.5
    max_sigma_range: float = 0.01  # ...or larger than this share of the landmark's distance
    seed: int = 0


def unambiguous_pose(
    X: np.ndarray,
    uv: np.ndarray,
    unique: np.ndarray,
    camera: Camera,
    reference: Pose | None,
    s: TrackSettings,
) -> PoseEstimate | Status:
    """Pose from matches with no prior pose, or why not (LOST, AMBIGUOUS).

    RANSAC runs on the `unique` matches only (points without a descriptor twin), so
    repeated texture never decides the pose. Then the second-hypothesis test: RANSAC
    again on the unique matches the first pose does not explain; a pose distinct from the
    first (`distinct_m` / `distinct_deg`) with at least `second_hypothesis` of its
    support means the evidence fits two places, and the answer is AMBIGUOUS. The
    accepted pose is refined over every match that agrees with it, twins included.
    """
    if unique.sum() < s.min_inliers:
        return Status.LOST
    kw = dict(
        method=s.method,
        ransac=RansacOptions(threshold_px=s.ransac_px, seed=s.seed),
        refine=RefineOptions(reject_px=s.reject_px, huber_px=s.huber_px),
    )
    Xu, uvu = X[unique], uv[unique]
    first = solve_pose(Xu, uvu, camera, reference, **kw)
    if not first.success:
        return Status.LOST
    n1 = int(first.inliers.sum())
    rest = ~first.inliers
    if rest.sum() >= max(s.min_inliers, 6):
        second = solve_pose(Xu[rest], uvu[rest], camera, None, **kw)
        if (
            second.success
            and second.inliers.sum() >= max(s.min_inliers, s.second_hypothesis * n1)
            and (
                second.pose.distance_to(first.pose) > s.distinct_m
                or second.pose.angle_to(first.pose) > s.distinct_deg
            )
        ):
            return Status.AMBIGUOUS
    err = np.linalg.norm(camera.project(X, first.pose) - uv, axis=1)
    inl = (err < s.ransac_px) & (first.pose.transform(X)[:, 2] > 0)
    full = np.zeros(len(X), bool)
    full[np.flatnonzero(unique)[first.inliers]] = True
    first.inliers = full
    if inl.sum() <= n1:
        return first
    final = solve_pose(
        X[inl], uv[inl], camera, first.pose, method=s.method,
        refine=RefineOptions(reject_px=s.reject_px, huber_px=s.huber_px),
    )  # fmt: skip
    if not final.success:
        return first
    full = np.zeros(len(X), bool)
    full[np.flatnonzero(inl)[final.inliers]] = True
    final.inliers = full
    return final


def frame_covariances(
    est: PoseEstimate,
    n: int,
    camera: Camera,
    points=None,
    huber_px: float = 0.5,
    model_rms_px: float = 0.0,
    model_error_points: float = 300.0,
    model_error_scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """6x6 covariances (the solver's parametrisation) of a pose: what its residuals show,
    and the model's own error (shared with every frame that sees the same points); the
    pose's is their sum.

    What the residuals show comes from the leverage-corrected sandwich covariance of the
    inliers (`points`: X, uv and est.inliers; see `solver.sandwich_covariance`), so a pose
    carried by a few bad or isolated points is as uncertain as it is; without points, the
    solver's (J^T J)^-1 s_res^2. Errors of the model points and of keypoint localisation
    on a face seen at an angle are shared by neighbouring points and do not average out
    over n, so they count as the model's reprojection RMS over `model_error_points`
    independent points: (J^T J)^-1 s_model^2 n / n_model. `model_error_scale` is what the
    model's leave-one-keyframe-out check measured (model_check.py): how much larger a
    pose's error is than these two predict, with the model's points and poses as they
    are (keyframe pose errors, calibration, real pixels); the excess is added to the
    shared part, which the smoother does not average away.
    """
    s2 = est.sigma_px**2
    res = est.covariance
    if not s2 > 0:
        return res, np.zeros((6, 6))
    if points is not None:
        X, uv = points
        inl = est.inliers
        sw = sandwich_covariance(X[inl], uv[inl], est.pose, camera, huber_px)
        if np.all(np.isfinite(sw)):
            res = sw
    shared = est.covariance * (model_rms_px**2 * n / (model_error_points * s2))
    if model_error_scale > 1.0:
        shared = shared + (model_error_scale**2 - 1.0) * (res + shared)
    return res, shared


def warm_up() -> None:
    """Compile (or load from the cache) the solver's and guided matching's kernels, so that
    `mirage track` does it before its clock starts instead of in the first frames."""
    _warm_up_solver()
    d = np.arange(256, dtype=np.float32).reshape(2, 128)  # integers: the compiled path
    px = np.zeros((2, 2), np.float32)
    guided_match(px, d, px, d, np.arange(2), 10.0)


_WORKER: ThreadPoolExecutor | None = None


def _worker() -> ThreadPoolExecutor:
    """The one background thread for detections (OpenCV's detectors release the GIL)."""
    global _WORKER
    if _WORKER is None:
        _WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mirage-detect")
    return _WORKER


def _forget_worker() -> None:
    global _WORKER
    _WORKER = None  # a forked child has none of the parent's threads: start its own


os.register_at_fork(after_in_child=_forget_worker)


def _local_means(gray: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Mean of the 7x7 pixels around each point (nearest pixel; 0 outside the image)."""
    h, w = gray.shape[:2]
    ij = np.rint(px).astype(np.int64)
    inside = (ij[:, 0] >= 3) & (ij[:, 0] < w - 3) & (ij[:, 1] >= 3) & (ij[:, 1] < h - 3)
    out = np.zeros(len(px))
    if inside.any():
        ii = ij[inside]
        x0, y0 = ii.min(axis=0) - 3
        x1, y1 = ii.max(axis=0) + 4
        area = cv2.blur(gray[y0:y1, x0:x1], (7, 7), borderType=cv2.BORDER_REPLICATE)
        out[inside] = area[ii[:, 1] - y0, ii[:, 0] - x0]
    return out


# a shrunk box keeps this much more resolution than the keyframes' (sub-pixel keypoints):
# 720p / 1080p orbits against the sample's model, p95 2.52 / 2.62 mm shrunk to the keyframes'
# scale, 1.98 / 2.40 mm with this margin (2.22 / 2.99 unshrunk)
SHRINK_MARGIN = 1.25


def _median_depth(pose: Pose, points: np.ndarray) -> float:
    """Median depth of the points seen from `pose` (0 without any)."""
    return float(np.median(pose.transform(points)[:, 2])) if len(points) else 0.0


def _deviation(res: FrameRecord, pred: Pose) -> float:
    """How far a pose is from its prediction, in the position sigmas of its residuals."""
    return res.pose.distance_to(pred) / max(sigmas(res.measurement.cov)[0], 1e-9)


class Tracker:
    """Stateful per-frame tracker; feed frames in order with `process(gray)`.

    Two kinds of detection. While tracking, features are detected in the box where the
    predicted pose (constant velocity, or the last frame's `uncertain` pose) puts the model
    (upsampled when small), and model points of the keyframes near the prediction are
    projected and matched only within `guided_radius_px` of their predicted pixel, so
    repeated texture elsewhere in the model cannot compete. When lost, the frame is
    *relocalised*: global recognition, descriptor matching, RANSAC on the matches to points
    that are neither twins (repeated texture) nor ground, then a second-hypothesis test
    (RANSAC again without the first pose's inliers); a distinct second pose with
    comparable support makes the frame `ambiguous`. The final pose is refined over every
    match consistent with it.
    """

    PREDICT_LOST = 3  # lost frames in a row that are still searched around the last pose

    def __init__(self, model: LandmarkModel, camera: Camera, settings: TrackSettings):
        self.model, self.camera, self.s = model, camera, settings
        self.detector = make_detector(model.detector)
        self.prev_pose: Pose | None = None
        self.velocity: Pose | None = None  # T_k @ T_{k-1}^-1 of the last two ok frames
        self.since_detect = 0
        self.lost_run = 0
        self.keyframe = -1
        self.track_px: np.ndarray | None = None  # (N,2) float32 inliers in prev frame
        self.track_X: np.ndarray | None = None  # (N,3) their model points
        self.track_land: np.ndarray | None = None  # (N,) bool: on the landmark
        # flow follows each point from the frame where it was detected (the anchor), so
        # its error does not add up from frame to frame
        self.anchor_gray: np.ndarray | None = None
        self.anchor_px: np.ndarray | None = None  # (N,2) float32, rows of track_px
        self.anchor_n = 0  # points detected in the anchor
        self._anchor_level: np.ndarray | None = None  # their 7x7 means (flow's gain check)
        self._kf_cache: dict[int, tuple] = {}
        self.twins = point_twins(model)  # the model's tables, built before the first frame
        model.prepare_recognition()
        self.on_landmark = ~ground_points(model.points)
        self.votes = ~self.twins & self.on_landmark  # may decide a relocalisation
        self._frame_no = -1  # frames processed, for the smoother's anchors
        self._anchor_no = -1  # the frame whose detection the flowed points come from
        self.hint: Pose | None = None  # the previous frame's uncertain pose (where to look)
        self._uncertain_pose: Pose | None = None
        # features of coming frames being detected on the worker: (frame, kind) -> Future,
        # kind 'box' (the next regular detection), 'lostbox', 'probe' or 'full' (a lost
        # frame's search: in the last pose's box, the half-size probe, the whole frame)
        self._pending: dict[tuple[int, str], Future] = {}
        self._bg_detector = None  # the worker's own detector object
        # the next regular detection's job, held until the frame after a detection flows
        self._held_box: tuple | None = None
        # where to detect while tracking: where the model has points (a subsample suffices;
        # the ground near the landmark steadies the pose, so it counts)
        P = model.points
        self._model_X = P[:: max(1, len(P) // 2000)] if len(P) else None
        # the landmark's scale in a frame against its keyframes: their median point depth
        # and the focal lengths (a model from one camera may track another's video)
        kfs = model.keyframes
        self._kf_points = [P[np.unique(kf.point_ids[kf.point_ids >= 0])] for kf in kfs]
        self._kf_depth = np.array(
            [_median_depth(kf.pose, X) for kf, X in zip(kfs, self._kf_points, strict=True)]
        )
        self._focal_ratio = float(camera.K[0, 0] / model.camera.K[0, 0])
        # how high each keyframe looks at the landmark (when to match its squashed views)
        land = P[self.on_landmark] if self.on_landmark.any() else P
        self._target = land.mean(axis=0) if len(land) else np.zeros(3)
        self._kf_elev = np.array([elevation_deg(kf.pose.center, self._target) for kf in kfs])
        err = model.reprojection_errors()
        self.model_rms_px = float(np.sqrt(np.mean(err**2))) if err.size else 0.0
        self.model_error_scale = float(model.meta.get("check", {}).get("error_scale", 1.0))

    @property
    def lookahead(self) -> int:
        """Frames `process` wants to see ahead of the current one (`ahead`)."""
        return self.s.redetect_every + 1 if self.s.flow and self.s.detect_ahead else 0

    # ------------------------------------------------------------------------------------
    def process(self, gray: np.ndarray, ahead: Sequence[np.ndarray | None] = ()) -> FrameRecord:
        """The record of this frame; `ahead` holds the next frames' gray images (None where
        undecodable), up to `lookahead` of them, for the next detection's features."""
        res = None
        self._uncertain_pose = None
        self._frame_no += 1
        self._pending = {k: f for k, f in self._pending.items() if k[0] >= self._frame_no}
        if self.lost_run > 0 and (self.prev_pose is not None or self.hint is None):
            self._search_ahead(ahead)  # lost (the first frame is expected to find it)
        if (
            self.s.flow
            and self.prev_pose is not None
            and self.track_px is not None
            and self.since_detect < self.s.redetect_every
        ):
            res = self._flow(gray)
        if res is None or not res.ok:
            res = self._detect(gray)
            if res.ok:
                self.anchor_gray, self.anchor_px = gray, self.track_px.copy()
                self.anchor_n = len(self.anchor_px)
                self._anchor_level = None
                self._anchor_no = self._frame_no
        if res.measurement is not None:  # flowed points share their anchor's errors
            res.measurement.anchor = self._anchor_no if res.mode == "flow" else self._frame_no
        if res.ok:
            # a detection near its prediction: the next frame's flow check will not doubt it
            calm = (
                res.mode != "flow" and self.velocity is not None and self.lost_run == 0
                and _deviation(res, self._predicted()) < self.s.flow_max_dev_sigma - 2
            )  # fmt: skip
            if self.prev_pose is not None and self.lost_run == 0:
                self.velocity = res.pose @ self.prev_pose.inverse()
            else:
                self.velocity = None
            self.prev_pose = res.pose
            self.lost_run = 0
            self._drop("full", "probe", "lostbox")  # found: the searches queued are moot
            if res.mode != "flow":
                self._detect_ahead(ahead, gray.shape, calm)
            elif self._held_box is not None:
                self._start(*self._held_box)
                self._held_box = None
        else:
            self.lost_run += 1
            self._drop("box")
            self._held_box = None
            self.track_px = self.track_X = self.track_land = None
            self.velocity = None
            if self.lost_run > self.PREDICT_LOST:
                self.prev_pose = None  # too long: recognise globally again
        # a pose too vague to write still says where to look in the next frame
        self.hint = self._uncertain_pose if res.status == Status.UNCERTAIN else None
        return res

    def _predicted(self, frames: int = 1) -> Pose | None:
        """The pose `frames` frames after the last one, at constant velocity."""
        if self.prev_pose is None:
            return self.hint  # the last frame's uncertain pose, if any
        if self.velocity is None:
            return self.prev_pose
        p = self.prev_pose
        for _ in range(frames):
            p = self.velocity @ p
        u, _, vt = np.linalg.svd(p.R)  # keep R orthonormal: products drift off it
        return Pose(u @ vt, p.t)

    # ------------------------------------------------------------------------------------
    def _flow(self, gray: np.ndarray) -> FrameRecord | None:
        a0 = self.anchor_px.reshape(-1, 1, 2)
        lk = dict(
            winSize=(self.s.flow_window_px, self.s.flow_window_px),
            maxLevel=self.s.flow_levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        # start each point where the predicted pose puts it (large motions stay within the
        # small window's reach), or where it was in the previous frame
        pred = self._predicted()
        guess = self.track_px
        if self.velocity is not None and np.all(pred.transform(self.track_X)[:, 2] > 1e-3):
            guess = self.camera.project(self.track_X, pred).astype(np.float32)
        tracked = self._lucas_kanade(gray, a0, guess, lk)
        if tracked is None:
            return None
        # Lucas-Kanade assumes constant brightness: when the exposure changed since the
        # anchor (auto-exposure; measured where the points flowed), flow again in the
        # frame scaled to the anchor's brightness (the first pass's points are biased)
        gain = self._gain(gray, *tracked)
        if abs(gain - 1) > self.s.flow_gain_tol:
            gray = cv2.convertScaleAbs(gray, alpha=gain)
            tracked = self._lucas_kanade(gray, a0, guess, lk)
            if tracked is None:
                return None
        p1, good = tracked
        if good.sum() < max(self.s.min_flow_points, self.s.flow_keep * self.anchor_n):
            return None  # the flow has weakened: detect afresh
        X, uv = self.track_X[good], p1[good]
        est = solve_pose(
            X,
            uv,
            self.camera,
            reference_pose=self.prev_pose,
            method=self.s.method,
            refine=RefineOptions(reject_px=self.s.reject_px, huber_px=self.s.huber_px),
        )
        land = self.track_land[good]
        res = self._gate(est, len(uv), "flow", True, land, (X, uv))
        if res.ok and est.rmse_px > self.s.flow_max_rmse_px:
            return None  # the flow has drifted or the motion was too large: detect afresh
        if res.ok and self.velocity is not None:
            # points that slid along an edge bend the pose while the residuals stay small;
            # a smooth path predicts the pose well, so a flowed pose far from the
            # prediction (in the sigmas of its residuals) is checked by a detection
            if _deviation(res, pred) > self.s.flow_max_dev_sigma:
                return None
        if res.ok:
            self.since_detect += 1
            self.track_px, self.track_X = uv[est.inliers].astype(np.float32), X[est.inliers]
            self.track_land = land[est.inliers]
            self.anchor_px = self.anchor_px[good][est.inliers]
            self._anchor_level = self._anchor_level[good][est.inliers]
            res.inlier_px = self.track_px
        return res

    def _lucas_kanade(self, gray, a0, guess, lk) -> tuple[np.ndarray, np.ndarray] | None:
        """The anchor's points in `gray` (N,2) and which of them flowed well (both ways)."""
        try:  # from the anchor image: the error does not add up from frame to frame
            p1, st, _ = cv2.calcOpticalFlowPyrLK(
                self.anchor_gray, gray, a0, guess.reshape(-1, 1, 2).copy(), **lk
            )
            p0r, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self.anchor_gray, p1, a0.copy(), **lk)
        except cv2.error:
            return None
        p1, p0r = p1.reshape(-1, 2), p0r.reshape(-1, 2)
        fb = np.linalg.norm(p0r - self.anchor_px, axis=1)
        h, w = gray.shape[:2]
        good = (
            (st.ravel() == 1) & (st2.ravel() == 1) & (fb < self.s.flow_fb_px)
            & (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        )  # fmt: skip
        return p1, good

    def _gain(self, gray: np.ndarray, p1: np.ndarray, good: np.ndarray) -> float:
        """The anchor's brightness over this frame's at the well-flowed points: the median
        ratio of their 7x7 means, the same surface in both (1 with too few points)."""
        if self._anchor_level is None:
            self._anchor_level = _local_means(self.anchor_gray, self.anchor_px)
        then, now = self._anchor_level[good], _local_means(gray, p1[good])
        ok = (now > 8) & (then > 8)  # dark points say little about the gain
        return float(np.median(then[ok] / now[ok])) if ok.sum() >= 10 else 1.0

    def _detect_ahead(self, ahead, shape, calm: bool = False) -> None:
        """A frame was just detected: if flow holds, the next detection comes
        `redetect_every` + 1 frames later, so start detecting that frame's features now, on
        the worker thread, in the box that covers the model both where it is now and where
        the constant-velocity prediction puts it then (a box too small to detect without
        upsampling, a far landmark, is left to its own frame: its scale must come from
        the box that frame predicts). Unless this detection was `calm` (within
        `flow_max_dev_sigma` - 2 sigmas of its prediction), the job starts only once the
        next frame has flowed: the flow's deviation check often asks for a detection right
        there (the velocity then spans the jump from the flowed poses to the detected one),
        which would leave the features unused, their time taken from that detection
        (sample orbit: after 14 of the 47 detections that were not calm, after 2 of the 48
        calm ones; a calm bound 1 sigma higher measured no faster)."""
        self._drop("box")
        self._held_box = None
        k = self.lookahead
        if not k or len(ahead) < k or ahead[k - 1] is None or ahead[k - 1].shape != shape:
            return
        boxes = [self._model_box(p, shape) for p in (self.prev_pose, self._predicted(k))]
        box = None
        if all(b is not None for b in boxes):
            (a0, a1, a2, a3, ash), (b0, b1, b2, b3, bsh) = boxes
            if max(b2 - b0, b3 - b1, a2 - a0, a3 - a1) < self.s.upsample_below_px:
                return
            box = (min(a0, b0), min(a1, b1), max(a2, b2), max(a3, b3), min(ash, bsh))
        self._held_box = (self._frame_no + k, "box", self._box_features, ahead[k - 1], box)
        if calm:
            self._start(*self._held_box)
            self._held_box = None

    def _search_ahead(self, ahead) -> None:
        """Lost: the coming frames, if they stay lost, are searched as `lost_run` says (in
        the box of the last pose while it is kept, then the whole frame or the half-size
        probe), so their features are queued on the worker, as far ahead as the frames
        are decoded, and detected while this frame is matched. What is searched depends
        on the frames and the last pose alone; a frame that is not processed
        (undecodable) does not count."""
        n, box = 0, None
        for gray in ahead[: self.lookahead]:
            if gray is None:
                continue
            n += 1
            lost_run, frame_no = self.lost_run + n, self._frame_no + n
            if (
                self.prev_pose is not None and lost_run <= self.PREDICT_LOST
                and (frame_no, "lostbox") not in self._pending
            ):  # fmt: skip
                if box is None:  # no velocity while lost: the same box for every frame
                    box = self._model_box(self.prev_pose, gray.shape) or ()
                if box:
                    self._start(frame_no, "lostbox", self._box_features, gray, box)
                    self._pending[frame_no, "lostbox"].box = box
            kind = self._search(lost_run)
            if kind is not None and (frame_no, kind) not in self._pending:
                fn = self._probe_features if kind == "probe" else detect
                self._start(frame_no, kind, fn, gray)

    def _drop(self, *kinds: str) -> None:
        """Forget the features of those kinds detected ahead (the plan changed); those not
        started yet are not detected at all."""
        for key in [k for k in self._pending if k[1] in kinds]:
            self._pending.pop(key).cancel()

    def _start(self, frame_no: int, kind: str, fn, gray, *args) -> None:
        if self._bg_detector is None:
            self._bg_detector = make_detector(self.model.detector)
        self._pending[frame_no, kind] = _worker().submit(fn, gray, *args, self._bg_detector)

    def _features(self, kind: str, fn, gray, *args):
        """This frame's features of that kind: detected ahead when they were, else now."""
        job = self._pending.pop((self._frame_no, kind), None)
        return job.result() if job is not None else fn(gray, *args, self.detector)

    def _search(self, lost_run: int) -> str | None:
        """How a lost frame is searched: 'full' (the whole frame) every `relocalise_every`
        frames, a 'probe' between (half size: a quarter of the pixels; it goes on to the
        whole frame only when it finds the landmark, so a far one waits for the next full
        search). Lost for longer than `long_lost` frames (a look-away, not a dropout), the
        whole frame every 2N frames and the probe every other frame between (None: not
        searched), so a near landmark is found within a frame of its return."""
        long = lost_run > self.s.long_lost
        if lost_run % (self.s.relocalise_every * (2 if long else 1)) == 0:
            return "full"
        return None if long and lost_run % 2 else "probe"

    def _probe_features(self, gray: np.ndarray, detector) -> tuple[np.ndarray, np.ndarray]:
        small = cv2.resize(gray, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        kps, desc = detect(small, detector)
        return kps * np.float32(2) + np.float32(0.5), desc

    def _box_features(self, gray: np.ndarray, box, detector) -> tuple[np.ndarray, np.ndarray]:
        """Features in the pixel box (None: the whole frame): shrunk first when the landmark
        looks larger than from its keyframes, else upsampled when the box is small."""
        if box is None:
            return detect(gray, detector)
        x0, y0, x1, y1, shrink = box
        crop = gray[y0:y1, x0:x1]
        up = 1.0
        if shrink > 1:  # the landmark larger than in its keyframes: at their scale
            up = 1 / shrink
            crop = cv2.resize(crop, None, fx=up, fy=up, interpolation=cv2.INTER_AREA)
        elif max(crop.shape) < self.s.upsample_below_px:  # small and far: finer features
            up = self.s.upsample_to_px / max(crop.shape)
            crop = cv2.resize(crop, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC)
        kps, desc = detect(crop, detector)
        return kps / np.float32(up) + np.array([x0, y0], np.float32), desc

    def _detect(self, gray: np.ndarray) -> FrameRecord:
        self.since_detect = 0
        pred = self._predicted()
        box = self._model_box(pred, gray.shape) if pred is not None else None
        early = self._pending.pop((self._frame_no, "box"), None) if pred is not None else None
        if early is None and box is not None:  # searched ahead in this box, while lost?
            early = self._pending.pop((self._frame_no, "lostbox"), None)
            early = early if early is not None and early.box == box else None
        if early is not None or box is not None:  # tracking: where the model is predicted
            if early is not None:
                kps, desc = early.result()
            else:
                kps, desc = self._box_features(gray, box, self.detector)
            if len(kps) >= self.s.min_track_inliers:
                res = self._guided(kps, desc, pred)
                # an uncertain pose found the landmark where predicted and says its view
                # is too weak: relocalising (no prediction, a stricter gate) sees the same
                # view and costs a full-frame detection more (4 m orbit: 200 ms a frame)
                if res.ok or res.status == Status.UNCERTAIN:
                    return res
        search = self._search(self.lost_run)
        if search is None:
            return FrameRecord(Status.LOST, mode="relocalise", reason=Reason.NOT_SEARCHED)
        if search == "probe":
            probe = self._probe(gray)
            if probe.status == Status.LOST:
                return probe
        kps, desc = self._features("full", detect, gray)
        if desc is None or len(kps) < self.s.min_inliers:
            return FrameRecord(Status.LOST, mode="detect", reason=Reason.FEW_FEATURES)
        if pred is not None and box is None:
            res = self._guided(kps, desc, pred)
            if res.ok or res.status == Status.UNCERTAIN:  # as above
                return res
        return self._relocalise(kps, desc)  # also when the prediction was too far off

    def _probe(self, gray: np.ndarray) -> FrameRecord:
        kps, desc = self._features("probe", self._probe_features, gray)
        if desc is None or len(kps) < self.s.min_inliers:
            return FrameRecord(Status.LOST, mode="relocalise", reason=Reason.FEW_FEATURES)
        return self._relocalise(kps, desc)

    def _model_box(self, pred: Pose, shape) -> tuple[int, int, int, int, float] | None:
        """Pixel box (x0, y0, x1, y1) around the model's points as the predicted pose sees
        them, with a margin: nothing outside it can match; and the factor to shrink it by
        before detection (`shrink_above`; 1: none). None when it would cover most of the
        frame anyway (or too few points are predicted in front), so the whole frame is
        searched."""
        if self.s.detect_margin_px < 0 or self._model_X is None:
            return None
        X = self._model_X
        front = pred.transform(X)[:, 2] > 1e-3
        if front.sum() < self.s.min_inliers:
            return None
        uv = self.camera.project(X[front], pred)
        if not np.isfinite(uv).all():  # points far off-axis: the distortion has no image
            return None  # (what the NaN box came to before, without numpy's warning)
        h, w = shape[:2]
        m = self.s.detect_margin_px
        lo, hi = np.percentile(uv, [1, 99], axis=0)  # one partition for both
        x0, y0 = np.floor(lo - m).astype(int)
        x1, y1 = np.ceil(hi + m).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 - x0 < 32 or y1 - y0 < 32 or (x1 - x0) * (y1 - y0) > 0.7 * w * h:
            return None
        shrink = 1.0
        if len(self._kf_depth):
            kf = self.model.nearest_keyframes(pred, 1)[0]  # its points, then and now
            depth = _median_depth(pred, self._kf_points[kf])
            larger = self._focal_ratio * self._kf_depth[kf] / depth if depth > 0 else 1.0
            shrink = round(larger / SHRINK_MARGIN, 2) if larger >= self.s.shrink_above else 1.0
        return int(x0), int(y0), int(x1), int(y1), shrink

    def _guided(self, kps, desc, pred: Pose) -> FrameRecord:
        """Tracking: match near the predicted projections of the nearby keyframes' points.
        When under half of the matches agree (the prediction was off: stills taken apart,
        a sudden turn), the matches near the prediction miss many of the frame's points
        and hold wrong ones: match again around the pose just found (and its nearest
        keyframes) within a quarter of the radius, and solve again from it."""
        radius = self.s.guided_radius_px * (1 + min(self.lost_run, 3))
        first = self._guided_solve(kps, desc, pred, radius)
        if first is None:
            return FrameRecord(Status.LOST, mode="detect", reason=Reason.FEW_MATCHES)
        est, uv, X, kf, land = first
        if est.success and est.inliers.sum() < 0.5 * len(uv):
            again = self._guided_solve(kps, desc, est.pose, radius / 4)
            if again is not None and again[0].success:
                if again[0].inliers.sum() > est.inliers.sum():
                    est, uv, X, kf, land = again
                    radius /= 4
        res = self._gate(est, len(uv), "detect", True, land, (X, uv), radius_px=radius)
        return self._accept(res, est, uv, X, kf, land)

    def _guided_solve(self, kps, desc, pred: Pose, radius: float):
        """Guided matches within `radius` of where `pred` projects the nearby keyframes'
        points, and the pose from them (None: too few matches)."""
        cands = list(self.model.nearest_keyframes(pred, self.s.local_keyframes))
        X_all, d_all, kf_of, pid_all = self._candidates(cands, self._below(pred, cands))
        Xc = pred.transform(X_all)
        front = Xc[:, 2] > 1e-3
        uvp = self.camera.project(X_all[front], pred)
        qi, ci = guided_match(kps, desc, uvp, d_all[front], pid_all[front], radius, self.s.ratio)
        ci = np.flatnonzero(front)[ci]
        if len(qi) < self.s.min_track_inliers:
            return None
        uv, X = kps[qi].astype(np.float64), X_all[ci]
        kf = int(np.argmax(np.bincount(kf_of[ci], minlength=len(self.model.keyframes))))
        est = solve_pose(
            X,
            uv,
            self.camera,
            reference_pose=pred,
            method=self.s.method,
            ransac=RansacOptions(threshold_px=self.s.ransac_px, seed=self.s.seed),
            refine=RefineOptions(reject_px=self.s.reject_px, huber_px=self.s.huber_px),
        )
        return est, uv, X, kf, self.on_landmark[pid_all[ci]]

    def _relocalise(self, kps, desc) -> FrameRecord:
        """Lost: recognise, match, and accept a pose only when the evidence is unambiguous.
        No pose from the keyframes as they are: again with their squashed views (a camera
        far above them, tilt.py)."""
        res = self._relocalise_with(kps, desc, False)
        if res.status != Status.LOST or not self.model.has_tilted:
            return res  # found, or ambiguous: more matches to one side do not settle that
        again = self._relocalise_with(kps, desc, True)
        return again if again.status in (Status.OK, Status.UNCERTAIN) else res

    def _relocalise_with(self, kps, desc, tilted: bool) -> FrameRecord:
        found = self.model.recognize(desc, top_k=self.s.global_keyframes, tilted=tilted)
        cands = [i for i, _ in found]
        if not cands:
            return FrameRecord(Status.LOST, mode="relocalise", reason=Reason.NOT_RECOGNISED)
        X_all, d_all, kf_of, pid_all = self._candidates(cands, set(cands) if tilted else ())
        # descriptor matching whose ratio test compares distinct 3D points (the same point
        # seen by two candidate keyframes is not a rival); no position prior: radius inf
        anywhere = np.zeros((len(X_all), 2))
        qi, ti = guided_match(kps, desc, anywhere, d_all, pid_all, np.inf, self.s.ratio)
        uv, X = kps[qi].astype(np.float64), X_all[ti]
        # matches to repeated texture or to the ground do not vote
        land = self.on_landmark[pid_all[ti]]
        unique = self.votes[pid_all[ti]]
        lost = FrameRecord(
            Status.LOST, matches=len(qi), mode="relocalise", reason=Reason.FEW_MATCHES
        )
        if unique.sum() < self.s.min_inliers:
            return lost
        kf = int(np.argmax(np.bincount(kf_of[ti[unique]], minlength=len(self.model.keyframes))))
        est = unambiguous_pose(X, uv, unique, self.camera, self.model.keyframes[kf].pose, self.s)
        if isinstance(est, Status):
            lost.status = est
            lost.reason = Reason.AMBIGUOUS if est == Status.AMBIGUOUS else Reason.FEW_INLIERS
            return lost
        res = self._gate(est, len(uv), "relocalise", False, land, (X, uv), unique)
        return self._accept(res, est, uv, X, kf, land)

    def _accept(self, res: FrameRecord, est: PoseEstimate, uv, X, kf: int, land) -> FrameRecord:
        res.keyframe = self.model.keyframes[kf].name
        if res.ok:
            self.keyframe = kf
            self.track_px = uv[est.inliers].astype(np.float32)
            self.track_X = X[est.inliers]
            self.track_land = land[est.inliers]
            res.inlier_px = self.track_px
        return res

    def _candidates(self, cands, tilted=()):
        """(X, descriptors, keyframe, point id) of the candidate keyframes' linked features;
        those in `tilted` add the features of their squashed views (tilt.py)."""
        parts = []
        for k in cands:
            if k not in self._kf_cache:
                kp, d, pid = self.model.keyframes[k].linked()
                self._kf_cache[k] = self._rows(k, d, pid)
            parts.append(self._kf_cache[k])
            t = self.model.keyframes[k].tilted
            if k in tilted and t is not None and len(t[2]):
                if (k, "tilt") not in self._kf_cache:
                    self._kf_cache[k, "tilt"] = self._rows(k, t[1], t[2])
                parts.append(self._kf_cache[k, "tilt"])
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(4))

    def _rows(self, k: int, d: np.ndarray, pid: np.ndarray):
        d = np.ascontiguousarray(d, dtype=self.model.detector.spec.dtype)
        return self.model.points[pid], d, np.full(len(pid), k, np.int32), pid.astype(np.int64)

    def _below(self, pose: Pose, cands) -> set[int]:
        """The candidate keyframes the pose looks down on from `tilt.ABOVE_DEG` higher."""
        if not self.model.has_tilted:
            return set()
        e = elevation_deg(pose.center, self._target)
        return {k for k in cands if e - self._kf_elev[k] >= ABOVE_DEG}

    def _covariances(self, est: PoseEstimate, n: int, points=None):
        return frame_covariances(
            est, n, self.camera, points, self.s.huber_px, self.model_rms_px,
            self.s.model_error_points, self.model_error_scale,
        )  # fmt: skip

    def _significant(
        self, est: PoseEstimate, n: int, mode: str, points, voting, radius_px=None
    ) -> bool:
        """Could the inliers be chance (evidence.py)? Wrong matches fall anywhere within the
        guided radius of their predicted pixel while tracking (flowed points as well: the
        flow searches no further), anywhere in the matched keypoints' box when
        relocalising. Only the matches that could decide the pose count (`voting`:
        matches to repeated texture or the ground are expected to pick the wrong twin)."""
        inl = est.inliers if voting is None else est.inliers & voting
        total = n if voting is None else int(voting.sum())
        if mode == "relocalise" and points is not None:
            uv = points[1] if voting is None else points[1][voting]
            area = search_area(uv)
        else:
            r = radius_px or self.s.guided_radius_px * (1 + min(self.lost_run, 3))
            area = np.pi * r**2
        p = chance_inlier_probability(self.s.ransac_px, area)
        return is_evidence(total, int(inl.sum()), p, RANSAC_HYPOTHESES, self.s.max_false_alarms)

    def _gate(
        self,
        est: PoseEstimate,
        n: int,
        mode: str,
        check_jump: bool,
        on_landmark: np.ndarray | None = None,
        points: tuple[np.ndarray, np.ndarray] | None = None,
        voting: np.ndarray | None = None,
        radius_px: float | None = None,
    ) -> FrameRecord:
        """ok only with enough consistent inliers, enough of them on the landmark itself
        (`on_landmark`, per match; None: all are), a small residual, a plausible motion and
        an uncertainty small enough to trust (else `uncertain`).

        `voting` (per match; None: all) are the matches that could decide the pose: the
        inlier ratio counts among them, since matches to repeated texture or the ground are
        expected to pick the wrong twin (a tiled floor in view is half the matches)."""
        ninl = int(est.inliers.sum()) if est.success else 0
        res = FrameRecord(
            Status.LOST,
            matches=n,
            inliers=ninl,
            iterations=est.iterations,
            rmse_px=est.rmse_px,
            mode=mode,
            reason=Reason.FEW_INLIERS,
        )
        if not est.success:
            return res
        cov_res, cov_model = self._covariances(est, ninl, points)
        res.sigma_pos_m, res.sigma_rot_deg = sigmas(cov_res + cov_model)
        # with a prediction a few points can make an ok pose (their uncertainty decides
        # below); without one, a pose needs the numbers that make RANSAC's answer unique
        need = self.s.min_inliers if mode == "relocalise" else self.s.min_track_inliers
        if ninl < need:
            return res
        if not self._significant(est, n, mode, points, voting, radius_px):
            res.reason = Reason.CHANCE
            return res
        n_land = ninl if on_landmark is None else int((est.inliers & on_landmark).sum())
        if n_land < min(self.s.min_landmark_inliers, need):
            res.reason = Reason.OFF_LANDMARK
            return res  # the ground (or background) alone: the landmark is not in view
        if not est.rmse_px <= self.s.max_rmse_px:
            res.reason = Reason.RESIDUAL
            return res
        if est.pose.transform(np.zeros((1, 3)))[0, 2] <= 0:
            res.reason = Reason.BEHIND
            return res  # the landmark behind the camera
        frames = 1 + self.lost_run  # since the previous ok pose: the limits are per frame
        if (
            check_jump
            and self.prev_pose is not None
            and (
                est.pose.distance_to(self.prev_pose) > self.s.max_jump_m * frames
                or est.pose.angle_to(self.prev_pose) > self.s.max_jump_deg * frames
            )
        ):
            res.reason = Reason.JUMP
            return res
        max_pos = self.s.max_sigma_pos_m
        if points is not None:  # relative to the range: the inliers' median depth
            depth = float(np.median(est.pose.transform(points[0][est.inliers])[:, 2]))
            max_pos = min(max_pos, self.s.max_sigma_range * depth)
        res.measurement = Measurement(
            est.pose, cov_res, cov_model, max_sigma_pos_m=max_pos,
            max_sigma_rot_deg=self.s.max_sigma_rot_deg,
        )  # fmt: skip
        if not (res.sigma_pos_m <= max_pos and res.sigma_rot_deg <= self.s.max_sigma_rot_deg):
            res.status, res.reason = Status.UNCERTAIN, Reason.UNCERTAIN
            self._uncertain_pose = est.pose
            return res
        res.status, res.pose, res.reason = Status.OK, est.pose, ""
        if mode == "flow" and self.keyframe >= 0:
            res.keyframe = self.model.keyframes[self.keyframe].name
        return res


def _to_world(rec: FrameRecord, level: np.ndarray) -> None:
    """A record's poses from the model's levelled frame (X' = level X) to W. The
    covariances are of a perturbation in the camera frame: the same in either."""
    if rec.pose is not None:
        rec.pose = Pose(rec.pose.R @ level, rec.pose.t)
    m = rec.measurement
    if m is not None:
        m.pose = Pose(m.pose.R @ level, m.pose.t)


def run(
    frames: Iterable[Frame], tracker: Tracker, keep_images: bool = False
) -> Iterator[FrameRecord]:
    """Track frames in order: one final record per frame, yielded as soon as it is final.

    The one tracking loop of `mirage track`, the demo and the benchmarks. A generator, so
    that callers write each record as it comes; it reads `tracker.lookahead` frames ahead
    (their features are detected in the background) but never changes a record once
    yielded.
    Undecodable frames are `decode_error`, frames of another size than the camera
    `size_mismatch`. `keep_images` leaves each frame's image on its record (overlays).
    """
    k = tracker.lookahead
    size = tracker.camera.size
    queue: deque = deque()  # (frame, gray or None), the current one first
    # the model (and the tracker) work in W's levelled copy; records leave in W
    level = tracker.model.world_from_model.T
    to_world = None if np.array_equal(level, np.eye(3)) else level

    def step() -> FrameRecord:
        f, gray = queue.popleft()
        t0 = time.perf_counter()
        if f.image is None:
            rec = FrameRecord(Status.DECODE_ERROR)
        elif gray is None:
            rec = FrameRecord(Status.SIZE_MISMATCH)
        else:
            with through_compiled_code():
                rec = tracker.process(gray, [g for _, g in queue])
        rec.frame, rec.time_s = f.id, f.time_s
        if to_world is not None:
            _to_world(rec, to_world)
        rec.ms = round((time.perf_counter() - t0) * 1000, 2)
        if keep_images:
            rec.image = f.image
        return rec

    for f in frames:
        signals.check()  # a signal a compiled-code callback swallowed: the interrupt now
        gray = None
        if f.image is not None:
            gray = to_gray(f.image)
            if gray.shape[::-1] != size:
                gray = None
        queue.append((f, gray))
        if len(queue) > k:
            yield step()
    while queue:
        yield step()
