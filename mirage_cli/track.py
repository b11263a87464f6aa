"""Per-frame camera pose against a landmark model (brief, section 4.3). Pure core.

Each frame is either *detected* (features matched to the model's keyframes, RANSAC,
Mirage-S from the best keyframe's or the previous pose) or *flowed* (the previous frame's
inliers followed with pyramidal Lucas-Kanade, keeping their 3D points, then Mirage-S from
the previous pose). Flow costs a few milliseconds where detection costs tens, so detection
runs only every `redetect_every` frames or when the flow weakens; both end in the same
ok / lost gate, so a frame without enough consistent evidence is `lost`, never a guess.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from .camera import Camera
from .features import detect, make_detector, make_matcher, ratio_match
from .frames import Frame
from .model import LandmarkModel
from .pose import Pose
from .solver import PoseEstimate, RansacOptions, RefineOptions, solve_pose
from .trajectory import FrameRecord, Status


@dataclass
class TrackSettings:
    method: str = "mirage-s"
    redetect_every: int = 5  # frames between full detections while flow holds
    min_inliers: int = 15  # fewer consistent points: lost
    min_inlier_ratio: float = 0.25  # of the matches, at detection
    max_rmse_px: float = 2.0
    ransac_px: float = 3.0
    ratio: float = 0.8
    flow: bool = True
    min_flow_points: int = 30
    flow_fb_px: float = 0.7  # forward-backward consistency of Lucas-Kanade
    flow_max_rmse_px: float = 1.0  # a worse flowed fit (large motion, drift) -> detect
    local_keyframes: int = 4  # keyframes near the previous pose to match against
    global_keyframes: int = 3  # keyframes proposed by recognition when lost
    max_jump_m: float = 0.5  # a pose this far from the previous ok pose (per frame)...
    max_jump_deg: float = 30.0  # ...or turned this much is distrusted (needs detection)
    seed: int = 0


class Tracker:
    """Stateful per-frame tracker; feed frames in order with `process(gray)`."""

    def __init__(self, model: LandmarkModel, camera: Camera, settings: TrackSettings):
        self.model, self.camera, self.s = model, camera, settings
        self.detector = make_detector(model.detector)
        self.prev_gray: np.ndarray | None = None
        self.prev_pose: Pose | None = None
        self.since_detect = 0
        self.lost_run = 0
        self.keyframe = -1
        self.track_px: np.ndarray | None = None  # (N,2) float32 inliers in prev frame
        self.track_X: np.ndarray | None = None  # (N,3) their model points
        self.matcher = make_matcher(model.detector)
        self._kf_cache: dict[int, tuple] = {}

    # ------------------------------------------------------------------------------------
    def process(self, gray: np.ndarray) -> FrameRecord:
        res = None
        if (
            self.s.flow
            and self.prev_pose is not None
            and self.track_px is not None
            and self.since_detect < self.s.redetect_every
        ):
            res = self._flow(gray)
        if res is None or not res.ok:
            res = self._detect(gray)
        self.prev_gray = gray
        if res.ok:
            self.prev_pose = res.pose
            self.lost_run = 0
        else:
            self.lost_run += 1
            self.track_px = self.track_X = None
            if self.lost_run > 3:
                self.prev_pose = None  # too long: recognise globally again
        return res

    # ------------------------------------------------------------------------------------
    def _flow(self, gray: np.ndarray) -> FrameRecord | None:
        p0 = self.track_px.reshape(-1, 1, 2)
        lk = dict(
            winSize=(15, 15),
            maxLevel=3,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        )
        try:
            p1, st, _ = cv2.calcOpticalFlowPyrLK(self.prev_gray, gray, p0, None, **lk)
            p0r, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self.prev_gray, p1, None, **lk)
        except cv2.error:
            return None
        p1, p0r = p1.reshape(-1, 2), p0r.reshape(-1, 2)
        fb = np.linalg.norm(p0r - self.track_px, axis=1)
        h, w = gray.shape[:2]
        good = (
            (st.ravel() == 1) & (st2.ravel() == 1) & (fb < self.s.flow_fb_px)
            & (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        )  # fmt: skip
        if good.sum() < self.s.min_flow_points:
            return None
        X, uv = self.track_X[good], p1[good]
        est = solve_pose(
            X,
            uv,
            self.camera,
            reference_pose=self.prev_pose,
            method=self.s.method,
            refine=RefineOptions(reject_px=self.s.ransac_px),
        )
        res = self._gate(est, len(uv), "flow", check_jump=True)
        if res.ok and est.rmse_px > self.s.flow_max_rmse_px:
            return None  # the flow has drifted or the motion was too large: detect afresh
        if res.ok:
            self.since_detect += 1
            self.track_px, self.track_X = uv[est.inliers].astype(np.float32), X[est.inliers]
            res.inlier_px = self.track_px
        return res

    def _detect(self, gray: np.ndarray) -> FrameRecord:
        self.since_detect = 0
        kps, desc = detect(gray, self.detector)
        if desc is None or len(kps) < self.s.min_inliers:
            return FrameRecord(Status.LOST, mode="detect")
        if self.prev_pose is not None:
            cands = list(self.model.nearest_keyframes(self.prev_pose, self.s.local_keyframes))
        else:
            cands = [i for i, _ in self.model.recognize(desc, top_k=self.s.global_keyframes)]
        if not cands:
            return FrameRecord(Status.LOST, mode="detect")
        best = FrameRecord(Status.LOST, mode="detect")
        # one matching pass against the union of candidate keyframes' 3D-linked features
        X_all, d_all, kf_of = self._candidates(cands)
        qi, ti = ratio_match(desc, d_all, self.s.ratio, self.matcher)
        if len(qi) < self.s.min_inliers:
            best.matches = len(qi)
            return best
        uv, X = kps[qi].astype(np.float64), X_all[ti]
        votes = np.bincount(kf_of[ti], minlength=len(self.model.keyframes))
        kf = int(np.argmax(votes))
        ref = self.prev_pose if self.prev_pose is not None else self.model.keyframes[kf].pose
        est = solve_pose(
            X,
            uv,
            self.camera,
            reference_pose=ref,
            method=self.s.method,
            ransac=RansacOptions(threshold_px=self.s.ransac_px, seed=self.s.seed),
        )
        res = self._gate(est, len(uv), "detect", check_jump=False)
        res.keyframe = self.model.keyframes[kf].name
        if res.ok:
            self.keyframe = kf
            self.track_px = uv[est.inliers].astype(np.float32)
            self.track_X = X[est.inliers]
            res.inlier_px = self.track_px
        return res

    def _candidates(self, cands):
        parts = []
        for k in cands:
            if k not in self._kf_cache:
                kp, d, pid = self.model.keyframes[k].linked()
                self._kf_cache[k] = (self.model.points[pid], d, np.full(len(pid), k, np.int32))
            parts.append(self._kf_cache[k])
        X = np.concatenate([p[0] for p in parts])
        d = np.concatenate([p[1] for p in parts])
        kf = np.concatenate([p[2] for p in parts])
        return X, d, kf

    def _gate(self, est: PoseEstimate, n: int, mode: str, check_jump: bool) -> FrameRecord:
        """ok only with enough consistent inliers, a small residual and a plausible motion."""
        ninl = int(est.inliers.sum()) if est.success else 0
        res = FrameRecord(
            Status.LOST,
            matches=n,
            inliers=ninl,
            iterations=est.iterations,
            rmse_px=est.rmse_px,
            mode=mode,
        )
        if not est.success:
            return res
        res.sigma_pos_m, res.sigma_rot_deg = est.sigma_pos_m, est.sigma_rot_deg
        if ninl < self.s.min_inliers or ninl < self.s.min_inlier_ratio * n:
            return res
        if not est.rmse_px <= self.s.max_rmse_px:
            return res
        if est.pose.transform(np.zeros((1, 3)))[0, 2] <= 0:
            return res  # the landmark behind the camera
        if (
            check_jump
            and self.prev_pose is not None
            and (
                est.pose.distance_to(self.prev_pose) > self.s.max_jump_m
                or est.pose.angle_to(self.prev_pose) > self.s.max_jump_deg
            )
        ):
            return res
        res.status, res.pose = Status.OK, est.pose
        if mode == "flow" and self.keyframe >= 0:
            res.keyframe = self.model.keyframes[self.keyframe].name
        return res


def run(
    frames: Iterable[Frame], tracker: Tracker, keep_images: bool = False
) -> Iterator[FrameRecord]:
    """Track frames in order: one final record per frame, yielded as soon as it is final.

    The one tracking loop of `mirage track`, the demo and the benchmarks. A generator, so
    that callers write each record as it comes; it may hold a few frames back (to confirm
    a pose with the frames after it) but never changes a record once yielded.
    Undecodable frames are `decode_error`, frames of another size than the camera
    `size_mismatch`. `keep_images` leaves each frame's image on its record (overlays).
    """
    for f in frames:
        t0 = time.perf_counter()
        if f.image is None:
            rec = FrameRecord(Status.DECODE_ERROR)
        else:
            gray = cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY) if f.image.ndim == 3 else f.image
            if gray.shape[::-1] != tracker.camera.size:
                rec = FrameRecord(Status.SIZE_MISMATCH)
            else:
                rec = tracker.process(gray)
        rec.frame, rec.time_s = f.id, f.time_s
        rec.ms = round((time.perf_counter() - t0) * 1000, 2)
        if keep_images:
            rec.image = f.image
        yield rec
