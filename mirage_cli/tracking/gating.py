"""The gate every pose ends in: enough consistent inliers that could not be chance, on the
landmark itself, a small residual, a plausible motion and an uncertainty small enough to
trust (else `uncertain`); and the pose's covariances (`frame_covariances`). A mixin of
`Tracker`."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..camera import Camera
from ..evidence import chance_inlier_probability, is_evidence, search_area
from ..model import INHERITED_TABLE
from ..records import FrameRecord, Measurement, Reason, Status
from ..solver import (
    PoseEstimate,
    RansacOptions,
    sandwich_covariance,
    sigmas,
    solve_pose,
    verifiable,
)
from ..tilt import camera_roll_deg
from .patching import disputed

RANSAC_HYPOTHESES = RansacOptions.iterations  # how many poses RANSAC tries at most


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


class PoseGate:
    """The gate and the covariances of a pose (a mixin of Tracker)."""

    _kf_rolls: np.ndarray | None = None  # the keyframes' rolls (`_implausible`), when asked
    _inherit_tree: tuple | None = None  # the points an extension carried, when asked

    def _covariances(
        self, est: PoseEstimate, n: int, points=None, patched: bool = False, dispute=None
    ):
        """The pose's own and the model's covariance; `dispute`, a covariance the pose's own
        must also cover (`_patch_verdict`)."""
        res, shared = frame_covariances(
            est, n, self.camera, points, self.settings.refine.huber_px, self.model_rms_px,
            self.settings.model_error_points, self.model_error_scale,
        )  # fmt: skip
        if patched:  # patch errors of one face's points err alike
            k = self.settings.patch_error_points
            floor = self.settings.patch_error_floor if self._shrunk_view(est) else 1.0
            res = res * max(floor, n / k)
        inherited = self._inherited_covariance(est, points)
        if inherited is not None:
            shared = shared + inherited
        return (res if dispute is None else res + dispute), shared

    def _inherited_covariance(self, est: PoseEstimate, points) -> np.ndarray | None:
        """The error a pose shares with the tracked frames its points were triangulated
        from (a model extended by the video, extend.py): their sigma, weighted by the
        share of its inliers on such points (isotropic; None: none of them)."""
        table = self.model.tables.get(INHERITED_TABLE)
        if table is None or points is None or not est.success:
            return None
        if self._inherit_tree is None:
            carried = np.flatnonzero(table[:, 0] > 0)
            self._inherit_tree = (cKDTree(self.model.points[carried]), table[carried])
        tree, sig = self._inherit_tree
        if not len(sig):
            return None
        d, i = tree.query(points[0][est.inliers], distance_upper_bound=1e-9)
        hit = np.isfinite(d)
        if not hit.any():
            return None
        sp, sr = sig[i[hit]].sum(axis=0) / max(int(est.inliers.sum()), 1)
        return np.diag([sr**2 / 3] * 3 + [sp**2 / 3] * 3)

    def _shrunk_view(self, est: PoseEstimate) -> bool:
        """Does the frame show the landmark at most 1 / `patch_floor_ratio` of its size in
        the nearest keyframe (`_view_scale`)? There each patch is a template shrunk from the
        keyframe, placed within a few pixels of the pose it measures in a small, blurred
        view, and its residuals understate its error (`patch_error_floor`); from nearly the
        keyframes' distance (views from above) they do not (above tuning seeds: honesty
        0.88 without the floor)."""
        if not est.success:
            return False
        return bool(self._view_scale(est.pose) * self.settings.patch_floor_ratio <= 1.0)

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
            r = radius_px or self.settings.guided_radius_px * (1 + min(self.lost_run, 3))
            area = np.pi * r**2
        p = chance_inlier_probability(self.settings.ransac.threshold_px, area)
        return is_evidence(
            total, int(inl.sum()), p, RANSAC_HYPOTHESES, self.settings.max_false_alarms
        )

    def _verify(self, est: PoseEstimate, points) -> None:
        """A pose that rests on a single point in some direction is fitted again without
        it (`max_leverage`, `solver.verifiable`), in place: the gate's caller keeps the
        inliers the gate judged."""
        if est.success and points is not None:
            checked = verifiable(est, *points, self.camera, self.settings.max_leverage,
                                 self.settings.refine)  # fmt: skip
            if checked is not est:
                vars(est).update(vars(checked))

    def _gate_covariances(self, est, ninl, mode, points, on_landmark, dispute):
        """`_covariances` for the gate: a flowed pose's points were placed as its anchor's
        were; a detected or flowed one may be disputed by its few ground inliers."""
        patched = self._anchor_patched if mode == "flow" else self._patched
        own, shared = self._covariances(est, ninl, points, patched, dispute)
        if dispute is None and mode in ("detect", "flow"):
            ground = self._ground_dispute(est, points, on_landmark, own)
            if ground is not None:
                own = own + ground
        return own, shared

    def _ground_dispute(self, est, points, on_landmark, own) -> np.ndarray | None:
        """A few inliers off the landmark (the ground by its foot) can pin a direction the
        landmark's own points leave open, and cut the sigma several times while the pose is
        wrong (near tuning seed 62: 2 ground inliers of 30, sigma 0.3 cm, 4 cm and 2.5 deg
        off). Fit again without them: a pose they moved beyond `patch_dispute` sigma (of
        `own`, the pose's own covariance) carries the gap in its covariance, as keypoints
        the patches dispute do."""
        if on_landmark is None or points is None:
            return None
        keep = est.inliers & on_landmark
        n_keep = int(keep.sum())
        off = int(est.inliers.sum()) - n_keep
        if not 0 < off <= self.settings.ground_dispute_max or n_keep < 6:
            return None
        X, uv = points
        alt = solve_pose(X[keep], uv[keep], self.camera, est.pose, method=self.settings.method,
                         refine=self.settings.refine)  # fmt: skip
        if not alt.success:
            return None
        return disputed(est.pose, alt.pose, own, self.settings.patch_dispute)

    def _implausible(self, pose) -> bool:
        """Rolled more than `max_roll_deg` beyond every keyframe (W's up in the image,
        `camera_roll_deg`): a drone or a robot keeps its camera about as level as the
        model's were, and a face's print seen from the side can look like its twin on a
        face the keyframes never saw only with the camera turned over (above tuning seed
        22: the top face's photograph also on a side face; 131 ok poses looking at the
        side face, rolled 43-123 deg, where the video and every keyframe are within 3)."""
        if self._kf_rolls is None:
            r = np.array([camera_roll_deg(kf.pose) for kf in self.model.keyframes])
            self._kf_rolls = r[np.isfinite(r)]
        roll = camera_roll_deg(pose)
        if not len(self._kf_rolls) or not np.isfinite(roll):
            return False
        beyond = np.abs((roll - self._kf_rolls + 180.0) % 360.0 - 180.0).min()
        return bool(beyond > self.settings.max_roll_deg)

    def _jumped(self, pose) -> bool:
        """Further from the previous ok pose than the motion allows (the limits are per
        frame since that pose)."""
        if self.prev_pose is None:
            return False
        frames = 1 + self.lost_run
        return (
            pose.distance_to(self.prev_pose) > self.settings.max_jump_m * frames
            or pose.angle_to(self.prev_pose) > self.settings.max_jump_deg * frames
        )

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
        dispute: np.ndarray | None = None,
    ) -> FrameRecord:
        """ok only with enough consistent inliers, enough of them on the landmark itself
        (`on_landmark`, per match; None: all are), a small residual, a plausible motion and
        an uncertainty small enough to trust (else `uncertain`).

        `voting` (per match; None: all) are the matches that could decide the pose: the
        inlier ratio counts among them, since matches to repeated texture or the ground are
        expected to pick the wrong twin (a tiled floor in view is half the matches)."""
        self._verify(est, points)
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
        cov_res, cov_model = self._gate_covariances(est, ninl, mode, points, on_landmark, dispute)
        res.sigma_pos_m, res.sigma_rot_deg = sigmas(cov_res + cov_model)
        # with a prediction a few points can make an ok pose (their uncertainty decides
        # below); without one, a pose needs the numbers that make RANSAC's answer unique
        need = (
            self.settings.min_inliers if mode == "relocalise" else self.settings.min_track_inliers
        )
        if ninl < need:
            return res
        if not self._significant(est, n, mode, points, voting, radius_px):
            res.reason = Reason.CHANCE
            return res
        n_land = ninl if on_landmark is None else int((est.inliers & on_landmark).sum())
        if n_land < min(self.settings.min_landmark_inliers, need):
            res.reason = Reason.OFF_LANDMARK
            return res  # the ground (or background) alone: the landmark is not in view
        if not est.rmse_px <= self.settings.max_ok_rmse_px:
            res.reason = Reason.RESIDUAL
            return res
        if est.pose.transform(np.zeros((1, 3)))[0, 2] <= 0:
            res.reason = Reason.BEHIND
            return res  # the landmark behind the camera
        if self._implausible(est.pose):
            res.reason = Reason.IMPLAUSIBLE
            return res
        if check_jump and self._jumped(est.pose):
            res.reason = Reason.JUMP
            return res
        max_pos = self.settings.max_sigma_pos_m
        if points is not None:  # relative to the range: the inliers' median depth
            depth = float(np.median(est.pose.transform(points[0][est.inliers])[:, 2]))
            ranged = max(self.settings.max_sigma_range * depth, self.settings.sigma_range_floor_m)
            max_pos = min(max_pos, ranged)
        res.measurement = Measurement(
            est.pose, cov_res, cov_model, max_sigma_pos_m=max_pos,
            max_sigma_rot_deg=self.settings.max_sigma_rot_deg,
        )  # fmt: skip
        if not (
            res.sigma_pos_m <= max_pos and res.sigma_rot_deg <= self.settings.max_sigma_rot_deg
        ):
            res.status, res.reason = Status.UNCERTAIN, Reason.UNCERTAIN
            self._uncertain_pose = est.pose
            return res
        res.status, res.pose, res.reason = Status.OK, est.pose, ""
        if mode == "flow" and self.keyframe >= 0:
            res.keyframe = self.model.keyframes[self.keyframe].name
        return res
