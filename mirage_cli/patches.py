"""Model points found in a frame by their keyframe patches (normalised cross-correlation).

A SIFT keypoint of a small, far landmark is placed to about a pixel: it comes from an
upsampled box of a noisy, blurred frame. The keyframe that saw the point from close up
holds its appearance at three or more times the detail. Warped into the frame as the
pose estimate predicts (the affine map of a small plane through the point: the face it
lies on, by its neighbours' normal, or else a plane facing the keyframe), blurred to the
frame's scale, and correlated within a few pixels of the prediction, it places the point
to a fraction of a pixel, and it finds points SIFT did not (far random scenes, at the
true pose: 160-190 points within 0.2 px median against 50-60 SIFT inliers at ~1 px; from
55 deg above the keyframes, 250-470 points at 0.2-0.4 px where SIFT matched 20-50).

Pure core: arrays in, arrays out.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .camera import Camera
from .pose import Pose
from .refine import _jit  # numba with the solver kernels' on-disk cache

HALF = 5  # template half size (px of the frame): 11 x 11
PLANE_PX = 8.0  # the plane's offsets, in keyframe pixels, that fix the affine map
NORMAL_NEIGHBOURS = 12  # model points whose scatter gives a point's normal


def keyframe_pyramid(gray: np.ndarray, levels: int = 4) -> list[np.ndarray]:
    """Levels of a keyframe image, each half the last (the warp picks the level nearest
    its scale, so a far frame's template is not aliased)."""
    out = [gray]
    for _ in range(levels - 1):
        out.append(cv2.pyrDown(out[-1]))
    return out


def point_normals(points: np.ndarray, k: int = NORMAL_NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:
    """Each model point's surface normal (unit, unsigned) and how flat its `k` nearest
    points lie (smallest over middle eigenvalue of their scatter: ~0 on a face, large
    across an edge). A view 30-60 deg above the keyframes sees a face foreshortened in a
    way a plane facing the keyframe does not predict (480-above scene, 55 deg up, at the
    true pose: 8-150 points placed at 0.4-2 px that way, 250-470 at 0.2-0.4 px with the
    faces' own normals)."""
    n = len(points)
    if n < k + 1:
        return np.full((n, 3), np.nan), np.full(n, np.inf)
    _, nb = cKDTree(points).query(points, k)
    Q = points[nb] - points[nb].mean(axis=1, keepdims=True)
    w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", Q, Q))
    return v[:, :, 0], w[:, 0] / np.maximum(w[:, 1], 1e-18)


def affine_maps(
    camera: Camera, X: np.ndarray, kf_pose: Pose, pose: Pose, kf_camera=None, normals=None
):
    """Per point: the keyframe pixel of X, its frame pixel, and the 2x2 map from keyframe
    to frame pixels of a small plane through X, facing the keyframe or with the given
    `normals` (N,3) where finite: (N,2), (N,2), (N,2,2)."""
    kc = kf_camera or camera
    ray = X - kf_pose.center
    depth = np.linalg.norm(ray, axis=1, keepdims=True)
    ray = ray / depth
    if normals is not None:
        ray = np.where(np.isfinite(normals).all(axis=1, keepdims=True), normals, ray)
    up = np.array([0.0, 0.0, 1.0])
    e1 = np.cross(ray, up)
    along = np.linalg.norm(e1, axis=1) < 1e-3  # a normal along z: another axis for the plane
    e1[along] = np.cross(ray[along], np.array([1.0, 0.0, 0.0]))
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-9)
    e2 = np.cross(ray, e1)
    d = depth * (PLANE_PX / kc.K[0, 0])
    P = np.concatenate([X, X + d * e1, X + d * e2])
    n = len(X)
    pk = kc.project(P, kf_pose).reshape(3, n, 2)
    pc = camera.project(P, pose).reshape(3, n, 2)
    Dk = np.stack([pk[1] - pk[0], pk[2] - pk[0]], axis=2)  # columns: the two offsets
    Dc = np.stack([pc[1] - pc[0], pc[2] - pc[0]], axis=2)
    A = Dc @ np.linalg.inv(Dk)
    return pk[0], pc[0], A


def templates(pyramid: list[np.ndarray], pk: np.ndarray, A: np.ndarray, half: int = HALF):
    """The keyframe's appearance of each point as the frame would see it: (N, T, T) float32,
    centred on the point, from the pyramid level whose scale the map's is nearest."""
    n, t = len(pk), 2 * half + 1
    g = np.arange(-half, half + 1, dtype=np.float64)
    grid = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)  # (T*T, 2) x, y
    Ainv = np.linalg.inv(A)
    scale = np.sqrt(np.abs(np.linalg.det(A)))  # frame px per keyframe px
    level = np.clip(np.floor(np.log2(1.0 / np.maximum(scale, 1e-6))), 0, len(pyramid) - 1)
    level = level.astype(int)
    out = np.zeros((n, t, t), np.float32)
    for lv in np.unique(level):
        idx = np.flatnonzero(level == lv)
        f = 0.5**lv  # pyrDown keeps the even pixels: x_l = x f
        src = (pk[idx, None, :] + grid[None] @ Ainv[idx].transpose(0, 2, 1)) * f
        mx = src[..., 0].astype(np.float32).reshape(len(idx) * t, t)
        my = src[..., 1].astype(np.float32).reshape(len(idx) * t, t)
        warped = cv2.remap(pyramid[lv], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out[idx] = warped.reshape(len(idx), t, t).astype(np.float32)
    return out


def correlate(gray: np.ndarray, centres, tpl: np.ndarray, reach: int, min_std: float = 3.0):
    """Where each template best matches the frame within `reach` px of its centre: (N,2)
    subpixel positions and the peak NCC (N,); NaN where the window leaves the frame, the
    template is too plain to place (grey-level deviation under `min_std`) or the peak sits
    on the search's edge (the point is elsewhere)."""
    n, t = tpl.shape[:2]
    half = t // 2
    w = t + 2 * reach
    c = np.rint(centres).astype(int)
    h, wd = gray.shape[:2]
    x0, y0 = c[:, 0] - half - reach, c[:, 1] - half - reach
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + w <= wd) & (y0 + w <= h)
    inside &= tpl.reshape(n, -1).std(axis=1) >= min_std
    pos = np.full((n, 2), np.nan)
    peak = np.full(n, np.nan)
    idx = np.flatnonzero(inside)
    if not len(idx):
        return pos, peak
    tp = tpl[idx] - tpl[idx].mean(axis=(1, 2), keepdims=True)
    tn = np.sqrt((tp**2).sum(axis=(1, 2)))
    ncc = np.empty((len(idx), 2 * reach + 1, 2 * reach + 1), np.float32)
    _ncc_search(np.ascontiguousarray(gray), x0[idx], y0[idx], tp, tn, ncc)
    s = 2 * reach + 1
    flat = ncc.reshape(len(idx), -1)
    k = flat.argmax(axis=1)
    ky, kx = k // s, k % s
    interior = (kx > 0) & (kx < s - 1) & (ky > 0) & (ky < s - 1)
    m = np.arange(len(idx))
    kxc, kyc = np.clip(kx, 1, s - 2), np.clip(ky, 1, s - 2)

    def vertex(a, b, cc):
        den = a - 2 * b + cc
        return np.where(den < 0, 0.5 * (a - cc) / np.where(den < 0, den, -1), 0.0)

    dx = vertex(ncc[m, kyc, kxc - 1], ncc[m, kyc, kxc], ncc[m, kyc, kxc + 1])
    dy = vertex(ncc[m, kyc - 1, kxc], ncc[m, kyc, kxc], ncc[m, kyc + 1, kxc])
    got = np.stack([x0[idx] + half + kx + dx, y0[idx] + half + ky + dy], axis=1)
    pos[idx[interior]] = got[interior]
    peak[idx[interior]] = flat[m, k][interior]
    return pos, peak


