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

import time
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future

import numpy as np

from .. import signals
from ..camera import Camera
from ..features import guided_match, make_detector, to_gray
from ..frames import Frame
from ..model import LandmarkModel, periodic_floor
from ..pose import Pose
from ..records import Cause, FrameRecord, Reason, Status
from ..signals import through_compiled_code
from ..solver import PoseEstimate
from ..solver import warm_up as _warm_up_solver
from ..tilt import elevation_deg
from .flow import FlowTracking, _deviation
from .gating import PoseGate
from .patching import PatchPlacement
from .relocalise import Polish, Relocalisation
from .schedule import DetectionSchedule
from .search import SHRINK_MARGIN, GuidedSearch, _median_depth
from .settings import TrackSettings

# a camera coarser than the model's (the same landmark in fewer pixels) is detected
# upsampled towards the keyframes' scale, by at most this factor
SEARCH_UPSAMPLE_MAX = 3.0


def detection_scales(focal_ratio: float, settings: TrackSettings) -> tuple[float, float]:
    """The scales (shrink factors: below 1, upsampled) a tracked frame's whole frame and a
    lost frame's search are detected at, for a video whose focal length is `focal_ratio`
    times the model's. Sharper by `shrink_above` or more: a tracked frame at the keyframes'
    scale with the boxes' SHRINK_MARGIN, and a lost frame, which only has to find the
    landmark, at the keyframes' own (1/1.56 of the pixels). Coarser by as much (a model from
    a phone's photos, a 240p drone feed): both upsampled to the keyframes' scale, boxes too,
    so that the finest features the keyframes hold exist in the frame (dtu_scan37's stills
    shrunk 3x: 50 -> 94% tracked, `benchmarks/real.py`). Else the frame's own."""
    if focal_ratio >= settings.shrink_above:
        return round(focal_ratio / SHRINK_MARGIN, 2), round(focal_ratio, 2)
    if focal_ratio <= 1 / settings.shrink_above:
        up = round(max(focal_ratio, 1 / SEARCH_UPSAMPLE_MAX), 2)
        return up, up
    return 1.0, 1.0


def warm_up() -> None:
    """Compile (or load from the cache) the solver's and guided matching's kernels, so that
    `mirage track` does it before its clock starts instead of in the first frames."""
    _warm_up_solver()
    d = np.arange(256, dtype=np.float32).reshape(2, 128)  # integers: the compiled path
    px = np.zeros((2, 2), np.float32)
    guided_match(px, d, px, d, np.arange(2), 10.0)


