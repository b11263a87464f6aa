"""Synthetic test scenes with exact ground truth: a textured 3D landmark, a chessboard,
keyframes circling the landmark, an orbit video path with realistic deviations, and point
scenes for the pose solver's tests and benchmark.

Pure core: builds scenes, poses and images in memory; `synth_cli` writes the files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from .boards import Board
from .camera import Camera
from .pose import Pose, look_at, matrix_from_rpy, rodrigues
from .render import Cylinder, Rect, Scene, random_texture, stable_rng

LIGHT = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])
LANDMARK_TARGET = np.array([0.0, 0.0, 0.28])  # where the keyframe and orbit cameras look

# The landmark: a base box, a smaller box on top and a cylinder beside it (metres, W frame).
BOXES = {
    "base": ((-0.30, 0.30), (-0.21, 0.21), (0.0, 0.34)),
    "upper": ((-0.26, 0.0), (-0.18, 0.07), (0.34, 0.52)),
}
CYLINDER = {"center": (0.15, 0.06), "radius": 0.09, "z": (0.34, 0.62)}
LANDMARK_BOUNDS = np.array([[-0.30, -0.21, 0.0], [0.30, 0.21, 0.62]])
TEXEL_M = 0.001
# The calibration chessboard of `mirage synth` (and so of the sample data, which the demo
# calibrates from): inner corners (cols, rows) and square side.
CALIB_BOARD, CALIB_SQUARE_M = (9, 6), 0.025


def default_camera() -> Camera:
    """The sample data's camera: a cheap 640x480 webcam with moderate barrel distortion."""
    K = np.array([[520.0, 0.0, 323.5], [0.0, 518.0, 237.2], [0.0, 0.0, 1.0]])
    return Camera(K, np.array([-0.18, 0.06, 0.0006, -0.0004, 0.0]), 640, 480)


# --------------------------------------------------------------------------------------
# landmark scene
# --------------------------------------------------------------------------------------
def _shade(normal) -> float:
    return float(0.55 + 0.45 * max(0.0, float(np.dot(normal, LIGHT))))


def weak_texture(rng: np.random.Generator, tex: np.ndarray, patches: int = 2) -> np.ndarray:
    """Plain paint with a few printed patches: the texture's own colour, smoothed flat,
    keeping `patches` squares of it (each about 30% of the shorter side), as a painted
    crate with a label or two. Few corners, mostly in the patches."""
    h, w = tex.shape[:2]
    paint = np.full_like(tex, np.median(tex.reshape(-1, 3), axis=0).astype(np.uint8))
    out = cv2.addWeighted(paint, 0.85, cv2.GaussianBlur(tex, (0, 0), 25), 0.15, 0.0)
    s = max(8, int(0.3 * min(h, w)))
    for _ in range(patches):
        y, x = int(rng.integers(0, max(1, h - s))), int(rng.integers(0, max(1, w - s)))
        out[y : y + s, x : x + s] = tex[y : y + s, x : x + s]
    return out