@_jit
def _ncc_search(gray, x0, y0, tp, tn, out):
    """out[i, dy, dx]: normalised cross-correlation of zero-mean template tp[i] (its norm
    tn[i]) with the frame at (x0[i] + dx, y0[i] + dy), every shift of the search (the
    window's sums from its integral images)."""
    m, t = tp.shape[0], tp.shape[1]
    s = out.shape[1]
    w = t + s - 1
    n = t * t
    ii = np.zeros((w + 1, w + 1))
    i2 = np.zeros((w + 1, w + 1))
    for i in range(m):
        for a in range(w):
            row = 0.0
            row2 = 0.0
            for b in range(w):
                v = float(gray[y0[i] + a, x0[i] + b])
                row += v
                row2 += v * v
                ii[a + 1, b + 1] = ii[a, b + 1] + row
                i2[a + 1, b + 1] = i2[a, b + 1] + row2
        for dy in range(s):
            for dx in range(s):
                si = ii[dy + t, dx + t] - ii[dy, dx + t] - ii[dy + t, dx] + ii[dy, dx]
                si2 = i2[dy + t, dx + t] - i2[dy, dx + t] - i2[dy + t, dx] + i2[dy, dx]
                sc = 0.0
                for a in range(t):
                    for b in range(t):
                        sc += float(gray[y0[i] + dy + a, x0[i] + dx + b]) * tp[i, a, b]
                den = np.sqrt(max(si2 - si * si / n, 0.0)) * tn[i]
                out[i, dy, dx] = sc / den if den > 1e-6 else 0.0
