"""Where to look while tracking: the pixel box where the predicted pose puts the model (and
how much to shrink or upsample it), and guided matching of the nearby keyframes' points
near their predicted pixels. A mixin of `Tracker`."""

from __future__ import annotations

import numpy as np

from ..features import guided_match
from ..pose import Pose
from ..records import FrameRecord, Reason
from ..solver import solve_pose
from ..tilt import ABOVE_DEG, elevation_deg

# a shrunk box keeps this much more resolution than the keyframes' (sub-pixel keypoints):
# 720p / 1080p orbits against the sample's model, p95 2.52 / 2.62 mm shrunk to the keyframes'
# scale, 1.98 / 2.40 mm with this margin (2.22 / 2.99 unshrunk)
SHRINK_MARGIN = 1.25


def _median_depth(pose: Pose, points: np.ndarray) -> float:
    """Median depth of the points seen from `pose` (0 without any)."""
    return float(np.median(pose.transform(points)[:, 2])) if len(points) else 0.0


class GuidedSearch:
    """Search boxes and guided matching while tracking (a mixin of Tracker)."""

    def _model_box(self, pred: Pose, shape) -> tuple[int, int, int, int, float] | None:
        """Pixel box (x0, y0, x1, y1) around the model's points as the predicted pose sees
        them, with a margin: nothing outside it can match; and the factor to shrink it by
        before detection (`shrink_above`; 1: none). None when it would cover most of the
        frame anyway (or too few points are predicted in front), so the whole frame is
        searched."""
        if self.settings.detect_margin_px < 0 or self._model_X is None:
            return None
        X = self._model_X
        front = pred.transform(X)[:, 2] > 1e-3
        if front.sum() < self.settings.min_inliers:
            return None
        uv = self.camera.project(X[front], pred)
        if not np.isfinite(uv).all():  # points far off-axis: the distortion has no image
            return None  # (what the NaN box came to before, without numpy's warning)
        h, w = shape[:2]
        m = self.settings.detect_margin_px
        lo, hi = np.percentile(uv, [1, 99], axis=0)  # one partition for both
        x0, y0 = np.floor(lo - m).astype(int)
        x1, y1 = np.ceil(hi + m).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 - x0 < 32 or y1 - y0 < 32 or (x1 - x0) * (y1 - y0) > 0.7 * w * h:
            return None
        larger = self._view_scale(pred)
        shrink = round(larger / SHRINK_MARGIN, 2) if larger >= self.settings.shrink_above else 1.0
        return int(x0), int(y0), int(x1), int(y1), shrink

    def _view_scale(self, pose: Pose) -> float:
        """How many times larger a frame taken from `pose` shows the landmark than its
        nearest keyframe did: that keyframe's points, then and now, and the focal lengths
        (a model from one camera may track another's video). 1 when it cannot tell. Both
        the detection box's shrink and the patch floor (`PoseGate._shrunk_view`) ask."""
        kf = self.model.nearest_keyframes(pose, 1) if len(self._kf_depth) else []
        if not kf:
            return 1.0
        depth = _median_depth(pose, self._kf_points[kf[0]])
        return self._focal_ratio * self._kf_depth[kf[0]] / depth if depth > 0 else 1.0

    def _guided(self, kps, desc, pred: Pose, radius: float | None = None) -> FrameRecord:
        """Tracking: match near the predicted projections of the nearby keyframes' points.
        When under half of the matches agree (the prediction was off: stills taken apart,
        a sudden turn), the matches near the prediction miss many of the frame's points
        and hold wrong ones: match again around the pose just found (and its nearest
        keyframes) within a quarter of the radius, and solve again from it. The ratio test
        of that second match still looks over the whole radius (`guided_match`'s
        `keep_px`): the pose it starts from may be the wrong one."""
        if radius is None:  # the prediction's reach: wider the longer it is out of date
            radius = self.settings.guided_radius_px * (1 + min(self.lost_run, 3))
        first = self._guided_solve(kps, desc, pred, radius)
        if first is None:
            return self._patches_alone(pred, radius)
        est, uv, X, kf, land, _ = first
        if est.success and est.inliers.sum() < 0.5 * len(uv):
            again = self._guided_solve(kps, desc, est.pose, radius, keep_px=radius / 4)
            if again is not None and again[0].success:
                if again[0].inliers.sum() > est.inliers.sum():
                    est, uv, X, kf, land, _ = again
                    radius /= 4
        dispute = None
        if est.success and self._patch_ok(est.pose):
            got = self._patch_solve(est.pose)
            if got is not None:
                better, dispute = self._patch_verdict(est, (X, uv), got)
                if better:
                    est, uv, X, kf, land = got
                    self._patched = True
        res = self._gate(
            est, len(uv), "detect", True, land, (X, uv), radius_px=radius, dispute=dispute
        )
        if not res.ok and not self._patched and res.reason != Reason.AMBIGUOUS:
            # the keypoints' pose, a few inliers on a foreshortened face, may be far off
            # the prediction, where the patches can place nothing: from the prediction
            held = self._uncertain_pose
            alone = self._patches_alone(pred, radius)
            if alone.ok:
                return alone
            self._uncertain_pose, self._patched = held, False
        return self._accept(res, est, uv, X, kf, land)

    def _guided_solve(self, kps, desc, pred: Pose, radius: float, keep_px: float | None = None):
        """Guided matches within `radius` of where `pred` projects the nearby keyframes'
        points (within `keep_px`, when given, with the ratio test over `radius`), and the
        pose from them: (estimate, uv, X, keyframe, on-landmark, may vote) per match (None:
        too few matches)."""
        cands = list(self.model.nearest_keyframes(pred, self.settings.local_keyframes))
        X_all, d_all, kf_of, pid_all = self._candidates(cands, self._below(pred, cands))
        Xc = pred.transform(X_all)
        front = Xc[:, 2] > 1e-3
        uvp = self.camera.project(X_all[front], pred)
        qi, ci = guided_match(
            kps, desc, uvp, d_all[front], pid_all[front], radius, self.settings.ratio, keep_px
        )
        ci = np.flatnonzero(front)[ci]
        if len(qi) < self.settings.min_track_inliers:
            return None
        uv, X = kps[qi].astype(np.float64), X_all[ci]
        kf = int(np.argmax(np.bincount(kf_of[ci], minlength=len(self.model.keyframes))))
        est = solve_pose(
            X,
            uv,
            self.camera,
            reference_pose=pred,
            method=self.settings.method,
            ransac=self.settings.ransac,
            refine=self.settings.refine,
        )
        pid = pid_all[ci]
        return est, uv, X, kf, self.on_landmark[pid], self.votes[pid]

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
        """The candidate keyframes whose squashed views to match: those the pose looks
        down on (`_looked_down_on`), when the model has them."""
        return self._looked_down_on(pose, cands) if self._has_tilted else set()

    def _looked_down_on(self, pose: Pose, cands) -> set[int]:
        """The candidate keyframes the pose looks down on from `tilt.ABOVE_DEG` higher."""
        e = elevation_deg(pose.center, self._target)
        return {k for k in cands if e - self._kf_elev[k] >= ABOVE_DEG}