def _box_faces(name, bounds, seed, markers, marker_normals, lookalike=False, weak=False):
    """Four sides and the top of a box, each with its own texture and 3 corner markers
    (with `lookalike` the -x / -y sides copy the +x / +y sides: a 180-degree twin; with
    `weak` each face is plain paint with a few patches)."""
    (x0, x1), (y0, y1), (z0, z1) = bounds
    c = np.array([(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2])
    half = np.array([(x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2])
    up = np.array([0.0, 0.0, 1.0])
    faces = []
    for axis, sign, label in [
        (0, 1, "+x"),
        (0, -1, "-x"),
        (1, 1, "+y"),
        (1, -1, "-y"),
        (2, 1, "top"),
    ]:
        n = np.zeros(3)
        n[axis] = sign
        if axis == 2:
            eu, ev = np.array([1.0, 0, 0]), np.array([0, -1.0, 0])
        else:
            eu, ev = np.cross(-n, up), -up
        wu = 2 * float(abs(eu) @ half)
        wv = 2 * float(abs(ev) @ half)
        origin = c + n * half[axis] - eu * wu / 2 - ev * wv / 2
        fname = f"{name}{label}"
        twin = {"-x": "+x", "-y": "+y"}.get(label, label) if lookalike else label
        rng = stable_rng(seed, f"{name}{twin}")
        tw, th = int(round(wu / TEXEL_M)), int(round(wv / TEXEL_M))
        tex = random_texture(rng, tw, th, density=1.3)
        if weak:
            tex = weak_texture(rng, tex)
        for _ in range(3):  # X-junction markers: exact, sub-pixel-detectable 3D points
            s = 12
            kx, ky = int(rng.integers(30, tw - 30)), int(rng.integers(30, th - 30))
            tex[ky - s : ky, kx - s : kx] = 20
            tex[ky : ky + s, kx : kx + s] = 20
            tex[ky - s : ky, kx : kx + s] = 235
            tex[ky : ky + s, kx - s : kx] = 235
            markers.append(origin + kx * TEXEL_M * eu + ky * TEXEL_M * ev)
            marker_normals.append(n)
        faces.append(Rect(fname, origin, eu, ev, (wu, wv), TEXEL_M, tex, _shade(n)))
    return faces


class Disk(Rect):
    """A horizontal disc (cylinder cap): a Rect clipped to a radius."""

    def __init__(self, name, center_xy, radius, z, texel_m, texture, shade):
        cx, cy = center_xy
        super().__init__(
            name,
            (cx - radius, cy + radius, z),
            (1.0, 0, 0),
            (0, -1.0, 0),
            (2 * radius, 2 * radius),
            texel_m,
            texture,
            shade,
        )
        self.c2, self.r = np.array([cx, cy]), radius

    def intersect(self, O, D):
        t = super().intersect(O, D)
        fin = np.isfinite(t)
        P = O[:2] + t[fin, None] * D[fin, :2]
        t[np.flatnonzero(fin)[np.linalg.norm(P - self.c2, axis=1) > self.r]] = np.inf
        return t


def landmark_scene(
    seed: int = 0, floor_tile_m: float | None = None, lookalike: bool = False,
    weak: bool = False,
) -> Scene:  # fmt: skip
    """The landmark at the origin on a textured ground inside a textured round room.

    Stress options (off by default, so the default scene is unchanged): `floor_tile_m`
    makes the ground one texture tile repeated with that period (every floor feature has
    exact twins one period apart); `lookalike` gives opposite sides of the landmark the
    same texture (box sides and the two halves of the cylinder); `weak` paints the
    landmark plain with a few textured patches per face (a weakly textured landmark)."""
    surfaces, markers, normals = [], [], []
    for name, bounds in BOXES.items():
        surfaces += _box_faces(name, bounds, seed, markers, normals, lookalike, weak)
    cyl = CYLINDER
    circ = 2 * np.pi * cyl["radius"]
    h = cyl["z"][1] - cyl["z"][0]
    if lookalike:  # two identical halves: texel chosen so half the circumference is whole
        half = int(round(circ / 2 / TEXEL_M))
        texel = circ / 2 / half
        tile = random_texture(stable_rng(seed, "cylinder"), half, int(h / texel), density=1.3)
        tex, cyl_texel = np.concatenate([tile, tile], axis=1), texel
    else:
        tex = random_texture(
            stable_rng(seed, "cylinder"), int(circ / TEXEL_M), int(h / TEXEL_M), density=1.3
        )
        cyl_texel = TEXEL_M
    if weak:
        tex = weak_texture(stable_rng(seed, "cylinder-weak"), tex, patches=3)
    surfaces.append(
        Cylinder("cylinder", cyl["center"], cyl["radius"], *cyl["z"], cyl_texel, tex, light=LIGHT)
    )
    d = int(2 * cyl["radius"] / TEXEL_M)
    cap = random_texture(stable_rng(seed, "cap"), d, d)
    if weak:
        cap = weak_texture(stable_rng(seed, "cap-weak"), cap)
    surfaces.append(
        Disk(
            "cylinder-top",
            cyl["center"],
            cyl["radius"],
            cyl["z"][1],
            TEXEL_M,
            cap,
            _shade(np.array([0, 0, 1])),
        )
    )
    surfaces.append(_ground(seed) if floor_tile_m is None else _tiled_ground(seed, floor_tile_m))
    wall_r, wall_h, wall_texel = 5.5, 3.0, 0.008
    wall_tex = random_texture(
        stable_rng(seed, "wall"),
        int(2 * np.pi * wall_r / wall_texel),
        int(wall_h / wall_texel),
        density=0.7,
        scale=4,
    )
    surfaces.append(
        Cylinder("wall", (0.0, 0.0), wall_r, 0.0, wall_h, wall_texel, wall_tex, inside=True)
    )
    for s in surfaces[:-2]:  # a bounding box lets the renderer skip rays that miss the landmark
        s.bounds = LANDMARK_BOUNDS
    return Scene(surfaces, markers=np.array(markers), marker_normals=np.array(normals))


def _ground(seed: int) -> Rect:
    """The default ground: a 12 m square of non-repeating texture, 5 mm texels."""
    return _ground_rect(
        random_texture(stable_rng(seed, "ground"), 2400, 2400, density=0.8, scale=3), 12.0
    )


def _ground_rect(texture: np.ndarray, g: float) -> Rect:
    """The ground: a square `g` metres wide centred on the origin, covered by `texture`."""
    return Rect(
        "ground",
        (-g / 2, g / 2, 0.0),
        (1.0, 0, 0),
        (0, -1.0, 0),
        (g, g),
        g / texture.shape[1],
        texture,
        0.85,
    )


def _tiled_ground(seed: int, period_m: float) -> Rect:
    """A ground of one texture tile repeated every `period_m` in x and y (a square of at
    least 12 m centred on the origin, a whole number of tiles wide). The tile is a power of
    two texels wide (texels near 5 mm), so every mip level repeats exactly too: renders
    shifted by one period match."""
    if not period_m > 0:
        raise ValueError(f"floor tile period must be > 0, got {period_m}")
    n = int(2 ** np.clip(np.round(np.log2(period_m / 0.005)), 3, 10))
    tiles = int(np.ceil(12.0 / period_m))
    g = tiles * period_m
    texel = period_m / n
    tile = random_texture(
        stable_rng(seed, "ground-tile"), n, n, density=0.8, scale=3 * 0.005 / texel
    )
    return _ground_rect(np.tile(tile, (tiles, tiles, 1)), g)


# An occluder for `--pole`: a vertical textured cylinder between the orbit and the landmark,
# passed in front of the landmark when the camera's azimuth is near `azimuth_deg`.
POLE = {"azimuth_deg": 60.0, "distance_m": 0.95, "radius": 0.04, "z": (0.0, 2.5)}


def pole(seed: int = 0, spec: dict = POLE) -> Cylinder:
    a = np.radians(spec["azimuth_deg"])
    c = (spec["distance_m"] * np.cos(a), spec["distance_m"] * np.sin(a))
    texel = 0.002
    tex = random_texture(
        stable_rng(seed, "pole"),
        int(2 * np.pi * spec["radius"] / texel),
        int((spec["z"][1] - spec["z"][0]) / texel),
        density=1.0,
    )
    return Cylinder("pole", c, spec["radius"], *spec["z"], texel, tex, light=LIGHT)


def add_occluder(scene: Scene, surface) -> Scene:
    """The scene with one more surface in front of the landmark (markers unchanged)."""
    return replace(scene, surfaces=[*scene.surfaces, surface])


def landmark_surface_samples(step: float = 0.02) -> np.ndarray:
    """Points spread over the landmark's outer surface (for visibility and coverage)."""
    pts = []
    for (x0, x1), (y0, y1), (z0, z1) in BOXES.values():
        xs, ys, zs = (np.arange(a, b + 1e-9, step) for a, b in ((x0, x1), (y0, y1), (z0, z1)))
        for X, Y, Z in [(xs, ys, [z1]), ([x0, x1], ys, zs), (xs, [y0, y1], zs)]:
            g = np.stack(np.meshgrid(X, Y, Z, indexing="ij"), -1).reshape(-1, 3)
            pts.append(g)
    (cx, cy), r, (z0, z1) = CYLINDER["center"], CYLINDER["radius"], CYLINDER["z"]
    th, zz = np.meshgrid(np.arange(0, 2 * np.pi, step / r), np.arange(z0, z1 + 1e-9, step))
    pts.append(
        np.column_stack([cx + r * np.cos(th.ravel()), cy + r * np.sin(th.ravel()), zz.ravel()])
    )
    return np.concatenate(pts)


def _box_distance(P, bounds) -> np.ndarray:
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    c, h = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(P - c) - h
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(axis=1), 0)
    return np.abs(outside + inside)


def landmark_surface_distance(points) -> np.ndarray:
    """Unsigned distance (m) from each point to the landmark's true surface."""
    P = np.asarray(points, float).reshape(-1, 3)
    d = [_box_distance(P, b) for b in BOXES.values()]
    (cx, cy), r, (z0, z1) = CYLINDER["center"], CYLINDER["radius"], CYLINDER["z"]
    radial = np.hypot(P[:, 0] - cx, P[:, 1] - cy) - r
    axial = np.maximum(z0 - P[:, 2], P[:, 2] - z1)
    q = np.column_stack([radial, axial])
    d.append(np.abs(np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)))
    return np.min(d, axis=0)


