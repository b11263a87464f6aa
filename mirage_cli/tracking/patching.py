"""Model points placed by their keyframe patches while tracking (patches.py holds the pure
image core): when the keypoints are weak (a small, far view's upsampled box; a view from
well above the keyframes), the pose is measured again by warping the nearby keyframes'
images into the frame around their points. A mixin of `Tracker`."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from ..patches import affine_maps, correlate, keyframe_pyramid, point_normals, templates
from ..pose import Pose, rotvec
from ..records import FrameRecord, Reason, Status
from ..solver import sigmas, solve_pose
from .smooth import world_covariance

PYRAMIDS_KEPT = 12  # keyframe image pyramids kept for patches


def pose_gap(a: Pose, b: Pose) -> np.ndarray:
    """(w, v) with b = exp([w, v]) a to first order: the solver's left perturbation of
    T_CW in the camera frame, the parametrisation of its covariances."""
    dR = b.R @ a.R.T
    return np.concatenate([rotvec(dR), b.t - dR @ a.t])


def disputed(a: Pose, b: Pose, cov: np.ndarray, limit: float) -> np.ndarray | None:
    """The covariance a must also cover when b, another measurement of the same frame,
    puts the camera more than `limit` sigma from it (`cov`: the solver's (w, v) at a; its
    centre's part in W decides): the outer product of the gap. None when within."""
    C = world_covariance(cov, a)[3:, 3:]
    dc = b.center - a.center
    try:
        far = float(dc @ np.linalg.solve(C, dc)) > limit**2
    except np.linalg.LinAlgError:
        return None
    if not far:
        return None
    gap = pose_gap(a, b)
    return np.outer(gap, gap)


class PatchPlacement:
    """Keyframe patches while tracking (a mixin of Tracker)."""

    def _init_patches(self, model) -> None:
        """The patches' state: the keyframe images (index -> grey image, when the model
        holds them), their pyramids once made, the model points' face normals when first
        asked, and this frame's pyramid as far as asked."""
        kfs = model.keyframes
        self._kf_image = (lambda k: kfs[k].gray_image()) if model.has_images else None
        self._pyramids: dict = {}
        # an extended model's added frames (extend.py) lend no patches: a template is cut
        # where the keyframe's pose projects its point, and their poses err (far tuning
        # seed 17: frames 1% off as keyframes, frames tracked again 3.6% off at 0.8% sigma)
        self._patch_kfs = int(model.meta.get("extended", {}).get("keyframes", len(kfs)))
        self._added_kfs = len(kfs) - self._patch_kfs
        self._normals: np.ndarray | None = None
        self._gray_levels: list[np.ndarray] = []
        self._gray: np.ndarray | None = None
        self._small_box = False  # this detection's box was upsampled (a small, far view)
        # the points were placed by their patches: this detection's, the flow's anchor's
        self._patched = self._anchor_patched = False

    def _patches_alone(self, pred: Pose, radius: float) -> FrameRecord:
        """The keypoints gave no pose the gate takes: the patches alone, where patches are
        used, from the prediction (within their reach of a tracked frame's; a lost frame's,
        the last pose without velocity, from the frame's quarter size down). From 50 deg
        above (above tuning seed 8) the keypoints matched nothing for 40 frames that the
        patches place 300-450 points in."""
        got = None
        if self._patch_ok(pred):
            # within reach of a tracked frame's prediction; else (lost: the last pose, no
            # velocity) from the frame's quarter size down
            got = self._patch_solve(pred) if self.lost_run == 0 else None
            if got is None:
                got = self._patch_search(pred, self.settings.patch_coarse_level)
        if got is None:
            return FrameRecord(Status.LOST, mode="detect", reason=Reason.FEW_MATCHES)
        est, uv, X, kf, land = got
        self._patched = True
        res = self._gate(est, len(uv), "detect", True, land, (X, uv), radius_px=radius)
        return self._accept(res, est, uv, X, kf, land)

    def _patch_refresh(self) -> FrameRecord | None:
        """The regular detection of a view from above whose points were placed by patches:
        the patches again, from the predicted pose, without detecting keypoints (mode
        `patch`). The keypoints added nothing there (480-above scene: 20-50 matched where
        the patches place 250-470) and cost 24 ms a box plus 8 of guided matching; the
        patches take 10. None (detect as usual) unless they place `patch_refresh_min`."""
        s = self.settings
        if self.velocity is None or self.lost_run:
            return None
        pred = self._predicted()
        if not self._refreshes(pred):
            return None
        self._patched = False
        got = self._patch_solve(pred)
        if got is None or got[0].inliers.sum() < s.patch_refresh_min:
            return None
        est, uv, X, kf, land = got
        self._patched = True
        res = self._gate(est, len(uv), "patch", True, land, (X, uv), radius_px=s.patch_reach_px)
        if not res.ok:
            self._patched, self._uncertain_pose = False, None
            return None
        self.since_detect = 0
        return self._accept(res, est, uv, X, kf, land)

    def _patch_verdict(self, est, points, got) -> tuple[bool, np.ndarray | None]:
        """Is the patch pose `got` the better measurement, and if not, the dispute the
        keypoints' covariance must cover (None: none). The patches win only with clearly
        more points than the keypoints matched (as many, under motion blur or on a small
        face, they err alike with a smaller sigma) and, as their covariances say, a smaller
        position sigma: a landmark large enough for fine keypoints (the stress orbit at 2.5
        m) is measured as well by them. When the keypoints keep the frame, their few points
        claiming the smaller sigma, but the patches' many put the camera elsewhere by more
        than both sigmas allow (`patch_dispute`), one of the two is wrong, and the frame's
        covariance takes in the gap between them (far tuning seeds: keypoint poses of
        13-33 inliers 6-7% of the range off at 0.7-0.9% sigma, where patches of 75-350
        points were 1-2% off)."""
        n = int(got[0].inliers.sum())
        if n < self.settings.patch_min_gain * est.inliers.sum():
            return False, None
        mine = self._covariances(est, int(est.inliers.sum()), points)[0]
        theirs = self._covariances(got[0], n, (got[2], got[1]), patched=True)[0]
        if sigmas(theirs)[0] < sigmas(mine)[0]:
            return True, None
        return False, disputed(est.pose, got[0].pose, mine + theirs, self.settings.patch_dispute)

    def _patch_ok(self, pose: Pose) -> bool:
        """Patches where keypoints are weak: a small box (upsampled: a far landmark) or a
        view from well above the nearby keyframes (their faces foreshortened)."""
        mode = self.settings.patch_refine
        if mode == "off" or self._gray is None or self._kf_image is None:
            return False
        # from above, not around a hint that goes back to an unconfirmed relocalisation:
        # patches find what the hint predicts, a look-alike side's as well, and their
        # many points turned its `uncertain` chain ok (report seed above 1006: 22 -> 84
        # wrong poses)
        return (
            mode == "all" or self._small_box
            or (self._above(pose) and not self._from_unconfirmed())
        )  # fmt: skip

    def _above(self, pose: Pose) -> bool:
        """Is the view `tilt.ABOVE_DEG` or more above the keyframes nearest it?"""
        near = self.model.nearest_keyframes(pose, self.settings.patch_keyframes)
        return bool(self._looked_down_on(pose, near))

    def _refreshes(self, pred: Pose) -> bool:
        """Will the regular detection at `pred` be the patches alone (`_patch_refresh`)?
        A view from above whose last detection was placed by patches."""
        return (
            self.settings.patch_refresh and self._anchor_patched and self._patch_ok(pred)
            and self._above(pred)
        )  # fmt: skip

    def _patch_search(self, pose: Pose, coarsest: int):
        """`_patch_solve` from the frame's pyramid level `coarsest` down to its own pixels,
        each level from the last one's pose: a reach of 4 px at level 2 is 16 px, for a
        pose found from a few keypoints or kept while lost."""
        got = None
        for level in range(coarsest, -1, -1):
            got = self._patch_solve(pose, level)
            if got is None:
                return None
            pose = got[0].pose
        return got

    def _frame_level(self, level: int) -> np.ndarray:
        """This frame's pyramid level (pyrDown: pixel x at x / 2^level), made once."""
        while len(self._gray_levels) <= level:
            self._gray_levels.append(cv2.pyrDown(self._gray_levels[-1]))
        return self._gray_levels[level]

    def _patch_solve(self, pose: Pose, level: int = 0):
        """The pose again from the nearby keyframes' points placed by their patches
        (patches.py), correlated on the frame's pyramid `level`: (estimate, uv, X,
        keyframe, on-landmark), or None."""
        s = self.settings
        f = 0.5**level
        cands = self.model.nearest_keyframes(pose, s.patch_keyframes + self._added_kfs)
        cands = [k for k in cands if k < self._patch_kfs][: s.patch_keyframes]
        # by the faces' normals from above; level far views keep planes facing the
        # keyframe (far tuning seeds 10-21 by normals: 3 wrong, honesty 1.96 on seed 17)
        faces = self._above(pose)
        seen = np.zeros(0, np.int64)  # points an earlier keyframe already tried
        Xs, uvs, pids, kfs = [], [], [], []
        for k in cands:
            kf = self.model.keyframes[k]
            pid = np.setdiff1d(kf.point_ids[kf.point_ids >= 0], seen)  # (sorted, unique)
            X = self.model.points[pid]
            nrm = (
                self._point_normals(pid, kf.pose.center, pose.center)
                if faces else np.full((len(pid), 3), np.inf)
            )  # fmt: skip
            front = pose.transform(X)[:, 2] > 1e-3
            # a point off a face (no normal) is warped as a plane facing the keyframe: true
            # enough only for a view from nearly the same direction
            a, b = X - kf.pose.center, X - pose.center
            cos = np.einsum("ij,ij->i", a, b) / (
                np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-12
            )
            limit = np.where(
                np.isfinite(nrm[:, 0]), s.patch_max_angle_normal_deg, s.patch_max_angle_deg
            )
            front &= (cos >= np.cos(np.radians(limit))) & ~np.isnan(nrm[:, 0])
            pid, X, nrm = pid[front], X[front], nrm[front]
            if len(pid) > s.patch_max_points:  # evenly: enough to pin the pose
                pick = np.linspace(0, len(pid) - 1, s.patch_max_points).astype(int)
                pid, X, nrm = pid[pick], X[pick], nrm[pick]
            if not len(pid):
                continue
            pk, pc, A = affine_maps(self.camera, X, kf.pose, pose, self.model.camera, nrm)
            good = np.isfinite(pc).all(axis=1) & np.isfinite(A).all(axis=(1, 2))
            if not good.any():
                continue
            pyramid, sc = self._kf_pyramid(k)
            tpl = templates(pyramid, pk[good] * sc, A[good] * (f / sc))
            pos, peak = correlate(self._frame_level(level), pc[good] * f, tpl, s.patch_reach_px)
            pos /= f
            keep = np.isfinite(peak) & (peak >= s.patch_min_ncc)
            Xs.append(X[good][keep])
            uvs.append(pos[keep])
            pids.append(pid[good][keep])
            kfs.append(np.full(keep.sum(), k))
            seen = np.concatenate([seen, pid])
        if not Xs:
            return None
        X, uv, pid = np.concatenate(Xs), np.concatenate(uvs), np.concatenate(pids)
        if len(X) < s.min_track_inliers:
            return None
        ransac = replace(s.patch_ransac, threshold_px=s.patch_ransac.threshold_px / f)
        est = solve_pose(
            X, uv, self.camera, reference_pose=pose, method=s.method, ransac=ransac,
            refine=s.refine,
        )  # fmt: skip
        if not est.success or est.inliers.sum() < s.min_track_inliers:
            return None
        kf = int(np.bincount(np.concatenate(kfs)).argmax())
        return est, uv, X, kf, self.on_landmark[pid]

    def _point_normals(self, pid, kf_center, center) -> np.ndarray:
        """The points' face normals, towards the keyframe; inf where the point lies on no
        face (an edge, a corner: warped as facing the keyframe) and NaN where the face is
        turned away from the frame or seen edge-on (no template)."""
        if self._normals is None:
            nrm, flat = point_normals(self.model.points)
            nrm[flat > self.settings.patch_flat_max] = np.inf
            self._normals = nrm
        n = self._normals[pid].copy()
        X = self.model.points[pid]
        face = np.isfinite(n[:, 0])
        sign = np.sign(np.einsum("ij,ij->i", n, kf_center - X))
        n[face] *= sign[face, None]
        v = center - X
        cos = np.einsum("ij,ij->i", n, v) / (np.linalg.norm(v, axis=1) + 1e-12)
        n[face & (cos < np.cos(np.radians(self.settings.patch_max_slant_deg)))] = np.nan
        return n

    def _kf_pyramid(self, k: int) -> tuple[list[np.ndarray], float]:
        """Keyframe k's image pyramid and its pixels per keyframe pixel; the last
        `PYRAMIDS_KEPT` used are kept (0.4 MB each at 640x480; a 144-keyframe orbit)."""
        got = self._pyramids.pop(k, None)
        if got is None:
            got = (keyframe_pyramid(self._kf_image(k)), self.model.keyframes[k].image_scale)
            while len(self._pyramids) >= PYRAMIDS_KEPT:
                self._pyramids.pop(next(iter(self._pyramids)))
        self._pyramids[k] = got  # (dicts keep insertion order: the oldest goes first)
        return got
