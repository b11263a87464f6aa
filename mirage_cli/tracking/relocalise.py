"""Relocalisation, when lost: global recognition, descriptor matching, RANSAC on the matches
that may vote (no twins, no ground), and the second-hypothesis test (`unambiguous_pose`);
and the confirmation a hint from an uncertain relocalisation needs after an ambiguous one
(`_confirm`). A mixin of `Tracker`."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..camera import Camera
from ..features import guided_match
from ..pose import Pose
from ..records import FrameRecord, Reason, Status
from ..solver import PoseEstimate, solve_pose
from .settings import TrackSettings

# relocalisation by proposals (`_relocalise_by_proposals`)
PROPOSE_RATIO = 0.9  # a looser ratio test: more right matches among more wrong ones
PROPOSE_ITERATIONS = 2000  # RANSAC's: ~1 all-right 4-sample at 15% right matches
PROPOSE_VERIFY = 8  # guided inliers a proposal needs before its box is searched
PROPOSE_LONG = 4  # a long loss: proposals at every 4th whole-frame search

# the rival side (`_rivalled`)
RIVAL_RANKED = 8  # recognition's ranking, this deep, may hold a rival place
RIVAL_SHARE = 0.25  # a rival pose with this share of the inliers makes the frame ambiguous
RIVAL_APART_M = 0.25  # ...when it is this far from the pose
RIVAL_APART_DEG = 10.0  # ...or turned this much
RIVAL_VAGUE = 2.5  # an uncertain rival counts within this many times the gate's limits


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
        ransac=s.ransac,
        refine=s.refine,
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
            and s.distinct(second.pose, first.pose)
        ):
            return Status.AMBIGUOUS
    err = np.linalg.norm(camera.project(X, first.pose) - uv, axis=1)
    inl = (err < s.ransac.threshold_px) & (first.pose.transform(X)[:, 2] > 0)
    full = np.zeros(len(X), bool)
    full[np.flatnonzero(unique)[first.inliers]] = True
    first.inliers = full
    if inl.sum() <= n1:
        return first
    final = solve_pose(
        X[inl], uv[inl], camera, first.pose, method=s.method,
        refine=s.refine,
    )  # fmt: skip
    if not final.success:
        return first
    full = np.zeros(len(X), bool)
    full[np.flatnonzero(inl)[final.inliers]] = True
    final.inliers = full
    return final


def _measured(rec: FrameRecord) -> bool:
    """ok, or uncertain by at most `RIVAL_VAGUE` times the gate's limits: a place measured
    about as well as an ok pose (a far landmark's keyframes, each on its own, also give
    vague poses metres apart: 3-11% of the range, 2.6-9x the limit, in the far family)."""
    m = rec.measurement
    if rec.ok:
        return True
    if rec.status != Status.UNCERTAIN or m is None:
        return False
    return (
        rec.sigma_pos_m <= RIVAL_VAGUE * m.max_sigma_pos_m
        and rec.sigma_rot_deg <= RIVAL_VAGUE * m.max_sigma_rot_deg
    )


class Relocalisation:
    """Relocalisation when lost (a mixin of Tracker)."""

    def _from_unconfirmed(self) -> bool:
        """This frame's prediction is a hint that goes back to an unconfirmed
        relocalisation."""
        return self.prev_pose is None and self.hint is not None and self._unconfirmed

    def _confirm(self, res: FrameRecord, gray: np.ndarray, full=None) -> FrameRecord:
        """A guided detection around a hint that goes back to an `uncertain` relocalisation,
        in a lost stretch where relocalisations also found two places (`ambiguous`): ok
        only when a relocalisation of this frame (on the lost search's schedule) is ok, and
        then as that relocalisation. Guided matching finds what the hint predicts: in the
        report seed above 1006 (11 frames ambiguous, then one uncertain relocalisation on
        a look-alike side) it was followed to ok poses 155 deg off (62 wrong, 23 with
        this check). Until confirmed the pose is only where to look next: `uncertain`,
        and no evidence for the smoother. `full`: the frame's whole-frame features when
        they are already detected."""
        if not self._from_unconfirmed() or res.status not in (Status.OK, Status.UNCERTAIN):
            return res
        pose = res.pose if res.ok else self._uncertain_pose
        if res.ok and self._search(self.lost_run) == "full":
            kps, desc = full or self._whole_frame(gray)
            if desc is not None and len(kps) >= self.settings.min_inliers:
                rel = self._relocalise(kps, desc)
                if rel.ok:  # as a lost frame's: the hint was only where to look
                    return rel
                if rel.status == Status.AMBIGUOUS:
                    res.reason = Reason.AMBIGUOUS
        res.status, res.pose, res.measurement = Status.UNCERTAIN, None, None
        if res.reason != Reason.AMBIGUOUS:
            res.reason = Reason.UNCERTAIN
        self._uncertain_pose = pose
        return res

    def _probe(self, gray: np.ndarray) -> FrameRecord:
        kps, desc = self._features("probe", self._probe_features, gray)
        self._at_scale(self.search_scale)  # (half size: it only says whether to go on)
        if desc is None or len(kps) < self.settings.min_inliers:
            return FrameRecord(Status.LOST, mode="relocalise", reason=Reason.FEW_FEATURES)
        return self._relocalise(kps, desc)

    def _relocalise(self, kps, desc, gray=None) -> FrameRecord:
        """Lost: recognise, match, and accept a pose only when the evidence is unambiguous.
        No pose from the keyframes as they are: again with their squashed views (a camera
        far above them, tilt.py); still none, with the whole frame's features (`gray`
        given) and on the proposal schedule: by proposals (`_relocalise_by_proposals`)."""
        res = self._relocalise_with(kps, desc, False)
        if res.status != Status.LOST or not self._has_tilted:
            return res  # found, or ambiguous: more matches to one side do not settle that
        ranked = self._recognised(desc, True)
        again = self._relocalise_with(kps, desc, True, ranked)
        if again.status in (Status.OK, Status.UNCERTAIN):
            return again
        if gray is not None and again.status == Status.LOST and self._propose_now():
            cands = ranked[: self.settings.global_keyframes]
            proposed = self._relocalise_by_proposals(gray, kps, desc, cands)
            if proposed is not None:
                return proposed
        return res

    def _propose_now(self) -> bool:
        """Proposals cost 70-150 ms (two RANSACs of 2000 iterations, guided checks): at
        every other whole-frame search of a short loss (lost 0, 6, 12 frames), and at
        every `PROPOSE_LONG`-th of a long one (a look-away is searched for seconds: the
        sample's 22-frame look-away had 5 proposals, 310 ms, with every search)."""
        lost, s = self.lost_run, self.settings
        every = 2 * s.relocalise_every * (1 if lost <= s.long_lost else PROPOSE_LONG)
        return lost % every == 0

    def _recognised(self, desc, tilted: bool) -> list[int]:
        """Recognition's ranking of the keyframes: its first `global_keyframes` are matched,
        the rest may hold a rival side (`_rivalled`)."""
        top = max(self.settings.global_keyframes, RIVAL_RANKED)
        return [i for i, _ in self.model.recognize(desc, top_k=top, tilted=tilted)]

    def _relocalise_by_proposals(self, gray, kps, desc, cands) -> FrameRecord | None:
        """A view far from every keyframe's (a drone 45-60 deg above a model made on foot):
        descriptor matching over the recognised keyframes keeps too few right matches for
        `unambiguous_pose` (above 2: 6-15 right of 60-90 at ratio 0.9), but a long RANSAC
        over them still proposes the pose, and guided matching around a proposal tells:
        a right one gathers 8-14 inliers of the frame's features, a wrong one 4-6. A
        proposal that gathers `PROPOSE_VERIFY` is then searched as while tracking (its
        box detected, upsampled when small) and must pass the relocalisation's gate
        (`min_inliers` of matches that may vote, chance among them, landmark). Two
        distinct proposals that pass: ambiguous."""
        if not cands:
            return None
        X_all, d_all, kf_of, pid_all = self._candidates(cands, set(cands))
        anywhere = np.zeros((len(X_all), 2))
        qi, ti = guided_match(kps, desc, anywhere, d_all, pid_all, np.inf, PROPOSE_RATIO)
        unique = self.votes[pid_all[ti]].copy()
        uv, X = kps[qi].astype(np.float64), X_all[ti]
        s = self.settings
        ransac = replace(s.ransac, iterations=PROPOSE_ITERATIONS, confidence=0.99999)
        passed = []
        for _ in range(s.proposals):
            if unique.sum() < 6:
                break
            per_kf = np.bincount(kf_of[ti[unique]], minlength=len(self.model.keyframes))
            ref = self.model.keyframes[int(np.argmax(per_kf))].pose
            est = solve_pose(
                X[unique], uv[unique], self.camera, ref, method=s.method, ransac=ransac,
                refine=s.refine,
            )  # fmt: skip
            if not est.success:
                break
            unique[np.flatnonzero(unique)[est.inliers]] = False  # the next round: the rest
            found = self._verified(gray, kps, desc, est.pose)
            if found is not None:
                passed.append(found)
        if not passed:
            return None
        passed.sort(key=lambda f: -f[0].inliers)
        best = passed[0]
        for other in passed[1:]:
            if other[0].inliers >= s.second_hypothesis * best[0].inliers and s.distinct(
                other[1].pose, best[1].pose
            ):
                return FrameRecord(Status.AMBIGUOUS, mode="relocalise", reason=Reason.AMBIGUOUS)
        res, est, uv, X, kf, land, scale = best
        self._at_scale(scale)  # the flow from here keeps the scale its points were found at
        self._uncertain_pose = est.pose if res.status == Status.UNCERTAIN else None
        return self._accept(res, est, uv, X, kf, land)

    def _verified(self, gray, kps, desc, pose: Pose):
        """A proposal's pose, checked as described in `_relocalise_by_proposals`: (record,
        estimate, uv, X, keyframe, on-landmark, scale) when it passes the gate, else None."""
        r = self.settings.guided_radius_px
        g = self._guided_solve(kps, desc, pose, 2 * r)
        if g is None or not g[0].success:
            return None
        g = self._guided_solve(kps, desc, g[0].pose, r)
        if g is None or not g[0].success or g[0].inliers.sum() < PROPOSE_VERIFY:
            return None
        box = self._model_box(g[0].pose, gray.shape)  # None: most of the frame
        if box is None:
            scale = self._whole_scale()  # the frame's own whole-frame features
        else:
            kps, desc = self._box_features(gray, box, self.detector)
            scale = max(1.0, box[4])
        self._at_scale(scale)
        g = self._guided_solve(kps, desc, g[0].pose, r)
        if g is None or not g[0].success:
            return None
        est, uv, X, kf, land, votes = g
        if (est.inliers & votes).sum() < self.settings.min_inliers:
            return None  # as unambiguous_pose: repeated texture and the ground never decide
        res = self._gate(est, len(uv), "relocalise", False, land, (X, uv), votes)
        if res.status not in (Status.OK, Status.UNCERTAIN):
            return None
        return res, est, uv, X, kf, land, scale

    def _relocalise_with(self, kps, desc, tilted: bool, ranked=None) -> FrameRecord:
        """Relocalise on recognition's first `global_keyframes` (`ranked`: its ranking, found
        when None); an ok pose that one of its keyframes, matched on its own, places
        elsewhere is ambiguous (`_rivalled`)."""
        ranked = self._recognised(desc, tilted) if ranked is None else ranked
        found = self._solve_with(kps, desc, tilted, ranked[: self.settings.global_keyframes])
        if isinstance(found, FrameRecord):
            return found
        res, est, uv, X, kf, land = found
        if res.ok and self._rivalled(kps, desc, tilted, ranked, res, est):
            self._uncertain_pose = None
            return FrameRecord(
                Status.AMBIGUOUS, matches=len(uv), inliers=res.inliers, mode="relocalise",
                reason=Reason.AMBIGUOUS,
            )  # fmt: skip
        if res.ok:
            polished = self._polished(kps, desc, res)
            if polished is not None:
                return polished
        return self._accept(res, est, uv, X, kf, land)

    def _rivalled(self, kps, desc, tilted: bool, ranked, res: FrameRecord, est) -> bool:
        """Does another place explain the frame about as well? Matching over keyframes of
        two sides loses the features that look alike on both to the ratio test, so a
        look-alike side can win with what is left: in the report seed near 1004 (two faces
        cut from one photograph) the first relocalisation was 174 deg off with 106
        inliers, while the true side's keyframe, ranked 3rd-8th, matched on its own gave
        57, and 48 ok poses followed the wrong side. So each ranked keyframe is matched
        on its own: a pose `RIVAL_APART_M` / `RIVAL_APART_DEG` away, measured about as
        well (`_measured`), with `RIVAL_SHARE` of the inliers is a rival, and the frame
        ambiguous (a pose from one keyframe's matches may be a little off; a rival is
        another place)."""
        pose, held = est.pose, self._uncertain_pose
        try:
            for k in ranked:
                found = self._solve_with(kps, desc, tilted, [k])
                if isinstance(found, FrameRecord):
                    continue  # (ambiguous within one keyframe: repeated texture of its own)
                rival, other = found[0], found[1].pose
                if (
                    _measured(rival)
                    and rival.inliers >= RIVAL_SHARE * res.inliers
                    and (
                        other.distance_to(pose) > RIVAL_APART_M
                        or other.angle_to(pose) > RIVAL_APART_DEG
                    )
                ):
                    return True
            return False
        finally:
            self._uncertain_pose = held

    def _solve_with(self, kps, desc, tilted: bool, cands):
        """The relocalisation's gated record on `cands` and what `_accept` needs (record,
        estimate, uv, X, keyframe, on-landmark), or the LOST / AMBIGUOUS record."""
        if not cands:
            return FrameRecord(Status.LOST, mode="relocalise", reason=Reason.NOT_RECOGNISED)
        X_all, d_all, kf_of, pid_all = self._candidates(cands, set(cands) if tilted else ())
        # descriptor matching whose ratio test compares distinct 3D points (the same point
        # seen by two candidate keyframes is not a rival); no position prior: radius inf
        anywhere = np.zeros((len(X_all), 2))
        qi, ti = guided_match(kps, desc, anywhere, d_all, pid_all, np.inf, self.settings.ratio)
        uv, X = kps[qi].astype(np.float64), X_all[ti]
        # matches to repeated texture or to the ground do not vote
        land = self.on_landmark[pid_all[ti]]
        unique = self.votes[pid_all[ti]]
        lost = FrameRecord(
            Status.LOST, matches=len(qi), mode="relocalise", reason=Reason.FEW_MATCHES
        )
        if unique.sum() < self.settings.min_inliers:
            return lost
        kf = int(np.argmax(np.bincount(kf_of[ti[unique]], minlength=len(self.model.keyframes))))
        est = unambiguous_pose(
            X, uv, unique, self.camera, self.model.keyframes[kf].pose, self.settings
        )
        if isinstance(est, Status):
            lost.status = est
            lost.reason = Reason.AMBIGUOUS if est == Status.AMBIGUOUS else Reason.FEW_INLIERS
            return lost
        res = self._gate(est, len(uv), "relocalise", False, land, (X, uv), unique)
        return res, est, uv, X, kf, land


class Polish:
    """An ok relocalisation measured again as a tracked frame would be (a mixin of
    Tracker)."""

    def _polished(self, kps, desc, res: FrameRecord) -> FrameRecord | None:
        """A relocalised pose measured again as a tracked frame is (ORB-SLAM's search by
        projection), at the tracking radius: the weak-texture orbit's first frame was
        relocalised 26 mm (2.8 sigma) off with 56 inliers; guided, 62 and 6 mm. A far
        landmark is also measured in its box, upsampled, as the next tracked frame would
        be, and the one with more inliers is kept: far tuning seed 19's first frame, 49
        whole-frame inliers 10 cm (2.2 sigma) off, has 350 there and is 1.4 cm off (the
        4 m stress orbit's relocalisation after its look-away: 266 in the whole frame, 100
        in the box). Kept when ok, with at least the relocalisation's inliers, and not
        moved as far as another hypothesis would be (`_moved`)."""
        held = self._uncertain_pose
        best, state = None, (self.px_scale, self._small_box)  # (the scale to leave)
        g = self._guided(kps, desc, res.pose, self.settings.guided_radius_px)
        if g.ok and g.inliers >= res.inliers and not self._moved(g.pose, res):
            best, state = (g, self._tracked()), (self.px_scale, self._small_box)
        box = self._model_box(res.pose, self._gray.shape) if self._gray is not None else None
        if self._upsamples(box):
            self._at_scale(1.0)
            self._small_box = True
            kps, desc = self._box_features(self._gray, box, self.detector)
            g = self._guided(kps, desc, res.pose, self.settings.guided_radius_px)
            if (
                g.ok and g.inliers >= max(res.inliers, best[0].inliers if best else 0)
                and not self._moved(g.pose, res)
            ):  # fmt: skip
                best, state = (g, self._tracked()), (self.px_scale, self._small_box)
        self._uncertain_pose = held
        self._at_scale(state[0])
        self._small_box = state[1]
        if best is None:
            return None
        g, tracked = best
        self._restore(tracked)
        g.mode = "relocalise"
        return g

    _TRACKED = ("keyframe", "track_px", "track_X", "track_land", "_patched")

    def _tracked(self) -> tuple:
        """What an accepted pose leaves for the next frame (`_accept`), to choose later."""
        return tuple(getattr(self, k) for k in self._TRACKED)

    def _restore(self, tracked: tuple) -> None:
        for k, v in zip(self._TRACKED, tracked, strict=True):
            setattr(self, k, v)

    def _moved(self, pose: Pose, res: FrameRecord) -> bool:
        """Another hypothesis than `res`, not a refinement of it: `distinct`, and beyond 3
        of its position sigmas (a far relocalisation can be 10 cm off at 2 sigma) or turned
        by `distinct_deg`."""
        d, sigma = pose.distance_to(res.pose), res.sigma_pos_m
        return bool(
            (d > self.settings.distinct_m and not d <= 3 * sigma)  # (no sigma: distinct)
            or pose.angle_to(res.pose) > self.settings.distinct_deg
        )