def landmark_visibility(camera: Camera, pose: Pose, samples: np.ndarray, occluders=()) -> float:
    """Share of landmark surface samples in front of the camera that project into the image
    (and, given `occluders`, are not hidden behind one of them; the landmark's own faces do
    not count as occluders, so a fully visible landmark scores the same either way)."""
    Xc = pose.transform(samples)
    front = Xc[:, 2] > 0.05
    if not front.any():
        return 0.0
    uv = camera.project(samples[front], pose)
    inside = (
        (uv[:, 0] >= 0)
        & (uv[:, 0] <= camera.width - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= camera.height - 1)
    )
    if len(occluders):
        P = samples[front][inside]
        d = P - pose.center
        dist = np.linalg.norm(d, axis=1)
        D = d / dist[:, None]
        hidden = np.zeros(len(P), bool)
        for s in occluders:
            hidden |= s.intersect(pose.center, D) < dist
        return float((~hidden).sum()) / len(samples)
    return float(inside.sum()) / len(samples)


# --------------------------------------------------------------------------------------
# chessboard scene
# --------------------------------------------------------------------------------------
def board_scene(cols: int, rows: int, square: float, seed: int = 0) -> Scene:
    """A printed chessboard (cols x rows inner corners) in plane Z=0 of the board frame.

    Inner corner (i, j) sits at (i*square, j*square, 0), OpenCV's object-point order.
    The camera looks from Z < 0; a textured desk lies behind the board at Z = 0.3 m.
    """
    px = 25  # texels per square
    margin = 1  # white margin, in squares
    printed = Board(cols, rows, square).image(px, margin)
    tex = np.repeat(np.where(printed > 127, 245, 25).astype(np.uint8)[..., None], 3, axis=2)
    nx, ny = cols + 1 + 2 * margin, rows + 1 + 2 * margin
    texel = square / px
    origin = (-(1 + margin) * square, -(1 + margin) * square, 0.0)
    board = Rect(
        "board", origin, (1.0, 0, 0), (0, 1.0, 0), (nx * square, ny * square), texel, tex, 1.0
    )
    desk_tex = random_texture(stable_rng(seed, "desk"), 1500, 1500, density=0.4, scale=3)
    desk = Rect(
        "desk", (-1.5, -1.5, 0.3), (1.0, 0, 0), (0, 1.0, 0), (3.0, 3.0), 0.002, desk_tex, 0.8
    )
    return Scene([board, desk])


