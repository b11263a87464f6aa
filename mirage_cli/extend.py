"""Growing a model from the video it tracks (`mirage track --extend`).

Keyframes taken on foot see a landmark's sides from near eye level; a drone's video sees
them from 30-60 deg above, and its tops, which no keyframe saw. Where the video was
tracked well, its frames are views with known poses like the keyframes: the frames that
look from where no keyframe (and no frame already taken) looked join the keyframes, the
model is built again with them, and the frames the first pass could not place are tracked
again against it (above tuning seeds 4 / 5 / 8: 24 / 55 / 41% -> 95 / 100 / 100%). It is
as safe as the first pass: a wrong run of `MIN_RUN` frames joins as well, and the second
pass then tracks the copy it made (above tuning seed 48: 61 wrong poses -> 150), which is
why it is an option.

A point that only the added frames triangulate carries their pose error: every frame
that rests on such points errs with them, however many it matches. The model keeps,
per point, the mean position and rotation sigma of the frames it came from (0 for the
keyframes' own points, seen by two of them or more), and the tracker adds that, as a
shared error, to every pose in proportion to its inliers on such points
(`PoseGate._inherited_covariance`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .build_model import (
    ROI,
    BuildSettings,
    View,
    ViewList,
    build_model,
    triangulate,
    views_change,
)
from .camera import Camera
from .features import to_gray
from .model import INHERITED_TABLE, LandmarkModel
from .pose import Pose
from .records import FrameRecord

SPACING_DEG = 6.0  # a frame joins when its view differs this much from every other's
MAX_SIGMA_SHARE = 0.01  # ... and its position sigma is at most this share of its range
MIN_RUN = 10  # ... and it is inside a run of this many ok frames (`ViewPicker`)
# `_depth_gain`: above tuning seeds 4 / 18 / 27, honesty 2.23 / 1.71 / 1.46 with none,
# 1.58 / 1.60 / 1.43 with these (15 deg and 3x: seeds 3 and 4 lost what they had gained;
# all before the added frames' patches were left out, then 4 / 18: 1.60 / 1.61)
NARROW_DEG = 10.0
MAX_GAIN = 2.0
MAX_VIEWS = 36  # at most this many frames join (a turn of the video at the spacing)


@dataclass
class TrackedView:
    """A well-tracked frame that joins the keyframes: its pose in the model's frame."""

    name: str
    pose: Pose
    sigma_pos_m: float
    sigma_rot_deg: float
    image: np.ndarray  # grey


class ViewPicker:
    """Picks, as the records come, the tracked frames worth adding to the model: ok, with
    a sigma of at most `max_sigma_share` of the range, from a view `spacing_deg` or more
    from every other's (`views_change`), and inside a run of `min_run` ok frames or more.
    One wrong pose that joined would mislead every frame that matches its points; the
    wrong poses the tracker still makes are single frames or short runs after a
    relocalisation (above tuning seed 22: one ok frame 1.7 m off, which joined and gave
    66 wrong poses)."""

    def __init__(
        self,
        model: LandmarkModel,
        spacing_deg: float = SPACING_DEG,
        max_sigma_share: float = MAX_SIGMA_SHARE,
        limit: int = MAX_VIEWS,
        min_run: int = MIN_RUN,
    ):
        self.spacing, self.share, self.limit, self.min_run = (
            spacing_deg, max_sigma_share, limit, min_run,
        )  # fmt: skip
        self.level = model.world_from_model.T  # records are in W, the model in its level copy
        self.centre = model.points.mean(axis=0) if len(model.points) else np.zeros(3)
        self.centres = np.array([kf.pose.center for kf in model.keyframes]).reshape(-1, 3)
        self.axes = np.array([kf.pose.R[2] for kf in model.keyframes]).reshape(-1, 3)
        self.views: list[TrackedView] = []
        self._pending: list[TrackedView] = []  # of the current run, until it is long enough
        self._run = 0

    def offer(self, rec: FrameRecord, image: np.ndarray | None) -> None:
        """The next record in frame order, with its frame's image (grey or BGR)."""
        if not rec.ok or rec.pose is None:
            self._run, self._pending = 0, []
            return
        self._run += 1
        view = self._candidate(rec, image)
        if view is not None:
            self._pending.append(view)
        if self._run >= self.min_run and self._pending:
            self.views += self._pending
            self.centres = np.vstack([self.centres] + [v.pose.center for v in self._pending])
            self.axes = np.vstack([self.axes] + [v.pose.R[2] for v in self._pending])
            self._pending = []

    def _candidate(self, rec: FrameRecord, image: np.ndarray | None) -> TrackedView | None:
        if image is None or len(self.views) + len(self._pending) >= self.limit:
            return None
        pose = Pose(rec.pose.R @ self.level.T, rec.pose.t)  # X_w = L^T X_model
        rng = float(np.linalg.norm(pose.center - self.centre))
        if not rec.sigma_pos_m <= self.share * rng:
            return None
        centres = np.vstack([self.centres] + [v.pose.center for v in self._pending])
        axes = np.vstack([self.axes] + [v.pose.R[2] for v in self._pending])
        if views_change(pose.center[None], pose.R[2][None], centres, axes, self.centre).min() < (
            self.spacing
        ):
            return None
        return TrackedView(f"frame {rec.frame}", pose, rec.sigma_pos_m, rec.sigma_rot_deg,
                           to_gray(image))  # fmt: skip