class Tracker(
    FlowTracking,
    DetectionSchedule,
    GuidedSearch,
    PatchPlacement,
    Relocalisation,
    Polish,
    PoseGate,
):
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
        self.model, self.camera, self.settings = model, camera, settings
        self.base_settings = settings  # `settings` is it at the current features' scale
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
        self.anchor_rmse = 0.0  # their detection's reprojection RMS (px)
        self.flow_refusal = Cause.FLOW_FAILED  # why the last flow gave no pose (records' cause)
        self._anchor_level: np.ndarray | None = None  # their 7x7 means (flow's gain check)
        self._kf_cache: dict[int, tuple] = {}
        self.twins = model.twins()  # the model's tables: stored in its file, or built now
        model.prepare_recognition()
        self.on_landmark = ~model.ground()
        # may decide a relocalisation: no twin, no ground, nothing on a repeating floor
        self.votes = ~self.twins & self.on_landmark & ~periodic_floor(model.points, self.twins)
        self._frame_no = -1  # frames processed, for the smoother's anchors
        self._anchor_no = -1  # the frame whose detection the flowed points come from
        self.hint: Pose | None = None  # the previous frame's uncertain pose (where to look)
        # the hint goes back to a relocalisation that was only `uncertain` in a lost
        # stretch where another relocalisation found two places: what is found around it
        # must be confirmed (`_confirm`)
        self._unconfirmed = False
        self._ambiguity_seen = False  # since the last ok pose
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
        self.full_scale, self.search_scale = detection_scales(self._focal_ratio, settings)
        self.px_scale = 1.0  # the current features' pixel size, in this frame's pixels
        # how high each keyframe looks at the landmark (when to match its squashed views)
        land = P[self.on_landmark] if self.on_landmark.any() else P
        self._target = land.mean(axis=0) if len(land) else np.zeros(3)
        self._kf_elev = np.array([elevation_deg(kf.pose.center, self._target) for kf in kfs])
        self._has_tilted = model.has_tilted  # once: every detection asks
        self._init_patches(model)  # placing points by their keyframe patches (patching.py)
        err = model.reprojection_errors()
        self.model_rms_px = float(np.sqrt(np.mean(err**2))) if err.size else 0.0
        self.model_error_scale = float(model.meta.get("check", {}).get("error_scale", 1.0))

    @property
    def lookahead(self) -> int:
        """Frames `process` wants to see ahead of the current one (`ahead`)."""
        return (
            self.settings.redetect_every + 1
            if self.settings.flow and self.settings.detect_ahead
            else 0
        )

    def process(self, gray: np.ndarray, ahead: Sequence[np.ndarray | None] = ()) -> FrameRecord:
        """The record of this frame; `ahead` holds the next frames' gray images (None where
        undecodable), up to `lookahead` of them, for the next detection's features."""
        res = None
        self._uncertain_pose = None
        self._frame_no += 1
        self._gray, self._small_box = gray, False
        self._gray_levels = [gray]  # its pyramid, as far as the patches asked
        chained = self._from_unconfirmed()
        self._pending = {k: f for k, f in self._pending.items() if k[0] >= self._frame_no}
        if self.lost_run > 0 and (self.prev_pose is not None or self.hint is None):
            self._search_ahead(ahead)  # lost (the first frame is expected to find it)
        can_flow = self.settings.flow and self.prev_pose is not None and self.track_px is not None
        due = can_flow and self.since_detect >= self.settings.redetect_every
        cause = Cause.SCHEDULED if due else Cause.LOST if self.settings.flow else Cause.NO_FLOW
        if can_flow and not due:
            res = self._flow(gray)
            cause = self.flow_refusal
        if res is None or not res.ok:
            res = self._detect(gray) if not due else self._regular_detection(gray)
            if res.mode != "flow":  # (a regular detection may keep the flow)
                res.cause = cause
            if res.ok and res.mode != "flow":
                self.anchor_gray, self.anchor_px = gray, self.track_px.copy()
                self.anchor_n = len(self.anchor_px)
                self._anchor_patched = self._patched
                self.anchor_rmse = res.rmse_px
                self._anchor_level = None
                self._anchor_no = self._frame_no
        if res.measurement is not None:  # flowed points share their anchor's errors
            res.measurement.anchor = self._anchor_no if res.mode == "flow" else self._frame_no
        if res.ok:
            # a detection near its prediction: the next frame's flow check will not doubt it
            calm = (
                res.mode != "flow" and self.velocity is not None and self.lost_run == 0
                and _deviation(res, self._predicted()) < self.settings.flow_max_dev_sigma - 2
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
        if res.ok:
            self._ambiguity_seen = False
        elif res.reason == Reason.AMBIGUOUS:
            self._ambiguity_seen = True
        self._unconfirmed = (
            self.hint is not None and self._ambiguity_seen
            and (res.mode == "relocalise" or chained)
        )  # fmt: skip
        return res

    def _at_scale(self, f: float) -> None:
        """Features detected on an image shrunk by `f`: the pixel limits follow (until the
        next detection: flowed points keep their detection's). Upsampled features keep the
        frame's own limits, as an upsampled box's do."""
        f = max(1.0, f)
        if f != self.px_scale:
            self.px_scale, self.settings = f, self.base_settings.at_scale(f)

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

    def _detect(self, gray: np.ndarray) -> FrameRecord:
        self.since_detect = 0
        self._patched = False
        pred = self._predicted()
        box = self._model_box(pred, gray.shape) if pred is not None else None
        early = self._pending.pop((self._frame_no, "box"), None) if pred is not None else None
        if early is not None and box is not None and not _covers(early.box, box):
            early = None  # detected where the model was predicted to be, not where it is
        if early is None and box is not None:  # searched ahead in this box, while lost?
            early = self._pending.pop((self._frame_no, "lostbox"), None)
            early = early if early is not None and early.box == box else None
        if early is not None or box is not None:  # tracking: where the model is predicted
            used = early.box if early is not None else box  # (None: the whole frame)
            if early is not None:
                kps, desc = early.result()
            else:
                kps, desc = self._box_features(gray, box, self.detector)
            self._at_scale(max(1.0, used[4]) if used else self.full_scale)
            self._small_box = self._upsamples(used)
            if len(kps) >= self.settings.min_track_inliers:
                res = self._confirm(self._guided(kps, desc, pred), gray)
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
        kps, desc = self._whole_frame(gray)
        if desc is None or len(kps) < self.settings.min_inliers:
            return FrameRecord(Status.LOST, mode="detect", reason=Reason.FEW_FEATURES)
        if pred is not None and box is None:
            res = self._confirm(self._guided(kps, desc, pred), gray, (kps, desc))
            if res.ok or res.status == Status.UNCERTAIN:  # as above
                return res
        return self._relocalise(kps, desc, gray)  # also when the prediction was too far off

    def _accept(self, res: FrameRecord, est: PoseEstimate, uv, X, kf: int, land) -> FrameRecord:
        res.keyframe = self.model.keyframes[kf].name
        if res.ok:
            self.keyframe = kf
            self.track_px = uv[est.inliers].astype(np.float32)
            self.track_X = X[est.inliers]
            self.track_land = land[est.inliers]
            res.inlier_px = self.track_px
        return res


def _covers(outer, inner, share: float = 0.9) -> bool:
    """Whether the pixel box `outer` (None: the whole frame) holds `share` of `inner`."""
    if outer is None:
        return True
    w = min(outer[2], inner[2]) - max(outer[0], inner[0])
    h = min(outer[3], inner[3]) - max(outer[1], inner[1])
    area = (inner[2] - inner[0]) * (inner[3] - inner[1])
    return w > 0 and h > 0 and w * h >= share * area


def _to_world(rec: FrameRecord, level: np.ndarray) -> None:
    """A record's poses from the model's levelled frame (X' = level X) to W. The
    covariances are of a perturbation in the camera frame: the same in either."""
    if rec.pose is not None:
        rec.pose = Pose(rec.pose.R @ level, rec.pose.t)
    m = rec.measurement
    if m is not None:
        m.pose = Pose(m.pose.R @ level, m.pose.t)


def track_frames(
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
        if keep_images:  # the colour the gray came from, when the source kept it
            rec.image = f.colour if f.colour is not None else f.image
        return rec

    try:
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
    finally:
        tracker.cancel_pending()  # interrupted or closed early: no detections left queued