def calibration_poses(
    camera: Camera, cols: int, rows: int, square: float, n: int, rng: np.random.Generator
) -> list[Pose]:
    """Views as a person takes them: tilted up to ~50 deg, rolled, the board in every part
    of the image (corners too), fully visible."""
    corners = Board(cols, rows, square).object_points
    centre = corners.mean(axis=0)
    span = np.ptp(corners, axis=0).max()
    poses: list[Pose] = []
    tries = 0
    while len(poses) < n:
        tries += 1
        if tries > 200 * n:
            raise RuntimeError("could not place the board in view; is the board too large?")
        tilt = np.radians(rng.uniform(5, 50))
        az = rng.uniform(0, 2 * np.pi)
        dist = rng.uniform(1.1, 2.6) * span * camera.fx / camera.width * 1.3
        direction = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        C = centre + dist * direction
        base = look_at(C, centre, up=(0.0, -1.0, 0.0))
        roll = np.radians(rng.uniform(-25, 25))
        Rroll = matrix_from_rpy(0, 0, roll)  # about the optical axis (camera z)
        # move the board centre to a random image position (corners of the image too)
        u = rng.uniform(0.12, 0.88) * camera.width
        v = rng.uniform(0.12, 0.88) * camera.height
        r = camera.pixel_rays([[u, v]])[0]
        Q = _rotation_between(np.array([0.0, 0, 1]), r)
        pose = Pose(Q @ Rroll @ base.R, Q @ Rroll @ base.t)
        Xc = pose.transform(corners)
        if np.any(Xc[:, 2] <= 0.05):
            continue
        uv = camera.project(corners, pose)
        m = 12
        if (
            uv[:, 0].min() < m
            or uv[:, 1].min() < m
            or uv[:, 0].max() > camera.width - 1 - m
            or uv[:, 1].max() > camera.height - 1 - m
        ):
            continue
        poses.append(pose)
    return poses


