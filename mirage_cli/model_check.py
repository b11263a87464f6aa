"""The model's own error, measured at build time: leave one keyframe out. Pure core.

Each keyframe's pose is known (the pose file or the board). Triangulate the points it sees
from the *other* keyframes alone, solve its pose from them as the tracker would (Mirage-S
from the given pose, the same covariance), and compare with the pose it was given. The
keyframes are frames with a known truth, so this says how far a tracked pose will be off
with this model, these poses, this camera and these pixels, against the uncertainty the
tracker would report: on rendered scenes the two agree; on real photographs (calibration
error, the poses' own error, JPEG, focus) the error was about twice the prediction
(dtu_scan37). The ratio, `error_scale`, widens every tracked pose's shared (model)
covariance (`track.frame_covariances`), so the sigma column keeps its promise.

A keyframe whose pose disagrees with the others' points by many sigmas is named: a wrong
row in the pose file, or a view of another scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .pose import Pose
from .solver import RefineOptions, sigmas, solve_pose

MIN_POINTS = 15  # fewer points seen by the other keyframes: that keyframe is not checked
CHI2_3_MEDIAN_OVER_3 = 0.7887  # median of chi-square(3) / 3: e^2 / sigma^2 of a 3-vector
SUSPECT = 4.0  # a keyframe this many sigmas off is named (ratio^2 ~ chi2(6)/6 when the
# model is right: P(ratio > 4) < 1e-15; the sample's 36 reach 1.5, one 1 cm off 4.6)


@dataclass
class KeyframeCheck:
    index: int
    points: int
    error_m: float
    error_deg: float
    sigma_m: float
    sigma_deg: float

    @property
    def ratio(self) -> float:
        """RMS of the position and rotation errors in their sigmas."""
        a = self.error_m / max(self.sigma_m, 1e-12)
        b = self.error_deg / max(self.sigma_deg, 1e-12)
        return float(np.sqrt(0.5 * (a * a + b * b)))


def check_keyframes(
    points_norm: np.ndarray,
    uv: np.ndarray,
    kf: np.ndarray,
    track: np.ndarray,
    poses: list[Pose],
    camera: Camera,
    max_reproj_px: float,
    covariances,
    triangulate,
) -> list[KeyframeCheck]:
    """One check per keyframe with enough points seen by two or more other keyframes.

    `points_norm` / `uv`: each observation's normalised and pixel coordinates; `kf`,
    `track`: its keyframe and 3D point. `covariances(est, n, points)` is the tracker's
    covariance of a pose (its sum is compared); `triangulate` the build's."""
    Rall = np.array([p.R for p in poses])
    tall = np.array([p.t for p in poses])
    out = []
    for k in range(len(poses)):
        mine = kf == k
        seen = np.unique(track[mine])
        other = ~mine & np.isin(track, seen)
        cnt = np.bincount(track[other], minlength=int(track.max()) + 1 if len(track) else 0)
        usable = seen[cnt[seen] >= 2]
        if len(usable) < MIN_POINTS:
            continue
        sel = other & np.isin(track, usable)
        ids, local = np.unique(track[sel], return_inverse=True)
        X = triangulate(points_norm[sel], Rall[kf[sel]], tall[kf[sel]], local, len(ids))
        # observations of the other keyframes must still agree with the new points
        Xo = X[local]
        proj = np.empty((int(sel.sum()), 2))
        kfs = kf[sel]
        for j in np.unique(kfs):
            m = kfs == j
            proj[m] = camera.project(Xo[m], poses[j])
        bad = np.linalg.norm(proj - uv[sel], axis=1) > max_reproj_px
        bad_pt = np.bincount(local[bad], minlength=len(ids)) > 0
        front = poses[k].transform(X)[:, 2] > 0
        good = ~bad_pt & front & np.all(np.isfinite(X), axis=1)
        if good.sum() < MIN_POINTS:
            continue
        # this keyframe's observation of each good point
        obs = np.flatnonzero(mine & np.isin(track, ids[good]))
        pos = np.searchsorted(ids, track[obs])
        Xk, uvk = X[pos], uv[obs]
        est = solve_pose(
            Xk, uvk, camera, reference_pose=poses[k], method="mirage-s",
            refine=RefineOptions(reject_px=2.0, huber_px=0.5),
        )  # fmt: skip
        if not est.success:
            continue
        n = int(est.inliers.sum())
        res, shared = covariances(est, n, (Xk, uvk))
        sp, sr = sigmas(res + shared)
        if not (np.isfinite(sp) and np.isfinite(sr) and sp > 0 and sr > 0):
            continue
        out.append(
            KeyframeCheck(k, n, est.pose.distance_to(poses[k]), est.pose.angle_to(poses[k]),
                          sp, sr)  # fmt: skip
        )
    return out


def error_scale(checks: list[KeyframeCheck]) -> float:
    """How much larger the errors are than predicted: from the median squared ratio
    (robust to a keyframe with a wrong pose), never below 1 (a model is not trusted more
    than its residuals say). 1 without checks."""
    if len(checks) < 3:
        return 1.0
    r2 = np.array([c.ratio**2 for c in checks])
    return float(max(1.0, np.sqrt(np.median(r2) / CHI2_3_MEDIAN_OVER_3)))


def summary(checks: list[KeyframeCheck], names: list[str]) -> dict:
    """What the model file keeps (meta['check']) and the build prints."""
    if not checks:
        return {"keyframes": 0, "error_scale": 1.0}
    scale = error_scale(checks)
    suspects = [names[c.index] for c in checks if c.ratio > SUSPECT * scale]
    return {
        "keyframes": len(checks),
        "error_scale": round(scale, 3),
        "median_error_m": float(np.median([c.error_m for c in checks])),
        "median_error_deg": float(np.median([c.error_deg for c in checks])),
        "median_sigma_m": float(np.median([c.sigma_m for c in checks])),
        "suspects": suspects,
    }
