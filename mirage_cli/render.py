"""A small exact ray caster for synthetic test scenes.

Rays are cast through every pixel of a *distorted* camera (pixel -> undistorted ray via
OpenCV's iterative undistortion), so perspective and lens distortion are exact rather than
approximated by warping a pinhole image. Scenes are textured rectangles and vertical
cylinders, which is all a landmark-on-the-ground scene and a chessboard need. Textures
carry mip levels so distant surfaces do not alias, and each pixel averages a 2x2 grid of
sub-pixel rays.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import cv2
import numpy as np

from .camera import Camera
from .pose import Pose


# --------------------------------------------------------------------------------------
# textures
# --------------------------------------------------------------------------------------
def stable_rng(seed: int, name: str) -> np.random.Generator:
    """Per-surface generator: the same scene for the same seed on every machine."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


def random_texture(
    rng: np.random.Generator, w: int, h: int, density: float = 1.0, scale: float = 1.0
) -> np.ndarray:
    """A feature-rich, non-repeating texture (uint8 BGR): blobs, bars, strokes and text."""
    base = rng.integers(60, 200, 3)
    low = rng.normal(0, 1, (max(2, h // 64), max(2, w // 64), 3))
    low = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
    img = np.clip(base + 35 * low, 0, 255).astype(np.uint8)
    n = int(density * w * h / (900 * scale * scale)) + 8
    kinds = rng.integers(0, 5, n)
    for k in kinds:
        col = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        s = float(scale * rng.uniform(4, 30))
        if k == 0:
            cv2.circle(img, (x, y), max(2, int(s / 2)), col, -1, cv2.LINE_AA)
        elif k == 1:
            x2, y2 = int(x + rng.uniform(-s, s)), int(y + rng.uniform(-s, s))
            cv2.rectangle(img, (x, y), (x2, y2), col, -1)
        elif k == 2:
            x2, y2 = int(x + rng.uniform(-2 * s, 2 * s)), int(y + rng.uniform(-2 * s, 2 * s))
            cv2.line(img, (x, y), (x2, y2), col, int(rng.integers(1, 4)), cv2.LINE_AA)
        elif k == 3:
            pts = np.array([x, y]) + rng.uniform(-s, s, (int(rng.integers(3, 6)), 2))
            cv2.fillPoly(img, [pts.astype(np.int32)], col, cv2.LINE_AA)
        else:
            letters = "ABCDEFGHJKLMNPQRSTUVWXYZ0123456789#%&@"
            txt = "".join(rng.choice(list(letters), int(rng.integers(1, 4))))
            cv2.putText(
                img,
                txt,
                (x, y),
                cv2.FONT_HERSHEY_SIMPLEX,
                s / 22.0,
                col,
                max(1, int(s / 12)),
                cv2.LINE_AA,
            )
    return cv2.GaussianBlur(img, (0, 0), 0.6)


def mip_levels(tex: np.ndarray, min_size: int = 8) -> list[np.ndarray]:
    """Gaussian pyramid; level L texel x_L = x_0 / 2**L (pyrDown centres on even texels)."""
    levels = [tex]
    while min(levels[-1].shape[:2]) >= 2 * min_size and len(levels) < 8:
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


# --------------------------------------------------------------------------------------
# surfaces
# --------------------------------------------------------------------------------------
@dataclass
class Rect:
    """A textured rectangle: origin corner, unit axes u (texture x) and v (texture y)."""

    name: str
    origin: np.ndarray
    eu: np.ndarray
    ev: np.ndarray
    size: tuple[float, float]  # extent along u, v in metres
    texel_m: float
    texture: np.ndarray
    shade: float = 1.0
    mips: list = field(default_factory=list)

    def __post_init__(self):
        self.origin, self.eu, self.ev = (
            np.asarray(a, float) for a in (self.origin, self.eu, self.ev)
        )
        self.normal = np.cross(self.eu, self.ev)
        self.mips = mip_levels(self.texture)

    def intersect(self, O, D):
        denom = D @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.origin - O) @ self.normal) / denom
        P = O + t[:, None] * D
        r = P - self.origin
        u, v = r @ self.eu, r @ self.ev
        ok = (t > 1e-9) & (u >= 0) & (u <= self.size[0]) & (v >= 0) & (v <= self.size[1])
        return np.where(ok, t, np.inf)

    def texcoords(self, P, D):
        """Texture coordinates in texel-edge units (texel k spans [k, k+1]), |cos|, shade."""
        r = P - self.origin
        cos = np.abs(D @ self.normal)
        return r @ self.eu / self.texel_m, r @ self.ev / self.texel_m, cos, self.shade

    def point(self, u_m: float, v_m: float) -> np.ndarray:
        return self.origin + u_m * self.eu + v_m * self.ev


@dataclass
class Cylinder:
    """Vertical cylinder side (outside, or inside for a surrounding wall)."""

    name: str
    center: tuple[float, float]
    radius: float
    z0: float
    z1: float
    texel_m: float
    texture: np.ndarray
    inside: bool = False
    light: np.ndarray | None = None
    mips: list = field(default_factory=list)

    def __post_init__(self):
        self.mips = mip_levels(self.texture)

    def intersect(self, O, D):
        ox, oy = O[0] - self.center[0], O[1] - self.center[1]
        a = D[:, 0] ** 2 + D[:, 1] ** 2
        b = 2 * (ox * D[:, 0] + oy * D[:, 1])
        c = ox * ox + oy * oy - self.radius**2
        disc = b * b - 4 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            sq = np.sqrt(disc)
            t = (-b + sq) / (2 * a) if self.inside else (-b - sq) / (2 * a)
        z = O[2] + t * D[:, 2]
        ok = (disc >= 0) & (t > 1e-9) & (z >= self.z0) & (z <= self.z1)
        return np.where(ok, t, np.inf)

    def texcoords(self, P, D):
        dx, dy = P[:, 0] - self.center[0], P[:, 1] - self.center[1]
        theta = np.mod(np.arctan2(dy, dx), 2 * np.pi)
        n = np.column_stack([dx, dy, np.zeros_like(dx)]) / self.radius
        if self.inside:
            n = -n
        cos = np.abs(np.einsum("ij,ij->i", D, n))
        shade = 1.0
        if self.light is not None:
            shade = 0.55 + 0.45 * np.clip(n @ self.light, 0, 1)
        return theta * self.radius / self.texel_m, (self.z1 - P[:, 2]) / self.texel_m, cos, shade


# --------------------------------------------------------------------------------------
# scene and renderer
# --------------------------------------------------------------------------------------
@dataclass
class Scene:
    surfaces: list
    sky_top: tuple = (235, 206, 170)  # BGR
    sky_horizon: tuple = (250, 240, 225)
    markers: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    marker_normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def sample(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup at texel-centre coordinates (N,) -> (N, 3) float32."""
    n = x.size
    w = 1024
    rows = -(-n // w)
    mx = np.zeros(rows * w, np.float32)
    my = np.zeros(rows * w, np.float32)
    mx[:n], my[:n] = x, y  # cv2.remap needs maps smaller than 32767 on each side
    smp = cv2.remap(
        tex,
        mx.reshape(rows, w),
        my.reshape(rows, w),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT,
    )
    return smp.reshape(-1, 3)[:n].astype(np.float32)


def _hits_box(O, D, bounds) -> np.ndarray:
    """Rays (slab test) that pass through an axis-aligned box [lo, hi]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (bounds[0] - O) / D
        t2 = (bounds[1] - O) / D
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return (tmax >= np.maximum(tmin, 0)) & (tmax > 0)


def _subpixel_grid(camera: Camera, aa: int) -> np.ndarray:
    """Pixel coordinates of aa x aa sub-samples per pixel, samples of a pixel contiguous."""
    offs = (np.arange(aa) + 0.5) / aa - 0.5
    ys, xs = np.mgrid[0 : camera.height, 0 : camera.width].astype(float)
    ox, oy = np.meshgrid(offs, offs)
    px = xs[..., None] + ox.ravel()
    py = ys[..., None] + oy.ravel()
    return np.stack([px.ravel(), py.ravel()], axis=1)


class Renderer:
    """Renders a Scene seen by a Camera from any Pose (uint8 BGR images)."""

    def __init__(self, scene: Scene, camera: Camera, aa: int = 2):
        self.scene, self.camera, self.aa = scene, camera, aa
        self.rays_c = camera.pixel_rays(_subpixel_grid(camera, aa))
        # angular size of one sub-sample, for mip level selection
        self.sample_angle = 1.0 / (max(camera.fx, camera.fy) * aa)

    def render(
        self, pose: Pose, noise_sigma: float = 0.0, rng=None, blur_poses: list[Pose] | None = None
    ) -> np.ndarray:
        """One frame; with `blur_poses` the exposure is averaged over them (motion blur)."""
        poses = blur_poses if blur_poses else [pose]
        acc = None
        for p in poses:
            img = self._render_float(p)
            acc = img if acc is None else acc + img
        img = acc / len(poses)
        if noise_sigma > 0:
            rng = rng if rng is not None else np.random.default_rng(0)
            img = img + rng.normal(0.0, noise_sigma, img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def visible(self, pose: Pose, points) -> np.ndarray:
        """Which world points are seen from `pose` (no surface in front of them)."""
        P = np.asarray(points, float).reshape(-1, 3)
        O = pose.center
        d = P - O
        dist = np.linalg.norm(d, axis=1)
        D = d / dist[:, None]
        first = np.full(len(P), np.inf)
        for s in self.scene.surfaces:
            first = np.minimum(first, s.intersect(O, D))
        in_front = pose.transform(P)[:, 2] > 0
        return in_front & (first >= dist - 1e-6)

    def _render_float(self, pose: Pose) -> np.ndarray:
        D = self.rays_c @ pose.R  # world directions (rows): R^T d_c
        O = pose.center
        n = len(D)
        best_t = np.full(n, np.inf)
        best_i = np.full(n, -1, np.int32)
        box_hits: dict[int, np.ndarray] = {}
        for i, s in enumerate(self.scene.surfaces):
            b = getattr(s, "bounds", None)
            if b is None:
                t = s.intersect(O, D)
                closer = t < best_t
                best_t[closer] = t[closer]
                best_i[closer] = i
                continue
            if id(b) not in box_hits:
                box_hits[id(b)] = np.flatnonzero(_hits_box(O, D, b))
            idx = box_hits[id(b)]
            t = s.intersect(O, D[idx])
            closer = t < best_t[idx]
            best_t[idx[closer]] = t[closer]
            best_i[idx[closer]] = i
        col = np.empty((n, 3), np.float32)
        miss = best_i < 0
        if miss.any():
            w = np.clip(D[miss, 2], 0, 1)[:, None]
            col[miss] = (1 - w) * np.array(self.scene.sky_horizon) + w * np.array(
                self.scene.sky_top
            )
        for i, s in enumerate(self.scene.surfaces):
            idx = np.flatnonzero(best_i == i)
            if idx.size == 0:
                continue
            Di = D[idx]
            P = O + best_t[idx, None] * Di
            tu, tv, cos, shade = s.texcoords(P, Di)
            foot = best_t[idx] * self.sample_angle / (s.texel_m * np.maximum(cos, 0.25))
            level = np.clip(np.floor(np.log2(np.maximum(foot, 1.0))), 0, len(s.mips) - 1).astype(
                int
            )
            out = np.empty((idx.size, 3), np.float32)
            for L in np.unique(level):
                m = level == L
                tex = s.mips[L]
                out[m] = sample(tex, (tu[m] - 0.5) / 2**L, (tv[m] - 0.5) / 2**L)
            shade = np.asarray(shade, np.float32)
            col[idx] = out * (shade[:, None] if shade.ndim else shade)
        aa2 = self.aa * self.aa
        img = col.reshape(-1, aa2, 3).mean(axis=1)
        return img.reshape(self.camera.height, self.camera.width, 3).astype(np.float64)