def _rotation_between(a, b) -> np.ndarray:
    """Smallest rotation taking unit vector a to unit vector b."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    s = np.linalg.norm(v)
    if s < 1e-12:
        return np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    ang = np.arctan2(s, c)
    return np.eye(3) + np.sin(ang) * k + (1 - np.cos(ang)) * (k @ k)


# --------------------------------------------------------------------------------------
# keyframes and the orbit path
# --------------------------------------------------------------------------------------
def keyframe_poses(
    step_deg: float = 10.0, radius: float = 1.4, heights=(0.6,)
) -> list[tuple[str, Pose]]:
    """Views every `step_deg` of azimuth at each height, looking at the landmark."""
    out = []
    for hi, h in enumerate(heights):
        for k, az in enumerate(np.arange(0.0, 360.0 - 1e-9, step_deg)):
            a = np.radians(az)
            C = np.array([radius * np.cos(a), radius * np.sin(a), h])
            name = f"kf_{k:03d}" if len(heights) == 1 else f"kf_h{hi}_{k:03d}"
            out.append((name, look_at(C, LANDMARK_TARGET)))
    return out


@dataclass
class OrbitPath:
    """A circle around the landmark with wobble in radius, height and heading, changes of
    speed, and a stretch where the camera turns away so the landmark leaves the view."""

    duration_s: float = 18.0
    radius_m: float = 1.6
    height_m: float = 0.55
    turns: float = 1.3
    start_deg: float = -20.0
    look_away_s: tuple[float, float] = (14.04, 16.02)  # = synth_cli._look_away(18)
    look_away_deg: float = 100.0

    def exposure_poses(self, t: float, n: int, exposure_s: float) -> list[Pose]:
        """The `n` sub-frame poses of a motion-blurred frame at time `t`: spread evenly over
        `exposure_s` and symmetric about `t`, so the frame's true pose is the blur's centre."""
        if n <= 1:
            return [self.pose(t)]
        return [self.pose(t + exposure_s * (k / max(n - 1, 1) - 0.5)) for k in range(n)]

    def pose(self, t: float) -> Pose:
        T = self.duration_s
        az = (
            np.radians(self.start_deg)
            + 2 * np.pi * self.turns * t / T
            + 0.25 * np.sin(2 * np.pi * t / 7.0)
        )
        r = self.radius_m + 0.18 * np.sin(2 * np.pi * t / 6.3) + 0.05 * np.sin(2 * np.pi * t / 1.7)
        h = self.height_m + 0.12 * np.sin(2 * np.pi * t / 5.1 + 1.0)
        C = np.array([r * np.cos(az), r * np.sin(az), h])
        base = look_at(C, LANDMARK_TARGET)
        yaw = np.radians(4.0 * np.sin(2 * np.pi * t / 2.3) + self.look_away_deg * self._away(t))
        pitch = np.radians(2.0 * np.sin(2 * np.pi * t / 3.1))
        roll = np.radians(2.0 * np.sin(2 * np.pi * t / 2.7))
        Rz = matrix_from_rpy(0, 0, yaw)
        Rcam = matrix_from_rpy(pitch, 0, roll)  # about camera x (tilt) and z (roll)
        R_wc = Rz @ base.R_wc @ Rcam
        return Pose.from_center(R_wc, C)

    def _away(self, t: float) -> float:
        """0 -> 1 -> 0 with smooth ramps of 0.45 s at both ends of the look-away stretch."""
        a, b = self.look_away_s
        ramp = 0.45

        def smooth(x):
            x = np.clip(x, 0, 1)
            return x * x * (3 - 2 * x)

        return float(min(smooth((t - a) / ramp), smooth((b - t) / ramp)))

    def desired_path(self) -> dict:
        return {
            "type": "circle",
            "center_m": [0.0, 0.0],
            "radius_m": self.radius_m,
            "height_m": self.height_m,
            "direction": "ccw",
            "look_at_m": [float(v) for v in LANDMARK_TARGET],
        }


def dusk_frame(img: np.ndarray, progress: float, seed: int, i: int) -> np.ndarray:
    """A frame at dusk: the light at 1 - 0.75 * progress (progress 0..1 over the video) and
    sensor noise that rises as it falls (+3 grey levels sigma at 25%)."""
    g = 1.0 - 0.75 * float(np.clip(progress, 0.0, 1.0))
    noise = stable_rng(seed, f"dusk-{i}").normal(0.0, 4.0 * (1.0 - g), img.shape)
    return np.clip(img.astype(np.float32) * g + noise, 0, 255).astype(np.uint8)


def encode_jpeg(img: np.ndarray, quality: int = 95) -> bytes:
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


# --------------------------------------------------------------------------------------
# opt-in: a ChArUco board lying on the ground around the landmark (`--ground-board`)
# --------------------------------------------------------------------------------------
GROUND_BOARD = Board(
    10,
    10,
    0.14,
    "charuco",
    marker_m=0.105,
    dictionary="DICT_4X4_250",
    # W position of the printed board's top-left corner; the board lies face up, its
    # printed x axis along W +x and its printed "up" along W +y (see Board.T_wb)
    origin_m=(-0.7, 0.7, 0.0005),
    placement="ground",
)


def ground_board_image(board: Board = GROUND_BOARD, texel_m: float = 0.001) -> np.ndarray:
    """The board as printed (BGR), one pixel per `texel_m`."""
    img = board.image(int(round(board.cell_m / texel_m)))
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def add_ground_board(scene: Scene, board: Board = GROUND_BOARD) -> Scene:
    """The scene with the board lying where `board` says (its origin 0.5 mm above the
    ground, so it is seen rather than the ground texture); the landmark stands on it."""
    texel = 0.001
    axes = board.T_wb.R + 0.0  # columns: the printed x and y axes in W (+0.0: no -0.0)
    rect = Rect(
        "ground-board",
        board.origin_m,
        axes[:, 0],
        axes[:, 1],
        board.size_m,
        texel,
        ground_board_image(board, texel),
        0.9,
    )
    return replace(scene, surfaces=[*scene.surfaces, rect])


# --------------------------------------------------------------------------------------
# point scenes for the pose solver (no images: its tests and benchmarks/solvers.py)
# --------------------------------------------------------------------------------------
def random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def pnp_scene(
    rng: np.random.Generator, n: int, cam: Camera, planar: bool = False, offset_deg: float = 15.0
) -> tuple[np.ndarray, Pose, Pose]:
    """(points_w, true pose, reference pose): n points near the origin, all in the image of
    `cam` 1.5-2.5 m away, mostly around and above them like a drone. Non-planar points fill
    a 0.5 m box, planar ones a 0.5 m square facing the camera, tilted by up to 30 deg. The
    reference pose is the camera moved around the landmark by `offset_deg`, still looking
    at it: rotation error = offset, centre shift = 2 d sin(offset / 2)."""
    while True:
        d = rng.uniform(1.5, 2.5)
        c = random_unit(rng)
        c[2] = abs(c[2]) * 0.7
        c = c / np.linalg.norm(c) * d
        X = _facing_square(rng, n, c / d) if planar else rng.uniform(-0.25, 0.25, (n, 3))
        truth = look_at(c, rng.normal(scale=0.05, size=3))
        if np.all(truth.transform(X)[:, 2] > 0.3):
            u = cam.project(X, truth)
            if np.all((u > 0) & (u < [cam.width, cam.height])):
                break
    Q = rodrigues(random_unit(rng) * math.radians(offset_deg))
    return X, truth, Pose.from_center(Q @ truth.R_wc, Q @ truth.center)


def _facing_square(rng: np.random.Generator, n: int, towards: np.ndarray) -> np.ndarray:
    """n points on a 0.5 m square through the origin whose normal is the unit vector
    `towards` tilted by an angle drawn from 0-30 deg."""
    tilt = np.radians(rng.uniform(0.0, 30.0))
    a = random_unit(rng)
    a -= a.dot(towards) * towards
    a /= np.linalg.norm(a)
    nrm = rodrigues(a * tilt) @ towards
    e1 = np.cross(nrm, random_unit(rng))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nrm, e1)
    uv = rng.uniform(-0.25, 0.25, (n, 2))
    return uv[:, :1] * e1 + uv[:, 1:] * e2
