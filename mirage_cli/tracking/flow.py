"""Frame-to-frame tracking: the last detection's inliers followed with pyramidal
Lucas-Kanade from the frame they were detected in (the anchor), then Mirage-S from the
previous pose. A mixin of `Tracker`: it reads the tracker's prediction and gate, and keeps
the anchor's state (`anchor_gray`, `anchor_px`, `anchor_n`, `_anchor_level`) and the points
followed (`track_px`, `track_X`, `track_land`), and keeps following them through a
regular detection that finds nothing against them."""

from __future__ import annotations

import cv2
import numpy as np

from ..pose import Pose
from ..records import Cause, FrameRecord, Reason
from ..solver import sigmas, solve_pose


def _local_means(gray: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Mean of the 7x7 pixels around each point (nearest pixel; 0 outside the image)."""
    h, w = gray.shape[:2]
    ij = np.rint(px).astype(np.int64)
    inside = (ij[:, 0] >= 3) & (ij[:, 0] < w - 3) & (ij[:, 1] >= 3) & (ij[:, 1] < h - 3)
    out = np.zeros(len(px))
    if inside.any():  # the 49 pixels of each point gathered (not a blur of their whole box)
        ii = ij[inside]
        xs = ii[:, 0, None] + _OFFSETS[None, :, 0]
        ys = ii[:, 1, None] + _OFFSETS[None, :, 1]
        out[inside] = gray[ys, xs].mean(axis=1)
    return out


_OFFSETS = np.stack(np.meshgrid(np.arange(-3, 4), np.arange(-3, 4)), axis=-1).reshape(-1, 2)


def _deviation(res: FrameRecord, pred: Pose) -> float:
    """How far a pose is from its prediction, in the position sigmas of its residuals."""
    return res.pose.distance_to(pred) / max(sigmas(res.measurement.cov)[0], 1e-9)


class FlowTracking:
    """Optical flow between detections (a mixin of Tracker)."""

    def _flow(self, gray: np.ndarray) -> FrameRecord | None:
        a0 = self.anchor_px.reshape(-1, 1, 2)
        lk = dict(
            winSize=(self.settings.flow_window_px, self.settings.flow_window_px),
            maxLevel=self.settings.flow_levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        # start each point where the predicted pose puts it (large motions stay within the
        # small window's reach), or where it was in the previous frame
        pred = self._predicted()
        guess = self.track_px
        if self.velocity is not None and np.all(pred.transform(self.track_X)[:, 2] > 1e-3):
            guess = self.camera.project(self.track_X, pred).astype(np.float32)
        self.flow_refusal = Cause.FLOW_FAILED
        tracked = self._lucas_kanade(gray, a0, guess, lk)
        if tracked is None:
            return None
        # Lucas-Kanade assumes constant brightness: when the exposure changed since the
        # anchor (auto-exposure; measured where the points flowed), flow again in the
        # frame scaled to the anchor's brightness (the first pass's points are biased)
        gain = self._gain(gray, *tracked)
        if abs(gain - 1) > self.settings.flow_gain_tol:
            gray = cv2.convertScaleAbs(gray, alpha=gain)
            tracked = self._lucas_kanade(gray, a0, guess, lk)
            if tracked is None:
                return None
        p1, good = tracked
        # the flow has weakened: detect afresh. A detection with few points (a small view
        # from above: 20-29 inliers) was trusted with them, so its flow needs most of them
        # (`flow_keep_few`), not more than it had
        n, s = self.anchor_n, self.settings
        need = max(min(s.min_flow_points, s.flow_keep_few * n), s.flow_keep * n)
        shifted = False  # (a turn the prediction missed: `_shifted_flow`)
        if good.sum() < need and s.flow_shift_retry and self.px_scale > 1:
            again = self._shifted_flow(gray, a0, guess, lk)
            if again is not None and again[1].sum() >= need:
                (p1, good), shifted = again, True
        if good.sum() < need:
            self.flow_refusal = Cause.FLOW_WEAK
            return None
        X, uv = self.track_X[good], p1[good]
        est = solve_pose(
            X,
            uv,
            self.camera,
            reference_pose=self.prev_pose,
            method=self.settings.method,
            refine=self.settings.refine,
        )
        land = self.track_land[good]
        res = self._gate(est, len(uv), "flow", True, land, (X, uv))
        # the flow has drifted or the motion was too large: detect afresh. Drift is a fit
        # worse than the anchor's own: from 50 deg above, detections fit at 0.8-0.9 px
        # (foreshortened keypoints and model points) and their flows at 1.0-1.2 px
        limit = max(s.flow_max_rmse_px, s.flow_rmse_growth * self.anchor_rmse)
        self.flow_refusal = Cause.FLOW_REFUSED  # unless the checks below say more
        if res.ok and est.rmse_px > limit:
            self.flow_refusal = Cause.FLOW_DRIFT
            return None
        if res.ok and self.velocity is not None and not shifted:
            # points that slid along an edge bend the pose while the residuals stay small;
            # a smooth path predicts the pose well, so a flowed pose far from the
            # prediction (in the sigmas of its residuals) is checked by a detection. Not
            # after a measured shift: the images showed the prediction wrong (1080p
            # look-away: such flows 0.2-1.8 mm off, 4.4-12.4 sigma from a prediction
            # 4.7-10.1 mm off)
            if _deviation(res, pred) > self.settings.flow_max_dev_sigma:
                self.flow_refusal = Cause.FLOW_DEVIATION
                return None
        if res.ok:
            self.since_detect += 1
            self.track_px, self.track_X = uv[est.inliers].astype(np.float32), X[est.inliers]
            self.track_land = land[est.inliers]
            self.anchor_px = self.anchor_px[good][est.inliers]
            self._anchor_level = self._anchor_level[good][est.inliers]
            res.inlier_px = self.track_px
        return res

    def _regular_detection(self, gray: np.ndarray) -> FrameRecord:
        """The detection the schedule asked for while the flow still held. When it finds
        nothing that contradicts the flow, the flow keeps the frame: a view that the
        keyframes match poorly (from 50 deg above the sample's keyframes: 12-13 inliers
        where the flow follows 23 of 25 points) is no reason to drop points that still
        follow the landmark, and losing them cost 40 frames of relocalisation. A detection
        that found two places (`ambiguous`) or a pose of its own away from the flowed one
        does contradict it: the flow may follow a look-alike side (tuning seed above 7:
        146 wrong poses when the flow was kept through its ambiguous detections), so the
        frame is the detection's. The next regular detection tries again."""
        refreshed = self._patch_refresh()
        if refreshed is not None:
            return refreshed
        scale = self.px_scale
        res = self._detect(gray)
        found = self._uncertain_pose  # the detection's own pose, if it was uncertain
        if res.ok or res.reason == Reason.AMBIGUOUS:
            return res
        self._at_scale(scale)  # the flowed points keep their detection's pixel limits
        flowed = self._flow(gray)
        self._uncertain_pose = found
        if (
            flowed is None
            or not flowed.ok
            or (found is not None and self.settings.distinct(found, flowed.pose))
        ):
            return res
        # the points are followed from this frame on, nearer the views to come than the
        # anchor's; they keep its errors, so its number (the smoother's anchor) stays
        self.anchor_gray, self.anchor_px = gray, self.track_px.copy()
        self.anchor_n, self._anchor_level = len(self.anchor_px), None
        return flowed

    def _lucas_kanade(self, gray, a0, guess, lk) -> tuple[np.ndarray, np.ndarray] | None:
        """The anchor's points in `gray` (N,2) and which of them flowed well (both ways).

        Lucas-Kanade's cost is its image pyramids and gradients, over the whole image
        passed: both images are cut to where the points are (and the search's reach), and
        when the features were detected on an image shrunk 2x or more (`px_scale`, a video
        much sharper than the keyframes) the flow runs on the pyramid level that matches
        it: a 4K frame against a 640x480 model (shrunk ~3.6x) flows on a half-size cut, as
        precise as the features it follows; the 1080p orbit's boxes (~1.8x) flow at full
        size."""
        cut = self._flow_images(gray, (self.anchor_px, guess), lk)
        if cut is None:
            return None
        A, B, off, f = cut
        a = (a0 - off) / np.float32(f)
        try:  # from the anchor image: the error does not add up from frame to frame
            p1, st, _ = cv2.calcOpticalFlowPyrLK(
                A, B, a, ((guess - off) / np.float32(f)).reshape(-1, 1, 2), **lk
            )
            p0r, st2, _ = cv2.calcOpticalFlowPyrLK(B, A, p1, a.copy(), **lk)
        except cv2.error:
            return None
        # the forward-backward check in the flowed image's pixels; the points in the frame's
        fb = np.linalg.norm(p0r.reshape(-1, 2) - a.reshape(-1, 2), axis=1)
        p1 = p1.reshape(-1, 2) * np.float32(f) + off
        h, w = gray.shape[:2]
        good = (
            (st.ravel() == 1) & (st2.ravel() == 1) & (fb < self.settings.flow_fb_px)
            & (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        )  # fmt: skip
        return p1, good

    def _flow_images(self, gray, points, lk) -> tuple | None:
        """(anchor, frame, offset, f): both images cut to `points` with the flow's reach
        (`_flow_region`) and shrunk by f (a power of 2) to the features' scale."""
        levels = int(np.floor(np.log2(max(self.px_scale, 1.0)) + 1e-9))
        f = 2**levels
        cut = _flow_region(gray.shape, points, lk, f)
        if cut is None:
            return None
        (x0, y0, x1, y1), off = cut, np.float32(cut[:2])
        A, B = self.anchor_gray[y0:y1, x0:x1], gray[y0:y1, x0:x1]
        for _ in range(levels):
            A, B = cv2.pyrDown(A), cv2.pyrDown(B)
        return A, B, off, f

    def _shifted_flow(self, gray, a0, guess, lk) -> tuple[np.ndarray, np.ndarray] | None:
        """`_lucas_kanade` from the guess moved by the image shift most points agree on
        (within 2 px of their median), measured by a coarse pass (3 levels more, a 15 px
        window). When the camera starts or stops turning the constant-velocity prediction
        misses by a shift, not a warp (the 1080p orbit's look-away: 18-58 px, the same
        within 1 px over the points, where the flow's window reaches ~15; measured within
        0.3 px of the truth's). Only for a video sharper than the features (`px_scale` > 1):
        there the flow follows the points more finely than they were detected, and the
        shifted flows are more precise than detections (1080p p95 2.65 -> 2.38 mm); at the
        features' own scale they were coarser (stress scenes, median: floor tiles 1.3 ->
        1.8 mm, far 2.5 m 4.8 -> 5.2; far 4 m + tiles: flows 80-100 mm off where the
        detections were 12-13)."""
        coarse = dict(winSize=(15, 15), maxLevel=3,
                      criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.03),
                      flags=cv2.OPTFLOW_USE_INITIAL_FLOW)  # fmt: skip
        cut = self._flow_images(gray, (self.anchor_px, guess), coarse)
        if cut is None:
            return None
        A, B, off, f = cut
        a, g = (a0 - off) / np.float32(f), ((guess - off) / np.float32(f)).reshape(-1, 1, 2)
        try:
            p1, st, _ = cv2.calcOpticalFlowPyrLK(A, B, a, g, **coarse)
        except cv2.error:
            return None
        d = (p1.reshape(-1, 2) * np.float32(f) + off - guess)[st.ravel() == 1]
        if len(d) < 10:
            return None
        m = np.median(d, axis=0)
        agree = np.linalg.norm(d - m, axis=1) < 2.0 * self.px_scale
        if agree.sum() < max(10, 0.3 * len(guess)):
            return None
        if np.linalg.norm(m) < self.settings.flow_window_px * self.px_scale:
            return None  # within the flow's own reach: the shift is not what lost the points
        return self._lucas_kanade(gray, a0, (guess + m).astype(np.float32), lk)

    def _gain(self, gray: np.ndarray, p1: np.ndarray, good: np.ndarray) -> float:
        """The anchor's brightness over this frame's at the well-flowed points: the median
        ratio of their 7x7 means, the same surface in both (1 with too few points)."""
        if self._anchor_level is None:
            self._anchor_level = _local_means(self.anchor_gray, self.anchor_px)
        then, now = self._anchor_level[good], _local_means(gray, p1[good])
        ok = (now > 8) & (then > 8)  # dark points say little about the gain
        return float(np.median(then[ok] / now[ok])) if ok.sum() >= 10 else 1.0


def _flow_region(shape, points, lk, f: int) -> tuple[int, int, int, int] | None:
    """The box (x0, y0, x1, y1) both images are cut to before Lucas-Kanade: every point
    (anchor and guess) with the search's reach around it (the window at each pyramid
    level), its corner on the pyramid's grid so that the cut's pyramid is the frame's."""
    h, w = shape[:2]
    pts = np.vstack(points)
    if not np.isfinite(pts).all():
        return None
    grid = f * 2 ** lk["maxLevel"]
    reach = 2 * (lk["winSize"][0] + 2) * grid
    x0, y0 = (np.maximum(np.floor(pts.min(axis=0) - reach), 0) // grid * grid).astype(int)
    x1, y1 = np.minimum(np.ceil(pts.max(axis=0) + reach) + 1, (w, h)).astype(int)
    if x1 - x0 < 2 * grid or y1 - y0 < 2 * grid:
        return None
    return int(x0), int(y0), int(x1), int(y1)
