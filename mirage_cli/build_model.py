"""Build the 360-degree landmark model from views with known poses (brief, section 4.2).

Pure core, no terminal I/O (warnings go to the `mirage` logger, the CLI prints them):

1. views: each image (or video frame) with its pose, from a pose CSV or a fiducial board
   in view (ChArUco / ArUco grid), which then defines W;
2. keyframes: one view per `spacing_deg` of azimuth (per elevation band);
3. features in every keyframe; matches between keyframes that see the landmark from
   neighbouring directions, filtered by the epipolar constraint of the known poses;
4. tracks (connected components of matches), triangulated from all their views (linear
   DLT, then Gauss-Newton on the reprojection error, vectorised over all tracks), kept
   when they reproject within `max_reproj_px` in every view, are in front of every camera,
   have a large enough triangulation angle and lie in the volume of interest.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from . import model_check
from .boards import Board, BoardPoser
from .camera import Camera
from .errors import InputError
from .features import DetectorSettings, detect, make_detector, make_matcher, ratio_match
from .frames import FrameSource, read_image, resolve_inputs
from .model import (
    REACH_DEG,
    Keyframe,
    LandmarkModel,
    encode_image,
    largest_azimuth_gap,
    make_thumbnail,
)
from .pose import Pose
from .tilt import tilted_features
from .trajectory import poses_by_frame, read_pose_csv

log = logging.getLogger("mirage")


# --------------------------------------------------------------------------------------
# settings and the volume of interest
# --------------------------------------------------------------------------------------
@dataclass
class ROI:
    """Volume of interest in W: a vertical cylinder about the z axis, or a box."""

    kind: str = "none"  # none | cylinder | box | auto
    values: tuple = ()
    reason: str = ""  # why 'auto' resolved to this

    @classmethod
    def parse(cls, text: str | None) -> ROI:
        """'auto', 'none', 'R,ZMIN,ZMAX' (cylinder) or 'X0,X1,Y0,Y1,Z0,Z1' (box)."""
        if text is None or str(text).strip().lower() in ("", "auto"):
            return cls("auto")
        t = str(text).strip().lower()
        if t == "none":
            return cls("none")
        try:
            v = tuple(float(x) for x in t.replace("cyl:", "").replace("box:", "").split(","))
        except ValueError:
            v = ()
        if not all(np.isfinite(v)):
            v = ()
        if len(v) == 3 and v[0] > 0 and v[1] < v[2]:
            return cls("cylinder", v)
        if len(v) == 6 and v[0] < v[1] and v[2] < v[3] and v[4] < v[5]:
            return cls("box", v)
        raise InputError(
            f"--roi {text!r}: expected 'auto', 'none', 'R,ZMIN,ZMAX' (cylinder about the "
            "origin) or 'XMIN,XMAX,YMIN,YMAX,ZMIN,ZMAX' (box), in metres"
        )

    def resolved(self, poses: list[Pose]) -> ROI:
        """'auto': when the cameras circle W's origin, a cylinder inside their ring (85% of
        the nearest camera's horizontal distance), from 0.2 m below the ground to 0.5 m
        above the highest camera: it keeps the landmark and the ground near it and drops
        the far background. Otherwise (a camera path along one side, a forward motion)
        'none': a volume about the origin would mean nothing there (`reason` says which)."""
        if self.kind != "auto":
            return self
        if not surrounds_origin(poses):
            return ROI("none", (), "the views do not circle W's origin")
        c = np.array([p.center for p in poses])
        r = 0.85 * float(np.min(np.hypot(c[:, 0], c[:, 1])))
        return ROI(
            "cylinder", (max(r, 0.05), -0.2, float(c[:, 2].max()) + 0.5),
            "inside the ring of views",
        )  # fmt: skip

    def contains(self, X: np.ndarray) -> np.ndarray:
        if self.kind == "cylinder":
            r, z0, z1 = self.values
            return (np.hypot(X[:, 0], X[:, 1]) <= r) & (X[:, 2] >= z0) & (X[:, 2] <= z1)
        if self.kind == "box":
            lo, hi = np.array(self.values[0::2]), np.array(self.values[1::2])
            return np.all((X >= lo) & (X <= hi), axis=1)
        return np.ones(len(X), bool)

    def describe(self) -> str:
        if self.kind == "cylinder":
            return "cylinder r={:.2f} m, z {:.2f}..{:.2f} m".format(*self.values)
        if self.kind == "box":
            return "box x {:.2f}..{:.2f}, y {:.2f}..{:.2f}, z {:.2f}..{:.2f} m".format(*self.values)
        return self.kind


@dataclass
class BuildSettings:
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    spacing_deg: float = 10.0
    ratio: float = 0.8
    max_reproj_px: float = 2.0
    min_angle_deg: float = 2.5
    epipolar_px: float = 2.0
    neighbours: int = 2  # match each keyframe with this many keyframes on each side
    roi: ROI = field(default_factory=lambda: ROI("auto"))
    up: str = "auto"  # W's up axis: auto (from the views) | +z | -z | +y | -y | +x | -x
    max_video_frames: int = 400  # frames examined in a video (evenly spaced)
    tilted_views: bool = True  # also each keyframe as from 45 and 60 deg higher (tilt.py)
    keyframe_images: bool = True  # store the images: far / from-above frames' patches


UP_AXES = ("auto", "+z", "-z", "+y", "-y", "+x", "-x")


def level_matrix(axis: str) -> np.ndarray:
    """The rotation L taking W to its levelled copy (X' = L X), whose Z is `axis` of W
    ('+z', '-y', ...): a signed permutation, so levelling changes no digit."""
    sign = -1.0 if axis[0] == "-" else 1.0
    k = "xyz".index(axis[1])
    z = np.zeros(3)
    z[k] = sign
    x = np.eye(3)[1 if k == 0 else 0]
    return np.stack([x, np.cross(z, x), z])


def find_up(poses: list[Pose], option: str = "auto") -> tuple[str, str]:
    """(axis, how it was found). 'auto': the world axis nearest the views' mean camera up
    direction (-y of the camera in W) when within 45 deg of it, else +z (the brief's
    convention): a ring of views, a robot arm's or a hand-held camera stay roughly upright,
    so their mean up is the world's, in whatever frame their poses were given."""
    if option != "auto":
        return option, "set by --up"
    ups = np.array([-p.R[1] for p in poses])  # camera -y axis in W (R's rows: camera axes)
    m = ups.mean(axis=0)
    if np.linalg.norm(m) < 1e-9:
        return "+z", "the views' up directions cancel: +z assumed"
    m /= np.linalg.norm(m)
    k = int(np.argmax(np.abs(m)))
    if abs(m[k]) < np.cos(np.radians(45.0)):
        return "+z", "no world axis within 45 deg of the views' mean up: +z assumed"
    axis = ("+" if m[k] > 0 else "-") + "xyz"[k]
    return axis, f"the views' mean camera up is {np.degrees(np.arccos(abs(m[k]))):.0f} deg from it"


class ViewList(list):
    """The selected views (their poses levelled) and how W was levelled (`up`)."""

    up: dict = {"axis": "+z", "how": "", "world_from_model": np.eye(3).tolist()}


def _level(views: list, option: str) -> ViewList:
    """The views with their poses in W's levelled copy (Z = the up axis)."""
    axis, how = find_up([v.pose for v in views], option)
    L = level_matrix(axis)
    out = ViewList(views)
    if axis != "+z":
        for v in out:
            v.pose = Pose(v.pose.R @ L.T, v.pose.t)
    out.up = {"axis": axis, "how": how, "world_from_model": L.T.tolist()}
    return out


@dataclass
class View:
    """An input view with a known pose; the image is loaded lazily (None until needed)."""

    name: str
    pose: Pose
    path: Path | None = None
    image: np.ndarray | None = None  # grey
    reason: str = ""  # why it was kept as a keyframe


# --------------------------------------------------------------------------------------
# views and keyframe selection
# --------------------------------------------------------------------------------------
def _check_size(img: np.ndarray, camera: Camera, name: str) -> None:
    h, w = img.shape[:2]
    if (w, h) != camera.size:
        raise InputError(
            f"{name} is {w}x{h} but the camera file is for {camera.width}x{camera.height}; "
            "use the camera calibrated for these images (or resize them)"
        )


def view_direction(pose: Pose) -> tuple[float, float]:
    """(azimuth, elevation) in degrees of the camera centre seen from W's origin."""
    c = pose.center
    return pose.azimuth_deg, float(np.degrees(np.arctan2(c[2], np.hypot(c[0], c[1]))))


def look_at_point(poses: list[Pose]) -> np.ndarray:
    """The point the views look at: closest (least squares) to every optical axis. W's
    origin when the axes are nearly parallel (a camera moving straight ahead) or the
    point would lie behind most of the cameras."""
    if len(poses) < 2:
        return np.zeros(3)
    C = np.array([p.center for p in poses])
    A = np.array([p.R[2] for p in poses])  # optical axes in W
    proj = np.eye(3)[None] - A[:, :, None] * A[:, None, :]
    M, b = proj.sum(axis=0), np.einsum("nij,nj->i", proj, C)
    w = np.linalg.eigvalsh(M)
    if w[0] < 0.01 * len(poses):  # axes within ~6 deg of parallel: no crossing point
        return np.zeros(3)
    P = np.linalg.solve(M, b)
    if np.mean(np.einsum("ni,ni->n", P - C, A) > 0) < 0.8:
        return np.zeros(3)
    return P


def view_change(poses: list[Pose], centre: np.ndarray | None = None) -> np.ndarray:
    """(n, n) how different two views are, in degrees: the largest of the angle between
    their optical axes, the parallax of their baseline at the scene's depth, and their
    change of scale (|ln| of the depth ratio, in radians as degrees). A ring of views
    every 10 deg gives 10 deg; so does a camera that moved sideways by a sixth of its
    distance, or forward by a tenth."""
    if centre is None:
        centre = look_at_point(poses)
    C = np.array([p.center for p in poses])
    A = np.array([p.R[2] for p in poses])
    return views_change(C, A, C, A, centre)


def views_change(Ca, Aa, Cb, Ab, centre: np.ndarray) -> np.ndarray:
    """(m, n) `view_change` between views a (camera centres, optical axes in W) and b."""
    da = np.maximum(np.linalg.norm(Ca - centre, axis=1), 1e-6)
    db = np.maximum(np.linalg.norm(Cb - centre, axis=1), 1e-6)
    axes = np.degrees(np.arccos(np.clip(Aa @ Ab.T, -1.0, 1.0)))
    base = np.linalg.norm(Ca[:, None] - Cb[None], axis=2)
    parallax = np.degrees(base / (0.5 * (da[:, None] + db[None])))
    scale = np.degrees(np.abs(np.log(da[:, None] / db[None])))
    return np.maximum(np.maximum(axes, parallax), scale)


def surrounds_origin(poses: list[Pose]) -> bool:
    """Do the views circle W's origin (no gap of half a turn in their azimuths)?"""
    if len(poses) < 3:
        return False
    return largest_azimuth_gap([p.azimuth_deg for p in poses])[0] < 180.0


ADD_CHANGE = 0.6  # of the spacing: a view halfway between two of a ring (0.5) adds nothing


def select_keyframes(
    poses: list[Pose],
    spacing_deg: float,
    max_offaxis_deg: float = 35.0,
    reasons: dict[int, str] | None = None,
    by_change: bool = True,
) -> list[int]:
    """Indices of the keyframes: one view per azimuth bin (and elevation band when heights
    differ), the one nearest the bin centre among those looking at the landmark (the
    point the views look at within `max_offaxis_deg` of the optical axis); then every
    other such view that differs from all kept ones by `ADD_CHANGE` of the spacing or more
    (`view_change`: a camera that moves sideways or forward changes its view without
    changing its azimuth). Ordered by band, then azimuth, then the added views in input
    order. `reasons`, when given, gets why each was kept."""
    if not poses:
        return []
    az, el = np.array([view_direction(p) for p in poses]).T
    bands = (
        np.zeros(len(poses), int)
        if np.ptp(el) < spacing_deg / 2
        else np.round((el - el.min()) / spacing_deg).astype(int)
    )
    nbins = max(1, int(round(360.0 / spacing_deg)))
    pos = np.mod(az, 360.0) / (360.0 / nbins)
    bins = np.mod(np.round(pos).astype(int), nbins)
    off = np.abs(pos - np.round(pos))
    # views that look away from the landmark (far off the optical axis) see little of it:
    # never pick them while another view exists
    centre = look_at_point(poses)
    centers = np.array([p.center for p in poses])
    axes = np.array([p.R[2] for p in poses])  # optical axis in W (third row of R_CW)
    to_c = centre - centers
    to_c /= np.maximum(np.linalg.norm(to_c, axis=1, keepdims=True), 1e-9)
    offaxis = np.degrees(np.arccos(np.clip(np.sum(axes * to_c, axis=1), -1.0, 1.0)))
    usable = offaxis <= max_offaxis_deg
    if not usable.any():
        usable[:] = True
    best: dict[tuple[int, int], int] = {}
    for i in np.lexsort((np.arange(len(poses)), off)):  # nearest to the bin centre first
        if usable[i]:
            best.setdefault((int(bands[i]), int(bins[i])), int(i))
    keep = [best[k] for k in sorted(best)]
    if reasons is not None:
        reasons.update({i: f"azimuth {np.mod(az[i], 360):.0f} deg" for i in keep})
    change = view_change(poses, centre) if by_change else None
    for i in np.flatnonzero(usable) if by_change else ():
        if i in best.values():
            continue
        d = float(change[i, keep].min())
        if d >= ADD_CHANGE * spacing_deg:
            keep.append(int(i))
            if reasons is not None:
                reasons[int(i)] = f"view change {d:.1f} deg"
    return keep


def _select(views: list, settings) -> ViewList:
    """The keyframe views, levelled (Z up), each with why it was kept."""
    views = _level(views, settings.up)
    reasons: dict[int, str] = {}
    idx = select_keyframes([v.pose for v in views], settings.spacing_deg, reasons=reasons)
    out = ViewList(views[i] for i in idx)
    out.up = views.up
    for i, v in zip(idx, out, strict=True):
        v.reason = reasons.get(i, "")
    return out


def views_from_inputs(
    inputs,
    camera: Camera,
    settings: BuildSettings,
    poses_csv=None,
    board: Board | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ViewList:
    """Resolve INPUT into the selected keyframe views (images loaded, sizes checked), their
    poses in W's levelled copy (`ViewList.up`: Z is the up axis found or set)."""
    if (poses_csv is None) == (board is None):
        raise InputError("give exactly one of --poses (pose CSV) or --board (board YAML)")
    media = resolve_inputs(inputs, "images of the landmark")
    if media.is_video:
        return _views_from_video(media.video, camera, settings, poses_csv, board, progress)
    paths = media.images
    if poses_csv is not None:
        known = poses_by_frame(read_pose_csv(poses_csv))
        views, missing = [], []
        for p in paths:
            pose = next((known[k] for k in (p.name, str(p), p.stem) if k in known), None)
            if pose is None:
                missing.append(p.name)
            else:
                views.append(View(p.name, pose, p))
        if missing and not views:
            raise InputError(
                f"pose file {poses_csv} has no rows for the images (e.g. {missing[0]}); its "
                "'frame' (or 'image') column must hold the image file names"
            )
        _need_two(views, "images with a pose")
        if missing:
            log.warning(
                f"skipping {len(missing)} image(s) without an ok pose in {poses_csv}: "
                + ", ".join(missing[:5])
                + (" ..." if len(missing) > 5 else "")
            )
        keep = _select(views, settings)
        for k, v in enumerate(keep):
            img = read_image(v.path, gray=True)
            _check_size(img, camera, v.name)
            v.image = img
            if progress:
                progress(k + 1, len(keep))
        return keep
    poser = BoardPoser(board, camera)
    views, seen, skipped = [], 0, []
    for k, p in enumerate(paths):
        img = read_image(p, gray=True)
        _check_size(img, camera, p.name)
        pose, why = poser.pose(img)
        seen += not why.startswith("board not found")
        if pose is None:
            skipped.append(f"skipping {p.name}: {why}")
        else:
            views.append(View(p.name, pose, p, img))
        if progress:
            progress(k + 1, len(paths))
    if seen == 0:
        raise InputError(
            f"the {board.pattern} board of the board file was not found in any of the "
            f"{len(paths)} image(s); check its type, squares, dictionary and marker size"
        )
    _need_two(views, "images where the board gives a reliable pose")
    for msg in skipped:  # only once the build goes on: an error says everything itself
        log.warning(msg)
    return _select(views, settings)


def _need_two(views: list, what: str) -> None:
    if len(views) < 2:
        raise InputError(
            f"only {len(views)} usable view(s) ({what}); a model needs at least 2 views "
            "of the landmark from different directions"
        )


def _views_from_video(video, camera, settings, poses_csv, board, progress) -> ViewList:
    src = FrameSource([video])
    if src.size != camera.size:
        _check_size(np.zeros(src.size[::-1], np.uint8), camera, f"video {video.name}")
    if poses_csv is not None:
        known = poses_by_frame(read_pose_csv(poses_csv))
        frames = {}
        for k, pose in known.items():
            try:
                frames[int(float(k))] = pose
            except ValueError:
                continue
        if not frames:
            raise InputError(
                f"pose file {poses_csv} has no rows with frame numbers for video {video.name}"
            )
        chosen = _select([View(f"frame_{i:06d}", frames[i]) for i in sorted(frames)], settings)
        by_frame = {int(v.name[6:]): v for v in chosen}
        _need_two(chosen, "video frames with a pose")
        wanted = set(by_frame)
        got: dict[int, np.ndarray] = {}
        for i, _, _, frame, _ in src.frames(end=max(wanted) + 1, gray=True):
            if i in wanted and frame is not None:
                got[i] = frame
                if progress:
                    progress(len(got), len(wanted))
            if len(got) == len(wanted):
                break
        lost = sorted(wanted - set(got))
        if lost:
            log.warning(f"frames {lost[:5]} of {video.name} could not be read; skipped")
        views = ViewList(v for i, v in by_frame.items() if i in got)
        views.up = chosen.up
        for v in views:
            v.image = got[int(v.name[6:])]
        _need_two(views, "readable video frames with a pose")
        return views
    poser = BoardPoser(board, camera)
    step = max(1, -(-src.count // settings.max_video_frames)) if src.count else 1
    cand: list[View] = []
    bad = 0
    for i, _, _, frame, _ in src.frames(every=step, gray=True):
        pose, _ = poser.pose(frame) if frame is not None else (None, "")
        if pose is None:
            bad += 1
        else:
            cand.append(View(f"frame_{i:06d}", pose, None, frame))
            # keep memory bounded: reselect whenever the candidates pile up
            if len(cand) > 4 * 360 / settings.spacing_deg:
                sel = select_keyframes([v.pose for v in cand], 1.0, by_change=False)
                cand = [cand[j] for j in sel]
        if progress:
            progress(i // step + 1, max(1, src.count // step))
    if bad:
        log.warning(f"{bad} sampled frame(s) of {video.name} skipped: no reliable board pose")
    _need_two(cand, "video frames where the board gives a reliable pose")
    return _select(cand, settings)


# --------------------------------------------------------------------------------------
# matching, tracks, triangulation
# --------------------------------------------------------------------------------------
def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def keyframe_pairs(
    poses: list[Pose], spacing_deg: float, neighbours: int = 2, max_change_deg: float = 60.0
) -> list:
    """Pairs of keyframes that see the landmark from directions at most `neighbours`
    spacings apart (1- and 2-apart neighbours by default, across elevation bands too).
    The spacing is the nominal one or the typical angle between neighbouring views. Each
    keyframe is also paired with its 2 x `neighbours` most similar views (`view_change`
    below `max_change_deg`, beyond which features rarely match), so that a view further
    from the others than is typical (or a path that is not a ring) still gets points."""
    if len(poses) < 2:
        return []
    dirs = np.array([p.center for p in poses])
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1, 1)))
    # views sparser than the nominal spacing (e.g. every 30 deg) still pair with neighbours
    nearest = np.sort(ang + np.diag(np.full(len(poses), np.inf)), axis=1)[:, 0]
    lim = (neighbours + 0.5) * max(spacing_deg, float(np.median(nearest)))
    near = ang <= lim
    change = view_change(poses) + np.diag(np.full(len(poses), np.inf))
    k = min(2 * neighbours, len(poses) - 1)
    similar = np.argsort(change, axis=1, kind="stable")[:, :k]
    rows = np.repeat(np.arange(len(poses)), k)
    ok = change[rows, similar.ravel()] <= max_change_deg
    near[rows[ok], similar.ravel()[ok]] = True
    near |= near.T
    i, j = np.nonzero(np.triu(near, 1))
    return list(zip(i.tolist(), j.tolist(), strict=True))


def epipolar_ok(xa: np.ndarray, xb: np.ndarray, pa: Pose, pb: Pose, tol: float) -> np.ndarray:
    """Sampson distance of normalised correspondences under the known relative pose."""
    rel = pb @ pa.inverse()
    E = _skew(rel.t) @ rel.R
    ha = np.column_stack([xa, np.ones(len(xa))])
    hb = np.column_stack([xb, np.ones(len(xb))])
    Ea = ha @ E.T
    Eb = hb @ E
    num = np.einsum("ij,ij->i", hb, Ea) ** 2
    den = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Eb[:, 0] ** 2 + Eb[:, 1] ** 2
    return num / np.maximum(den, 1e-30) < tol**2


def triangulate(
    x: np.ndarray, Rs: np.ndarray, ts: np.ndarray, track: np.ndarray, n_tracks: int, iters: int = 5
) -> np.ndarray:
    """Points (T,3) from normalised observations x (N,2) of `track` ids seen by cameras
    (Rs (N,3,3), ts (N,3)): DLT summed per track, then Gauss-Newton on the reprojection."""
    P = np.concatenate([Rs, ts[:, :, None]], axis=2)  # (N,3,4)
    r1 = x[:, 0:1] * P[:, 2] - P[:, 0]
    r2 = x[:, 1:2] * P[:, 2] - P[:, 1]
    A = np.einsum("ni,nj->nij", r1, r1) + np.einsum("ni,nj->nij", r2, r2)
    M = np.zeros((n_tracks, 4, 4))
    np.add.at(M, track, A)
    _, vecs = np.linalg.eigh(M)
    h = vecs[:, :, 0]
    w = np.where(np.abs(h[:, 3]) < 1e-12, 1e-12, h[:, 3])
    X = h[:, :3] / w[:, None]
    for _ in range(iters):
        Xc = np.einsum("nij,nj->ni", Rs, X[track]) + ts
        z = np.where(np.abs(Xc[:, 2]) < 1e-9, 1e-9, Xc[:, 2])
        res = Xc[:, :2] / z[:, None] - x
        Jp = np.zeros((len(x), 2, 3))
        Jp[:, 0, 0] = Jp[:, 1, 1] = 1 / z
        Jp[:, 0, 2] = -Xc[:, 0] / z**2
        Jp[:, 1, 2] = -Xc[:, 1] / z**2
        J = Jp @ Rs
        H = np.zeros((n_tracks, 3, 3))
        g = np.zeros((n_tracks, 3))
        np.add.at(H, track, np.einsum("nki,nkj->nij", J, J))
        np.add.at(g, track, np.einsum("nki,nk->ni", J, res))
        H += 1e-12 * np.eye(3)
        X = X - np.linalg.solve(H, g[:, :, None])[:, :, 0]
    return X


@dataclass
class Tracks:
    """Observations (keyframe, feature) grouped into tracks, one per candidate 3D point."""

    kf: np.ndarray
    feat: np.ndarray
    track: np.ndarray
    n: int


def build_tracks(matches: list, offsets: np.ndarray) -> Tracks:
    """Connected components of the match graph; components in which one keyframe appears
    twice are inconsistent (two features, one point) and dropped."""
    total = int(offsets[-1])
    if not matches:
        return Tracks(*(np.zeros(0, int),) * 3, 0)
    a = np.concatenate([offsets[i] + qa for i, _, qa, _ in matches])
    b = np.concatenate([offsets[j] + qb for _, j, _, qb in matches])
    g = coo_matrix((np.ones(len(a)), (a, b)), shape=(total, total))
    _, label = connected_components(g, directed=False)
    node = np.unique(np.concatenate([a, b]))
    lab = label[node]
    kf = np.searchsorted(offsets, node, side="right") - 1
    # drop components with a repeated keyframe
    key = lab.astype(np.int64) * (len(offsets) + 1) + kf
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    bad_lab = np.unique(lab[cnt[inv] > 1])
    keep = ~np.isin(lab, bad_lab)
    node, lab, kf = node[keep], lab[keep], kf[keep]
    uniq, track = np.unique(lab, return_inverse=True)
    return Tracks(kf, node - offsets[kf], track, len(uniq))


@dataclass
class BuildResult:
    model: LandmarkModel
    pairs: int
    matches: int
    tracks: int
    rejected: dict


def build_model(
    views: list[View],
    camera: Camera,
    settings: BuildSettings,
    progress: Callable[[str, int, int], None] | None = None,
) -> BuildResult:
    """Keyframes, features and 3D points from views with known poses (images loaded)."""
    _need_two(views, "views")
    kps, descs, norm = [], [], []
    workers = max(1, min(4, os.cpu_count() or 1))
    dets = [make_detector(settings.detector) for _ in range(workers)]

    def job(k):  # OpenCV releases the GIL: threads use every core, no pickling
        return detect(views[k].image, dets[k % workers])

    with ThreadPoolExecutor(workers) as pool:
        for k, (kp, d) in enumerate(pool.map(job, range(len(views)))):
            kps.append(kp)
            descs.append(d)
            norm.append(camera.undistort_points(kp))
            if progress:
                progress("features", k + 1, len(views))
    poses = [v.pose for v in views]
    pairs = keyframe_pairs(poses, settings.spacing_deg, settings.neighbours)
    f = max(camera.fx, camera.fy)
    matches = []
    matcher = make_matcher(settings.detector)
    for k, (i, j) in enumerate(pairs):
        qi, ti = ratio_match(descs[i], descs[j], settings.ratio, matcher)
        ok = epipolar_ok(norm[i][qi], norm[j][ti], poses[i], poses[j], settings.epipolar_px / f)
        if ok.any():
            matches.append((i, j, qi[ok], ti[ok]))
        if progress:
            progress("matching", k + 1, len(pairs))
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in kps])]).astype(np.int64)
    tr = build_tracks(matches, offsets)
    roi = settings.roi.resolved(poses)
    X, kf, feat, track, rejected = _triangulate_tracks(tr, norm, kps, poses, camera, settings, roi)
    check = _check(X, kf, feat, track, norm, kps, poses, camera, settings)
    if progress:
        progress("checking", 1, 1)
    point_ids = [np.full(len(k), -1, np.int32) for k in kps]
    for i in range(len(views)):
        m = kf == i
        point_ids[i][feat[m]] = track[m]
    keyframes = [
        Keyframe(v.name, v.pose, kps[i], descs[i], point_ids[i], make_thumbnail(v.image))
        for i, v in enumerate(views)
    ]
    if settings.keyframe_images:
        for kf, v in zip(keyframes, views, strict=True):
            kf.image, kf.image_scale = encode_image(v.image)
    if settings.tilted_views:

        def tilted(k):
            v = views[k]
            return tilted_features(v.image, v.pose, kps[k], point_ids[k], dets[k % workers])

        with ThreadPoolExecutor(workers) as pool:
            for kf, t in zip(keyframes, pool.map(tilted, range(len(views))), strict=True):
                kf.tilted = t
    for kf in keyframes:
        kf.compact()
    del descs
    meta = {
        "spacing_deg": settings.spacing_deg,
        "roi": {"kind": roi.kind, "values": list(roi.values), "reason": roi.reason},
        "kept": {v.name: v.reason for v in views if v.reason},
        "check": model_check.summary(check, [v.name for v in views]),
        "up": getattr(views, "up", ViewList.up),
        "max_reproj_px": settings.max_reproj_px,
        "min_angle_deg": settings.min_angle_deg,
        "ratio": settings.ratio,
    }
    model = LandmarkModel(camera, settings.detector, keyframes, X, meta=meta)
    n_matches = int(sum(len(m[2]) for m in matches))
    return BuildResult(model, len(pairs), n_matches, tr.n, rejected)


