"""Random scene families: landmarks, lighting, cameras and paths drawn from a seed.

A figure measured on one hand-made scene says how well the tracker fits that scene. A
family draws the whole scene at random (the landmark's shape and size, real photographs on
its faces, the floor, the light and its drift, an occluder, blur and noise, the camera's
intrinsics and distortion, the keyframes' and the video's distance and height), so the
seeds used while tuning can be kept apart from the seeds that are reported.

- near: the video orbits 0.8-2 m from the landmark (the keyframes from elsewhere);
- far: the video is 3-5 m away, the landmark 50-120 px tall; keyframes 1-1.5 m away;
- above: the video looks down from 30-60 deg above the horizon; keyframes at 0-20 deg.

Pure core: a `FamilyScene` holds the scene, camera, keyframe poses and the video path;
`synth_cli` renders and writes them exactly as the default scene.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np

from .camera import Camera, fold_radius
from .pose import Pose, look_at, matrix_from_rpy
from .render import Cylinder, Rect, Scene, random_texture, stable_rng
from .synth import Disk

FAMILIES = ("near", "far", "above")
LENS_FOLD_MARGIN = 1.05  # a drawn lens grows at least this far past the corners

# skimage.data's bundled photographs with texture enough to be a printed or painted face
# (silhouettes, colour wheels and tiny images left out)
PHOTOS = (
    "astronaut", "brick", "camera", "chelsea", "coffee", "grass", "gravel", "rocket",
    "immunohistochemistry", "hubble_deep_field", "coins", "page", "text", "clock", "retina",
)  # fmt: skip


@functools.cache
def photo(name: str) -> np.ndarray:
    """A bundled photograph as uint8 BGR (grey ones tinted later)."""
    try:
        from skimage import data
    except ImportError as e:  # pragma: no cover - scikit-image is a dependency
        raise RuntimeError("random scenes need scikit-image (pip install scikit-image)") from e
    img = np.asarray(getattr(data, name)())
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3].astype(np.uint8)
    return np.ascontiguousarray(img[..., ::-1])


def photo_texture(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A w x h texel texture cut from a random photograph (random crop, tint, gain); faces
    larger than the photo's resolution get it magnified, as a print would. A crop with
    next to no texture (sky, a plain wall of the photo) is drawn again: a landmark worth
    tracking has something on each face."""
    best, best_e = None, -1.0
    for _ in range(6):
        img = photo(PHOTOS[int(rng.integers(len(PHOTOS)))]).astype(np.float32)
        H, W = img.shape[:2]
        aspect = w / h
        ch = int(rng.uniform(0.55, 1.0) * min(H, W / aspect))
        cw = max(8, int(ch * aspect))
        ch = max(8, min(ch, H))
        cw = min(cw, W)
        y0, x0 = int(rng.integers(0, H - ch + 1)), int(rng.integers(0, W - cw + 1))
        crop = img[y0 : y0 + ch, x0 : x0 + cw]
        if rng.random() < 0.5:
            crop = crop[:, ::-1]
        tint = rng.uniform(0.75, 1.15, 3).astype(np.float32)
        crop = crop * tint * rng.uniform(0.8, 1.1) + rng.uniform(-15, 15)
        e = texture_energy(crop)
        if e > best_e:
            best, best_e = crop, e
        if e >= MIN_TEXTURE:
            break
    out = cv2.resize(best, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(out, 0, 255).astype(np.uint8)


MIN_TEXTURE = 0.08  # share of strong gradients a face's photograph needs (see below)


def texture_energy(img: np.ndarray) -> float:
    """Share of pixels with a strong gradient (Sobel > 40) at 256 px wide: photographs
    score 0.1-0.9, a plain crop near 0."""
    g = cv2.cvtColor(np.clip(img, 0, 255).astype(np.uint8), cv2.COLOR_BGR2GRAY)
    g = cv2.resize(g, (256, max(8, round(256 * g.shape[0] / g.shape[1]))), cv2.INTER_AREA)
    g = g.astype(np.float32)
    m = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    return float(np.mean(m > 40))


# --------------------------------------------------------------------------------------
# the landmark
# --------------------------------------------------------------------------------------
@dataclass
class Box:
    center: np.ndarray  # of the footprint, on its bottom face (m, W)
    size: np.ndarray  # (length, width, height)
    yaw: float  # rad about W z


@dataclass
class Drum:
    center: np.ndarray  # (x, y)
    radius: float
    z0: float
    z1: float


@dataclass
class Landmark:
    boxes: list[Box]
    drums: list[Drum]

    @property
    def height(self) -> float:
        return max([b.center[2] + b.size[2] for b in self.boxes] + [d.z1 for d in self.drums])

    def samples(self, step: float) -> np.ndarray:
        """Points over the outer surface (for visibility): box sides and tops, drum sides."""
        pts = []
        for b in self.boxes:
            hx, hy, hz = b.size / 2
            xs = np.arange(-hx, hx + 1e-9, step)
            ys = np.arange(-hy, hy + 1e-9, step)
            zs = np.arange(0, 2 * hz + 1e-9, step)
            local = [
                np.stack(np.meshgrid(X, Y, Z, indexing="ij"), -1).reshape(-1, 3)
                for X, Y, Z in [(xs, ys, [2 * hz]), ([-hx, hx], ys, zs), (xs, [-hy, hy], zs)]
            ]
            P = np.concatenate(local) @ _yaw(b.yaw).T + b.center
            pts.append(P)
        for d in self.drums:
            th, zz = np.meshgrid(
                np.arange(0, 2 * np.pi, step / d.radius), np.arange(d.z0, d.z1 + 1e-9, step)
            )
            pts.append(
                np.column_stack(
                    [
                        d.center[0] + d.radius * np.cos(th.ravel()),
                        d.center[1] + d.radius * np.sin(th.ravel()),
                        zz.ravel(),
                    ]
                )
            )
        return np.concatenate(pts)


def _yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def random_landmark(rng: np.random.Generator, height: float) -> Landmark:
    """Boxes, a stack of boxes or a drum (with a box), about `height` metres tall."""
    kind = ["boxes", "stack", "drum"][int(rng.integers(3))]
    boxes: list[Box] = []
    drums: list[Drum] = []
    if kind == "drum":
        r = height * rng.uniform(0.22, 0.4)
        drums.append(Drum(np.zeros(2), r, 0.0, height))
        if rng.random() < 0.6:  # a box beside it, lower
            s = np.array([rng.uniform(0.6, 1.2), rng.uniform(0.5, 1.0), rng.uniform(0.3, 0.6)])
            s *= height
            a = rng.uniform(0, 2 * np.pi)
            off = (r + s[0] / 2 + 0.005) * np.array([np.cos(a), np.sin(a)])
            boxes.append(Box(np.array([off[0], off[1], 0.0]), s, a))
        return Landmark(boxes, drums)
    n = 2 if kind == "boxes" else int(rng.integers(2, 4))
    base_h = height * (rng.uniform(0.5, 0.7) if n > 1 else 1.0)
    base = np.array([rng.uniform(0.7, 1.5) * height, rng.uniform(0.5, 1.0) * height, base_h])
    yaw = rng.uniform(0, np.pi)
    boxes.append(Box(np.zeros(3), base, yaw))
    z, top = base_h, base
    for _ in range(n - 1):
        h = (height - z) if kind == "stack" else (height - base_h)
        h = max(h / (1 if kind == "boxes" else (n - len(boxes))), 0.1 * height)
        s = np.array([top[0] * rng.uniform(0.4, 0.8), top[1] * rng.uniform(0.5, 0.9), h])
        room = (top[:2] - s[:2]) / 2
        off = _yaw(yaw)[:2, :2] @ (rng.uniform(-1, 1, 2) * room)
        boxes.append(Box(np.array([off[0], off[1], z]), s, yaw + rng.uniform(-0.3, 0.3)))
        z, top = z + h, s
        if kind == "boxes":
            break
    return Landmark(boxes, drums)


def _shade(normal, light) -> float:
    return float(0.5 + 0.5 * max(0.0, float(np.dot(normal, light))))


def _face_texture(rng, w_m: float, h_m: float, texel: float) -> np.ndarray:
    tw, th = max(16, int(round(w_m / texel))), max(16, int(round(h_m / texel)))
    if rng.random() < 0.85:
        return photo_texture(rng, tw, th)
    return random_texture(rng, tw, th, density=1.0, scale=max(1.0, 0.001 / texel * 2))


def landmark_surfaces(lm: Landmark, seed: int, light: np.ndarray, texel: float) -> list:
    """Textured surfaces of the landmark: four sides and a top per box, a side and a cap
    per drum, each with a photograph of its own."""
    out = []
    for k, b in enumerate(lm.boxes):
        R = _yaw(b.yaw)
        hx, hy, h = b.size[0] / 2, b.size[1] / 2, b.size[2]
        c = b.center + np.array([0.0, 0.0, h / 2])
        up = np.array([0.0, 0.0, 1.0])
        for label, n_local, half in [
            ("+x", np.array([1.0, 0, 0]), hx),
            ("-x", np.array([-1.0, 0, 0]), hx),
            ("+y", np.array([0, 1.0, 0]), hy),
            ("-y", np.array([0, -1.0, 0]), hy),
        ]:
            n = R @ n_local
            eu = np.cross(-n, up)
            ev = -up
            wu = 2 * (hy if label in ("+x", "-x") else hx)
            origin = c + n * half - eu * wu / 2 - ev * h / 2
            rng = stable_rng(seed, f"box{k}{label}")
            tex = _face_texture(rng, wu, h, texel)
            shade = _shade(n, light)
            out.append(Rect(f"box{k}{label}", origin, eu, ev, (wu, h), texel, tex, shade))
        eu, ev = R @ np.array([1.0, 0, 0]), R @ np.array([0, -1.0, 0])
        origin = b.center + np.array([0, 0, h]) - eu * hx + R @ np.array([0, hy, 0])
        tex = _face_texture(stable_rng(seed, f"box{k}top"), 2 * hx, 2 * hy, texel)
        out.append(
            Rect(f"box{k}top", origin, eu, ev, (2 * hx, 2 * hy), texel, tex, _shade(up, light))
        )
    for k, d in enumerate(lm.drums):
        circ, h = 2 * np.pi * d.radius, d.z1 - d.z0
        tex = _face_texture(stable_rng(seed, f"drum{k}"), circ, h, texel)
        out.append(
            Cylinder(f"drum{k}", tuple(d.center), d.radius, d.z0, d.z1, texel, tex, light=light)
        )
        n = int(2 * d.radius / texel)
        cap = _face_texture(stable_rng(seed, f"drum{k}cap"), 2 * d.radius, 2 * d.radius, texel)
        out.append(
            Disk(
                f"drum{k}cap", tuple(d.center), d.radius, d.z1, 2 * d.radius / n,
                cv2.resize(cap, (n, n)), _shade(np.array([0, 0, 1.0]), light),
            )
        )  # fmt: skip
    return out


def _floor(rng: np.random.Generator, seed: int, half: float) -> tuple[Rect, str]:
    """Plain paint, a tiled pattern, or grass / gravel (photographs repeated)."""
    kind = ["plain", "tiled", "grass"][int(rng.integers(3))]
    g = 2 * half
    if kind == "plain":
        n = 256
        base = rng.integers(70, 190, 3)
        low = cv2.resize(rng.normal(0, 1, (8, 8, 3)), (n, n), interpolation=cv2.INTER_CUBIC)
        tex = np.clip(base + 8 * low, 0, 255).astype(np.uint8)
    else:
        period = rng.uniform(0.4, 1.2)
        n = 256
        if kind == "tiled":
            tile = random_texture(stable_rng(seed, "floor-tile"), n, n, density=0.6, scale=2)
        else:
            tile = (
                photo_texture(rng, n, n)
                if rng.random() < 0.3
                else cv2.resize(photo(["grass", "gravel"][int(rng.integers(2))]), (n, n))
            )
        reps = int(np.ceil(g / period))
        tex = np.tile(tile, (reps, reps, 1))
        g = reps * period
    rect = Rect(
        "ground", (-g / 2, g / 2, 0.0), (1.0, 0, 0), (0, -1.0, 0), (g, g), g / tex.shape[1],
        tex, 0.85,
    )  # fmt: skip
    return rect, kind


# --------------------------------------------------------------------------------------
# camera and path
# --------------------------------------------------------------------------------------
def random_camera(rng: np.random.Generator) -> Camera:
    """A 640x480 camera: focal length 440-700 px, principal point off centre by up to 12
    px, barrel or mild pincushion distortion that grows out to the image's corners (a
    barrel term that folds back inside them, as k1 -0.3 at 440 px does, renders pixels
    with no ray: `camera.beyond_fold`; such a draw is drawn again from a generator of its
    own, so the scene's other draws stay as they were)."""
    fx = rng.uniform(440, 700)
    K = np.array(
        [
            [fx, 0.0, 319.5 + rng.uniform(-12, 12)],
            [0.0, fx * rng.uniform(0.99, 1.01), 239.5 + rng.uniform(-12, 12)],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = np.array(
        [
            rng.uniform(-0.3, 0.05),
            rng.uniform(-0.02, 0.1),
            rng.uniform(-1e-3, 1e-3),
            rng.uniform(-1e-3, 1e-3),
            0.0,
        ]
    )
    cam = Camera(K, dist, 640, 480)
    corners = np.array([[0, 0], [639, 0], [0, 479], [639, 479]], float)
    reach = np.hypot(*((corners - K[:2, 2]) / np.diag(K)[:2]).T).max()
    attempt = 0
    while fold_radius(cam) < LENS_FOLD_MARGIN * reach:
        attempt += 1
        sub = np.random.default_rng([int(fx * 1e6), attempt])
        dist[:2] = sub.uniform(-0.3, 0.05), sub.uniform(-0.02, 0.1)
        cam = Camera(K, dist, 640, 480)
    return cam


@dataclass
class FamilyPath:
    """An arc around the landmark: radius, height and heading wobble, a random sweep and
    direction, optionally a look-away stretch."""

    duration_s: float
    radius_m: float
    height_m: float
    target: np.ndarray
    start_rad: float
    sweep_rad: float  # signed: the direction
    wobble: float  # share of the radius
    look_away_s: tuple[float, float] | None = None
    look_away_deg: float = 100.0
    phase: np.ndarray = field(default_factory=lambda: np.zeros(6))

    def pose(self, t: float) -> Pose:
        T, ph = self.duration_s, self.phase
        s = t / T
        az = self.start_rad + self.sweep_rad * (s + 0.04 * np.sin(2 * np.pi * s * 1.3 + ph[0]))
        r = self.radius_m * (1 + self.wobble * np.sin(2 * np.pi * t / 3.7 + ph[1]))
        h = self.height_m + self.wobble * self.radius_m * 0.5 * np.sin(2 * np.pi * t / 4.3 + ph[2])
        C = np.array([r * np.cos(az), r * np.sin(az), max(h, 0.15)])
        base = look_at(C, self.target)
        yaw = np.radians(3.0 * np.sin(2 * np.pi * t / 2.3 + ph[3]))
        if self.look_away_s is not None:
            yaw += np.radians(self.look_away_deg) * _ramp(t, *self.look_away_s)
        pitch = np.radians(2.0 * np.sin(2 * np.pi * t / 3.1 + ph[4]))
        roll = np.radians(3.0 * np.sin(2 * np.pi * t / 2.7 + ph[5]))
        R_wc = matrix_from_rpy(0, 0, yaw) @ base.R_wc @ matrix_from_rpy(pitch, 0, roll)
        return Pose.from_center(R_wc, C)

    def exposure_poses(self, t: float, n: int, exposure_s: float) -> list[Pose]:
        if n <= 1:
            return [self.pose(t)]
        return [self.pose(t + exposure_s * (k / (n - 1) - 0.5)) for k in range(n)]

    def desired_path(self) -> dict:
        return {
            "type": "circle",
            "center_m": [0.0, 0.0],
            "radius_m": float(self.radius_m),
            "height_m": float(self.height_m),
            "direction": "ccw" if self.sweep_rad > 0 else "cw",
            "look_at_m": [float(v) for v in self.target],
        }


def _ramp(t: float, a: float, b: float, ramp: float = 0.35) -> float:
    def smooth(x):
        x = np.clip(x, 0, 1)
        return x * x * (3 - 2 * x)

    return float(min(smooth((t - a) / ramp), smooth((b - t) / ramp)))


# --------------------------------------------------------------------------------------
# the family scene
# --------------------------------------------------------------------------------------
@dataclass
class FamilyScene:
    family: str
    seed: int
    scene: Scene  # what the keyframes see
    video_scene: Scene  # the same with the occluder, if any
    camera: Camera
    keyframes: list[tuple[str, Pose]]
    path: FamilyPath
    landmark: Landmark
    occluders: list
    noise: float
    motion_blur: int
    gain: tuple[float, float, float]  # lighting drift: mean, amplitude, period (s)
    recipe: dict

    def gain_at(self, t: float) -> float:
        m, a, p = self.gain
        return float(m + a * np.sin(2 * np.pi * t / p))

    def samples(self) -> np.ndarray:
        return self.landmark.samples(max(0.01, self.landmark.height / 30))


def _elevated(radius_m: float, elevation_deg: float, target_z: float) -> tuple[float, float]:
    """(horizontal radius, height) of a camera `radius_m` from the target, that far above."""
    e = np.radians(elevation_deg)
    return radius_m * np.cos(e), target_z + radius_m * np.sin(e)


def _family_geometry(family: str, rng, f: float) -> tuple[float, float, float, float, float]:
    """(landmark height, video distance, keyframe distance, video elevation, keyframe
    elevation) of a family's scene, drawn from `rng` (focal length `f` px)."""
    if family == "far":
        d_video = rng.uniform(3.0, 5.0)
        height = float(np.clip(rng.uniform(50, 120) * d_video / f, 0.3, 2.0))
        d_kf = rng.uniform(1.0, 1.5)
        e_video, e_kf = rng.uniform(0, 20), rng.uniform(0, 20)
    elif family == "near":
        height = rng.uniform(0.3, 1.0)
        d_video = rng.uniform(0.8, 2.0)
        d_kf = d_video * rng.uniform(0.75, 1.4)
        e_video, e_kf = rng.uniform(-5, 25), rng.uniform(0, 25)
    else:
        height = rng.uniform(0.3, 1.0)
        d_video = rng.uniform(1.2, 2.5)
        d_kf = d_video * rng.uniform(0.75, 1.25)
        e_video, e_kf = rng.uniform(30, 60), rng.uniform(0, 20)
    return height, d_video, d_kf, e_video, e_kf


def _wall(seed: int, room: float) -> Cylinder:
    """A textured wall round the room (its texture from its own seed)."""
    wall_texel = 0.012
    wall_tex = random_texture(
        stable_rng(seed, "wall"),
        int(2 * np.pi * room / wall_texel),
        int(3.0 / wall_texel),
        density=0.6,
        scale=4,
    )
    return Cylinder("wall", (0.0, 0.0), room, 0.0, 3.0, wall_texel, wall_tex, True)


def _pole(rng, seed: int, path, r_v: float, span: float, light) -> Cylinder:
    """A pole the video passes behind, drawn from `rng`."""
    a = path.start_rad + path.sweep_rad * rng.uniform(0.3, 0.7)
    dist = r_v * rng.uniform(0.45, 0.7)
    rad = max(0.02, 0.05 * span)
    tex = random_texture(stable_rng(seed, "pole"), int(2 * np.pi * rad / 0.002), 1250)
    return Cylinder(
        "pole", (dist * np.cos(a), dist * np.sin(a)), rad, 0.0, 2.5, 0.002, tex, light=light
    )


def _keyframe_ring(rng, d_kf: float, e_kf: float, target) -> tuple[float, list]:
    """The keyframes: a ring at a drawn spacing (deg) and start azimuth."""
    step = rng.uniform(12, 24)
    r_kf, h_kf = _elevated(d_kf, e_kf, target[2])
    az0 = rng.uniform(0, 360)
    keyframes = [
        (f"kf_{k:03d}", look_at(
            [r_kf * np.cos(np.radians(a)), r_kf * np.sin(np.radians(a)), h_kf], target
        ))
        for k, a in enumerate(np.arange(az0, az0 + 360 - 1e-9, step))
    ]  # fmt: skip
    return step, keyframes


def _video_path(rng, duration_s, d_video, e_video, target, span) -> tuple[float, FamilyPath]:
    """The video's horizontal radius and path: a drawn sweep, look-away and wobble."""
    r_v, h_v = _elevated(d_video, e_video, target[2])
    sweep = np.radians(rng.uniform(70, 160)) * (1 if rng.random() < 0.5 else -1)
    away = None
    if rng.random() < 0.35:
        a = rng.uniform(0.45, 0.7) * duration_s
        away = (a, a + rng.uniform(0.5, 0.9))
    path = FamilyPath(
        duration_s,
        r_v,
        h_v,
        target + rng.normal(0, 0.03 * span, 3),
        rng.uniform(0, 2 * np.pi),
        sweep,
        rng.uniform(0.02, 0.08),
        away,
        phase=rng.uniform(0, 2 * np.pi, 6),
    )
    return r_v, path


def family_scene(family: str, seed: int, duration_s: float = 5.0) -> FamilyScene:
    """Draw one scene of `family` from `seed` (the same scene on every machine)."""
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; choose from {', '.join(FAMILIES)}")
    rng = stable_rng(seed, f"family-{family}")
    cam = random_camera(rng)
    f = float(cam.fy)
    height, d_video, d_kf, e_video, e_kf = _family_geometry(family, rng, f)
    lm = random_landmark(rng, height)
    extent = lm.samples(max(0.01, height / 20))
    span = float(np.ptp(extent, axis=0).max())
    # the keyframes frame the whole landmark (a person steps back for a big one)
    d_kf = max(d_kf, 1.25 * span * f / cam.height + span / 2)
    d_video = max(d_video, 0.55 * span + 0.3)
    target = np.array([0.0, 0.0, 0.5 * lm.height])
    light = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.4, 1.2)])
    light /= np.linalg.norm(light)
    texel = max(0.0006, span / 900)
    surfaces = landmark_surfaces(lm, seed, light, texel)
    bounds = np.array([extent.min(axis=0) - 0.02, extent.max(axis=0) + 0.02])
    for s in surfaces:
        s.bounds = bounds
    room = max(8.0, 2.2 * d_video + 2)
    floor, floor_kind = _floor(rng, seed, room)
    surfaces.append(floor)
    if rng.random() < 0.75:
        surfaces.append(_wall(seed, room))
    scene = Scene(surfaces)

    step, keyframes = _keyframe_ring(rng, d_kf, e_kf, target)
    r_v, path = _video_path(rng, duration_s, d_video, e_video, target, span)
    sweep, away = path.sweep_rad, path.look_away_s
    occluders = []
    video_scene = scene
    if rng.random() < 0.4:  # a pole the video passes behind
        occluders = [_pole(rng, seed, path, r_v, span, light)]
        video_scene = Scene([*surfaces, occluders[0]])
    noise = float(rng.uniform(0.5, 3.0))
    blur = 3 if rng.random() < 0.3 else 1
    gain = (float(rng.uniform(0.8, 1.1)), float(rng.uniform(0.0, 0.2)), float(rng.uniform(2, 6)))
    recipe = {
        "family": family,
        "seed": int(seed),
        "landmark": {
            "boxes": len(lm.boxes),
            "drums": len(lm.drums),
            "height_m": round(lm.height, 3),
            "span_m": round(span, 3),
        },
        "keyframes": {"count": len(keyframes), "distance_m": round(d_kf, 3),
                      "elevation_deg": round(e_kf, 1), "step_deg": round(step, 1)},
        "video": {"distance_m": round(d_video, 3), "elevation_deg": round(e_video, 1),
                  "sweep_deg": round(np.degrees(sweep), 1), "look_away": away is not None},
        "occluder": bool(occluders),
        "noise": round(noise, 2),
        "motion_blur": blur,
        "gain": [round(g, 3) for g in gain],
        "floor": floor_kind,
        "landmark_px": round(lm.height * f / d_video, 1),
    }  # fmt: skip
    return FamilyScene(
        family, seed, scene, video_scene, cam, keyframes, path, lm, occluders, noise, blur,
        gain, recipe,
    )  # fmt: skip