def can_extend(model: LandmarkModel, camera: Camera) -> str | None:
    """Why the model cannot be built again with the video's frames (None: it can): it
    needs its keyframes' images at full size, and the video's camera must be the model's
    (one build, one camera)."""
    if not model.keyframes or any(kf.image is None for kf in model.keyframes):
        return "the model has no keyframe images (built with --no-keyframe-images or before)"
    if any(kf.image_scale != 1.0 for kf in model.keyframes):
        return "the model's keyframe images are stored halved (larger than 2048 px)"
    if not camera.same_as(model.camera, tol_px=1.0):
        return "the video's camera is not the model's"
    return None


def why_not_extend(model: LandmarkModel, camera: Camera, picker: ViewPicker, records) -> str | None:
    """Why the first pass's `records` are final (None: extend and track again)."""
    why = can_extend(model, camera)
    if why is None and not picker.views:
        why = "no frame was tracked well from a view the keyframes lack"
    if why is None and all(r.ok for r in records):
        why = "every frame is already ok"
    return why


def extended_model(model: LandmarkModel, views: list[TrackedView]) -> LandmarkModel:
    """The model built again from its keyframes and the tracked views, with the build
    settings it was made with, and each point's inherited sigma (`INHERITED_TABLE`)."""
    meta = model.meta
    roi = meta.get("roi") or {}
    settings = BuildSettings(
        detector=model.detector,
        spacing_deg=float(meta.get("spacing_deg", BuildSettings.spacing_deg)),
        ratio=float(meta.get("ratio", BuildSettings.ratio)),
        max_reproj_px=float(meta.get("max_reproj_px", BuildSettings.max_reproj_px)),
        min_angle_deg=float(meta.get("min_angle_deg", BuildSettings.min_angle_deg)),
        roi=ROI(roi.get("kind", "none"), tuple(roi.get("values", ())), roi.get("reason", "")),
        tilted_views=model.has_tilted,
    )
    base = [View(kf.name, kf.pose, None, kf.gray_image()) for kf in model.keyframes]
    added = [View(v.name, v.pose, None, v.image, "tracked") for v in views]
    all_views = ViewList(base + added)
    all_views.up = meta.get("up") or ViewList.up
    out = build_model(all_views, model.camera, settings).model
    out.meta["extended"] = {
        "keyframes": len(base),
        "frames": [v.name for v in views],
        "sigma_pos_m": [v.sigma_pos_m for v in views],
    }
    _keyframes_own_points(out, len(base))
    out.tables[INHERITED_TABLE] = inherited_sigmas(out, len(base), views)
    return out


def _keyframes_own_points(model: LandmarkModel, n_base: int) -> None:
    """Each point two or more of the first `n_base` keyframes see is triangulated from
    those alone, in place, as the model had it: an added frame's pose error (1% of a far
    view's range is 4 cm) is not theirs to carry. (A safeguard: on far tuning seed 17 it
    changed nothing measurable; that seed's bias was the added frames' patches.)"""
    obs = model.point_observations
    pt, kf, feat = (np.asarray(obs[k], np.int64) for k in ("point", "keyframe", "feature"))
    own = kf < n_base
    keep = np.bincount(pt[own], minlength=len(model.points)) >= 2
    use = own & keep[pt]
    if not use.any():
        return
    ids, track = np.unique(pt[use], return_inverse=True)
    kps = [model.keyframes[k].keypoints for k in range(n_base)]
    at = np.concatenate([[0], np.cumsum([len(k) for k in kps])])[kf[use]] + feat[use]
    x = model.camera.undistort_points(np.concatenate(kps).astype(np.float64)[at])
    Rs = np.array([model.keyframes[k].pose.R for k in kf[use]])
    ts = np.array([model.keyframes[k].pose.t for k in kf[use]])
    model.points[ids] = triangulate(x, Rs, ts, track, len(ids))


def inherited_sigmas(model: LandmarkModel, n_base: int, views: list[TrackedView]) -> np.ndarray:
    """(N, 2) per point: the mean position (m) and rotation (rad) sigma of the added views
    that see it; 0 for a point two or more of the first `n_base` keyframes see (their
    poses are the model's truth: such a point is as good as before)."""
    n = len(model.points)
    obs = model.point_observations
    pt, kf = np.asarray(obs["point"], np.int64), np.asarray(obs["keyframe"], np.int64)
    own = np.bincount(pt[kf < n_base], minlength=n)
    new = kf >= n_base
    sig = np.array([[v.sigma_pos_m, np.radians(v.sigma_rot_deg)] for v in views]).reshape(-1, 2)
    count = np.bincount(pt[new], minlength=n).astype(float)
    out = np.zeros((n, 2))
    for j in range(2):
        total = np.bincount(pt[new], weights=sig[kf[new] - n_base, j], minlength=n)
        out[:, j] = np.divide(total, count, out=np.zeros(n), where=count > 0)
    out[own >= 2] = 0.0
    return out * _depth_gain(model, pt, kf)[:, None]


def _depth_gain(model, pt: np.ndarray, kf: np.ndarray) -> np.ndarray:
    """Per point, how much its error grows from its views' errors along their rays: a
    point its views see from directions `theta` apart is placed along them to
    sin(NARROW_DEG) / sin(theta) of the error across them (1 at NARROW_DEG and more,
    `MAX_GAIN` at most)."""
    n = len(model.points)
    if not len(pt):
        return np.ones(n)
    centres = np.array([k.pose.center for k in model.keyframes])
    u = model.points[pt] - centres[kf]
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    mean = np.zeros((n, 3))
    np.add.at(mean, pt, u)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    dev = np.arccos(np.clip(np.einsum("ij,ij->i", u, mean[pt]), -1.0, 1.0))
    spread = np.zeros(n)
    np.maximum.at(spread, pt, 2 * dev)  # two rays: exactly their angle
    gain = np.sin(np.radians(NARROW_DEG)) / np.maximum(np.sin(spread), 1e-9)
    return np.clip(gain, 1.0, MAX_GAIN)