def _check(X, kf, feat, track, norm, kps, poses, camera, settings) -> list:
    """Leave-one-keyframe-out check of the model (model_check.py), with the tracker's
    covariance of a pose."""
    from .tracking import TrackSettings
    from .tracking.gating import frame_covariances

    if not len(X):
        return []
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in kps])]).astype(np.int64)
    at = offsets[kf] + feat
    x = np.concatenate(norm)[at]
    uv = np.concatenate(kps).astype(np.float64)[at]
    err = _reproj(X[track], kf, uv, poses, camera)
    rms = float(np.sqrt(np.mean(err**2))) if len(err) else 0.0
    ts = TrackSettings()

    def covariances(est, n, points):
        return frame_covariances(
            est, n, camera, points, ts.refine.huber_px, rms, ts.model_error_points, 1.0
        )

    return model_check.check_keyframes(
        x, uv, kf, track, poses, camera, settings.max_reproj_px, covariances, triangulate
    )


def _triangulate_tracks(tr: Tracks, norm, kps, poses, camera, settings, roi):
    """Triangulate, then twice drop observations beyond the pixel limit and retriangulate;
    finally keep points that pass every test. Returns points and their observations."""
    Rall = np.array([p.R for p in poses])
    tall = np.array([p.t for p in poses])
    kf, feat, track, n = tr.kf, tr.feat, tr.track, tr.n
    rejected = {"reprojection": 0, "angle": 0, "behind": 0, "roi": 0}
    if n == 0:
        return np.zeros((0, 3)), kf, feat, track, rejected
    x = np.concatenate([norm[i][feat[kf == i]] for i in range(len(poses))]) if len(kf) else None
    order = np.concatenate([np.flatnonzero(kf == i) for i in range(len(poses))])
    kf, feat, track = kf[order], feat[order], track[order]
    uv = np.concatenate([kps[i][feat[kf == i]] for i in range(len(poses))]).astype(float)
    for _ in range(3):
        X = triangulate(x, Rall[kf], tall[kf], track, n)
        err = _reproj(X[track], kf, uv, poses, camera)
        good = err <= settings.max_reproj_px
        cnt = np.bincount(track[good], minlength=n)
        if good.all():
            break
        keep = good & (cnt[track] >= 2)
        kf, feat, track, x, uv = kf[keep], feat[keep], track[keep], x[keep], uv[keep]
        used, track = np.unique(track, return_inverse=True)
        n = len(used)
        if n == 0:
            return np.zeros((0, 3)), kf, feat, track, rejected
    X = triangulate(x, Rall[kf], tall[kf], track, n)
    err = _reproj(X[track], kf, uv, poses, camera)
    depth = np.einsum("nj,nj->n", Rall[kf, 2], X[track]) + tall[kf, 2]
    obs_bad = (err > settings.max_reproj_px) | ~np.isfinite(err)
    bad_reproj = np.bincount(track[obs_bad], minlength=n) > 0
    behind = np.bincount(track[depth <= 0], minlength=n) > 0
    angle = _max_angle(X, kf, track, poses, n)
    low_angle = angle < settings.min_angle_deg
    out_roi = ~roi.contains(X)
    ok = ~(bad_reproj | behind | low_angle | out_roi)
    rejected.update(
        reprojection=int(bad_reproj.sum()),
        behind=int((behind & ~bad_reproj).sum()),
        angle=int((low_angle & ~bad_reproj & ~behind).sum()),
        roi=int((out_roi & ~low_angle & ~bad_reproj & ~behind).sum()),
    )
    new_id = np.full(n, -1)
    new_id[ok] = np.arange(ok.sum())
    m = ok[track]
    return X[ok], kf[m], feat[m], new_id[track[m]], rejected


