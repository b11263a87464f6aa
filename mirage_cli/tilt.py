"""Keyframe features as a camera higher up would see them (affine view simulation).

A model made on foot sees the landmark's sides from near eye level; a drone 30-60 deg
higher sees the same sides foreshortened along the image's vertical by cos(elevation)
(0.87 at 30 deg, 0.71 at 45, 0.5 at 60), past what SIFT's descriptors tolerate (a tilt of
about 1.4). As ASIFT does on both images, but once and on the model's side only: each
keyframe is squashed along the direction of W's up axis in its image by the tilts
`TILTS`, features are detected in the squashed images, mapped back, and linked to the 3D
point of the keyframe's own feature they coincide with. The tracker matches them only
when the predicted view is well above the keyframe's, or when a lost frame found no pose
with the keyframes as they are.

Pure core: images and arrays in, arrays out.
"""

from __future__ import annotations

import cv2
import numpy as np

from .features import Detector, detect
from .pose import Pose

TILTS = (0.71, 0.5)  # 45 and 60 deg above a level keyframe (ASIFT's sqrt(2) steps)
LINK_PX = 2.0  # a squashed-view feature mapped back this close to a linked one is it
ABOVE_DEG = 20.0  # the predicted view this much higher than a keyframe: match its tilts


def up_angle(pose: Pose) -> float:
    """Angle (rad) of W's up axis in the keyframe's image, from the image's -y axis."""
    up = pose.R[:, 2]  # W's z in camera coordinates
    return float(np.arctan2(up[0], -up[1]))


def camera_roll_deg(pose: Pose) -> float:
    """`up_angle` in degrees: how far a camera is rolled; NaN for a camera looking within
    20 deg of straight up or down (W's up nearly along its axis: no roll to speak of)."""
    up = pose.R[:, 2]
    if np.hypot(up[0], up[1]) < np.sin(np.radians(20.0)):
        return float("nan")
    return float(np.degrees(up_angle(pose)))


def tilted_features(
    gray: np.ndarray,
    pose: Pose,
    keypoints: np.ndarray,
    point_ids: np.ndarray,
    detector: Detector,
    tilts=TILTS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(keypoints in the keyframe's pixels, descriptors, point ids) of the features of the
    keyframe's squashed views that land on one of its linked features."""
    linked = point_ids >= 0
    empty = (np.zeros((0, 2), np.float32), np.zeros((0, 0)), np.zeros(0, np.int32))
    if linked.sum() == 0:
        return empty
    from scipy.spatial import cKDTree  # here: `track` imports this module, not scipy's

    tree = cKDTree(keypoints[linked])
    pids = point_ids[linked]
    h, w = gray.shape[:2]
    phi = up_angle(pose)
    out_k, out_d, out_p = [], [], []
    for t in tilts:
        A = squash_matrix(phi, t, w, h)
        size = (w, h) if abs(phi) > np.radians(5) else (w, int(np.ceil(h * t)))
        sigma = 0.8 * np.sqrt(1 / t**2 - 1)  # ASIFT's anti-aliasing before the squash
        img = _blur_along(gray, phi, sigma)
        sq = cv2.warpAffine(img, A, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        kp, desc = detect(sq, detector)
        if not len(kp):
            continue
        back = _apply(cv2.invertAffineTransform(A), kp)
        d, j = tree.query(back, distance_upper_bound=LINK_PX)
        hit = np.isfinite(d)
        out_k.append(back[hit].astype(np.float32))
        out_d.append(desc[hit])
        out_p.append(pids[j[hit]].astype(np.int32))
    if not out_k:
        return empty
    return np.concatenate(out_k), np.concatenate(out_d), np.concatenate(out_p)


def squash_matrix(phi: float, t: float, w: int, h: int) -> np.ndarray:
    """2x3 affine: squash by t along the image direction at angle `phi` from -y (W's up),
    about the image centre (a level keyframe: a plain vertical squash from the top)."""
    if abs(phi) <= np.radians(5):
        return np.array([[1.0, 0.0, 0.0], [0.0, t, 0.5 * t - 0.5]])
    u = np.array([np.sin(phi), -np.cos(phi)])  # up in the image
    M = np.eye(2) - (1 - t) * np.outer(u, u)
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    return np.column_stack([M, c - M @ c])


def _blur_along(gray: np.ndarray, phi: float, sigma: float) -> np.ndarray:
    """Gaussian blur of `sigma` px along the up direction only (near-level keyframes:
    along y)."""
    if abs(phi) <= np.radians(5):
        return cv2.GaussianBlur(gray, (1, 0), sigmaX=0.01, sigmaY=sigma)
    k = int(np.ceil(3 * sigma)) * 2 + 1
    x = np.arange(k) - k // 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    u = np.array([np.sin(phi), -np.cos(phi)])
    kernel = np.zeros((k, k), np.float32)
    for i, v in zip(x, g, strict=True):  # a line kernel along u (k taps)
        px, py = int(round(k // 2 + i * u[0])), int(round(k // 2 + i * u[1]))
        kernel[py, px] += v
    return cv2.filter2D(gray, -1, kernel)


def _apply(A: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts.astype(np.float64) @ A[:, :2].T + A[:, 2]


def elevation_deg(center: np.ndarray, target: np.ndarray) -> float:
    """How high above `target` a camera centre is seen from it (deg; the model's z is up)."""
    d = np.asarray(center, float) - target
    return float(np.degrees(np.arctan2(d[2], np.hypot(d[0], d[1]))))