def _reproj(Xobs, kf, uv, poses, camera) -> np.ndarray:
    err = np.empty(len(kf))
    for i in np.unique(kf):
        m = kf == i
        err[m] = np.linalg.norm(camera.project(Xobs[m], poses[i]) - uv[m], axis=1)
    return err


def _max_angle(X, kf, track, poses, n, chunk: int = 4_000_000) -> np.ndarray:
    """Largest angle (deg) between the viewing rays of each point (padded, vectorised, in
    groups of tracks holding `chunk` ray pairs at most: 144 keyframes' tracks are up to 60
    views long, and all their pairs at once took 700 MB)."""
    C = np.array([p.center for p in poses])
    rays = C[kf] - X[track]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    order = np.argsort(track, kind="stable")
    t_sorted = track[order]
    start = np.searchsorted(t_sorted, np.arange(n))
    slot = np.arange(len(track)) - start[t_sorted]
    L = int(slot.max()) + 1 if len(slot) else 1
    pad = np.full((n, L, 3), np.nan)
    pad[t_sorted, slot] = rays[order]
    min_dot = np.empty(n)
    step = max(1, chunk // (L * L))
    for a in range(0, n, step):  # a few groups of tracks, each vectorised
        dots = np.einsum("tai,tbi->tab", pad[a : a + step], pad[a : a + step])
        np.nan_to_num(dots, copy=False, nan=2.0)
        min_dot[a : a + step] = dots.reshape(len(dots), -1).min(axis=1)
    return np.degrees(np.arccos(np.clip(min_dot, -1, 1)))


def coverage_warning(model: LandmarkModel) -> str | None:
    """The largest azimuth gap, if it leaves frames further than `REACH_DEG` from every
    keyframe (where tracking was measured to fail)."""
    gap, lo, hi = largest_azimuth_gap(model.azimuths())
    if gap > 2 * REACH_DEG:
        return (
            f"azimuth gap of {gap:.0f} deg between {lo:.0f} and {hi:.0f} deg: frames more "
            f"than {REACH_DEG:g} deg from a keyframe may not be tracked (measured: a 100 deg "
            "gap tracks 57-82% of the frames 30-50 deg away, a 120 deg gap none beyond 30); "
            "add views of that side"
        )
    return None
