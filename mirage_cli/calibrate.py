"""Camera calibration from chessboard or ChArUco views: detection, calibration, diagnostics.

Pure core: no terminal output. Problems with the data are returned as warning strings
(the CLI prints them); failures the user can fix raise InputError.

Corner accuracy matters more than anything else here. Every detection (classic
findChessboardCorners first, findChessboardCornersSB as fallback for hard views) is
checked for plausibility and refined with cornerSubPix, with a window sized from the
corner spacing in that view: a fixed 23x23 window (OpenCV's sample) reaches across
squares on small boards and drags corners by several pixels; SB's own corners are
~0.1 px noisier than the refinement on clean views.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .boards import Board
from .camera import Camera, lens_fold_warning
from .errors import InputError, cv_message
from .frames import FrameSource, read_image
from .runtime import opencv_one_thread

SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
MIN_VIEWS = 3
MIN_CHARUCO_CORNERS = 8


# --- detection ----------------------------------------------------------------------------
@dataclass
class View:
    """Board corners found in one image or video frame."""

    name: str  # file name or "frame 123"
    corners: np.ndarray  # (N, 2) float32 pixels
    ids: np.ndarray  # (N,) int: index into Board.object_points
    method: str  # sb | classic | charuco
    frame: int | None = None
    time_s: float | None = None


@dataclass
class Detections:
    views: list[View]
    image_size: tuple[int, int]  # (width, height)
    examined: int  # images or frames looked at
    not_found: list[str] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)
    duplicates: int = 0  # video frames skipped because the board had not moved
    warnings: list[str] = field(default_factory=list)


def find_corners(
    gray: np.ndarray, board: Board, subpix_window: int | None = None
) -> tuple[np.ndarray, np.ndarray, str] | None:
    """Corners (N,2), their ids and the detector used, or None when no board is seen.

    `subpix_window`: fixed cornerSubPix half-window in px (default: from corner spacing).
    """
    try:
        if board.pattern == "charuco":
            return _find_charuco(gray, board, subpix_window)
        return _find_chessboard(gray, board, subpix_window)
    except cv2.error as e:
        raise InputError(f"corner detection failed: {cv_message(e)}") from None


def _find_chessboard(gray, board: Board, subpix_window=None):
    size = (board.cols, board.rows)
    norm = cv2.CALIB_CB_NORMALIZE_IMAGE
    # Classic first: ~30x faster than SB on clean views, and after cornerSubPix its
    # corners are as accurate; SB (then exhaustive SB) rescues blurred or hard views.
    attempts = (
        (
            "classic",
            lambda: cv2.findChessboardCorners(
                gray, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | norm
            ),
        ),
        ("sb", lambda: cv2.findChessboardCornersSB(gray, size, flags=norm)),
        (
            "sb",
            lambda: cv2.findChessboardCornersSB(gray, size, flags=norm | cv2.CALIB_CB_EXHAUSTIVE),
        ),
    )
    for method, detect in attempts:
        ok, corners = detect()
        if not ok or corners is None:
            continue
        grid = corners.reshape(board.rows, board.cols, 2).astype(np.float32)
        if plausible_grid(gray, grid):
            corners = refine_corners(gray, grid, subpix_window).reshape(-1, 2)
            return corners, np.arange(len(corners)), method
    return None


def plausible_grid(gray: np.ndarray, grid: np.ndarray) -> bool:
    """Reject detections that are not the whole declared board.

    With a wrong --board the detectors (SB in particular) return grids that skip rows,
    include points off the board or are a part of a larger board; calibrating on them
    gives a confident wrong camera. A real board view is smooth (small second
    differences, even under strong distortion), its cells alternate dark/bright, and
    it does not continue past its sides.
    """
    for axis in (0, 1):
        g = np.moveaxis(grid, axis, 0)
        bend = np.linalg.norm(g[2:] - 2 * g[1:-1] + g[:-2], axis=-1)
        step = np.linalg.norm(g[2:] - g[:-2], axis=-1) / 2
        if g.shape[0] > 2 and np.max(bend / np.maximum(step, 1e-6)) > 0.3:
            return False
    centres = (grid[:-1, :-1] + grid[1:, :-1] + grid[:-1, 1:] + grid[1:, 1:]) / 4
    m = centres.reshape(-1, 1, 2).astype(np.float32)
    blurred = cv2.GaussianBlur(gray, (5, 5), 0).astype(np.float32)
    vals = cv2.remap(blurred, m[..., 0], m[..., 1], cv2.INTER_LINEAR).ravel()
    parity = (np.indices(centres.shape[:2]).sum(axis=0) % 2).ravel().astype(bool)
    agree = np.mean((vals > np.median(vals)) == parity)
    if max(agree, 1 - agree) < 0.9:
        return False
    return not extends_beyond(gray, grid)


def refine_corners(gray: np.ndarray, grid: np.ndarray, half: int | None = None) -> np.ndarray:
    """cornerSubPix with a window that stays inside the squares around each corner.

    `grid` is (rows, cols, 2); the half-window is a quarter of the smallest spacing
    between neighbouring corners, clamped to 2..8 px.
    """
    spacing = min(
        np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
        np.linalg.norm(np.diff(grid, axis=0), axis=2).min(),
    )
    half = half or int(np.clip(spacing // 4, 2, 8))
    pts = np.ascontiguousarray(grid.reshape(-1, 1, 2), np.float32)
    cv2.cornerSubPix(gray, pts, (half, half), (-1, -1), SUBPIX_CRITERIA)
    return pts.reshape(grid.shape)


def extends_beyond(gray: np.ndarray, grid: np.ndarray, limit: float = 0.75) -> bool:
    """True when the chessboard continues past a side of the detected (rows, cols) grid.

    findChessboardCornersSB happily returns a 7x5 part of a 9x6 board. One step past
    each side of a complete board lies the board's outer edge (one dark square of four
    quadrants: half the X-corner contrast); past a partial board lies another X-corner.
    The saddle contrast there, relative to the inner corners', tells them apart.
    """
    g = cv2.GaussianBlur(gray, (3, 3), 0).astype(np.float32)
    h, w = g.shape
    du = np.gradient(grid, axis=1)  # one step along a row
    dv = np.gradient(grid, axis=0)  # one step down a column

    def saddle(p, u, v):  # |(q++ + q--) - (q+- + q-+)| / 2 at points p (N, 2)
        offs = np.array([[1, 1], [-1, -1], [1, -1], [-1, 1]], np.float32) * 0.3
        q = p[:, None] + offs[None, :, :1] * u[:, None] + offs[None, :, 1:] * v[:, None]
        m = q.reshape(-1, 1, 2).astype(np.float32)
        vals = cv2.remap(
            g,
            m[..., 0],
            m[..., 1],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=np.nan,
        ).reshape(-1, 4)
        inside = np.all((q >= 1) & (q <= [w - 2, h - 2]), axis=(1, 2))
        sc = np.abs(vals[:, 0] + vals[:, 1] - vals[:, 2] - vals[:, 3]) / 2
        return np.where(inside, sc, np.nan)

    ref = np.nanmedian(saddle(grid.reshape(-1, 2), du.reshape(-1, 2), dv.reshape(-1, 2)))
    if not ref > 0:
        return False
    sides = [
        (2 * grid[0] - grid[1], du[0], dv[0]),
        (2 * grid[-1] - grid[-2], du[-1], dv[-1]),
        (2 * grid[:, 0] - grid[:, 1], du[:, 0], dv[:, 0]),
        (2 * grid[:, -1] - grid[:, -2], du[:, -1], dv[:, -1]),
    ]
    for p, u, v in sides:
        sc = saddle(p, u, v)
        if np.isfinite(sc).sum() >= 2 and np.nanmedian(sc) / ref > limit:
            return True
    return False


def _find_charuco(gray, board: Board, subpix_window=None):
    detector = board.cv_detector()
    corners, ids, _, _ = detector.detectBoard(gray)
    if corners is None or ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    corners = corners.reshape(-1, 2).astype(np.float32)
    ids = ids.ravel().astype(int)
    # refine as for a chessboard; spacing from the nearest neighbour of each corner
    d = np.linalg.norm(corners[:, None] - corners[None], axis=2)
    np.fill_diagonal(d, np.inf)
    half = subpix_window or int(np.clip(np.median(d.min(axis=1)) // 4, 2, 8))
    pts = np.ascontiguousarray(corners.reshape(-1, 1, 2))
    cv2.cornerSubPix(gray, pts, (half, half), (-1, -1), SUBPIX_CRITERIA)
    return pts.reshape(-1, 2), ids, "charuco"


def detect_images(
    paths: Sequence[Path],
    board: Board,
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
    subpix_window: int | None = None,
) -> Detections:
    """Find the board in each image, in parallel (OpenCV releases the GIL)."""
    workers = default_workers() if workers is None else max(1, workers)

    paths = [Path(p) for p in paths]

    def one(path: Path):
        try:
            gray = read_image(path, gray=True)
        except InputError as e:
            return path, None, None, str(e)
        return path, gray.shape[::-1], find_corners(gray, board, subpix_window), None

    views, not_found, unreadable, warnings = [], [], [], []
    sizes: dict[tuple[int, int], str] = {}
    with ThreadPoolExecutor(workers) as pool:
        for path, size, found, err in pool.map(one, paths):
            if progress:
                progress(1)
            if err:
                unreadable.append(path.name)
                warnings.append(f"skipped {err}")
                continue
            sizes.setdefault(size, path.name)
            if found is None:
                not_found.append(path.name)
            else:
                views.append(View(path.name, *found))
    if len(sizes) > 1:
        desc = ", ".join(f"{n} is {w}x{h}" for (w, h), n in sizes.items())
        raise InputError(
            f"images have different sizes ({desc}); calibrate one camera resolution at a time"
        )
    if not sizes:
        raise InputError(f"none of the {len(paths)} images could be read")
    return Detections(
        views, next(iter(sizes)), len(paths), not_found, unreadable, warnings=warnings
    )


def detect_video(
    path: Path,
    board: Board,
    every: int = 10,
    min_motion_px: float = 8.0,
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
    subpix_window: int | None = None,
) -> Detections:
    """Find the board in every `every`-th frame; drop views where it has barely moved.

    Near-duplicate views add no information but weight that pose more than others.
    """
    workers = default_workers() if workers is None else max(1, workers)
    src = FrameSource([path])
    unreadable: list[str] = []

    def decoded(frames):
        for f in frames:
            if f.image is None:  # a damaged stretch: counted, and decoding goes on after it
                unreadable.append(f"frame {f.index}")
                if progress:
                    progress(1)
            else:
                yield f

    def one(f):
        return f.index, f.time_s, find_corners(f.image, board, subpix_window)

    found: list[View] = []
    not_found: list[str] = []
    examined = 0
    with ThreadPoolExecutor(workers) as pool:
        for chunk in _chunks(decoded(src.frames(every=every, gray=True)), 4 * workers):
            for index, t, res in pool.map(one, chunk):
                examined += 1
                if progress:
                    progress(1)
                if res is None:
                    not_found.append(f"frame {index}")
                else:
                    found.append(View(f"frame {index}", *res, frame=index, time_s=t))
    if examined == 0:
        raise InputError(f"video {path} has no readable frames")
    views, last = [], None
    for v in found:
        if last is not None and _motion_px(last, v) < min_motion_px:
            continue
        views.append(v)
        last = v
    warnings = [f"skipped {len(unreadable)} undecodable frame(s)"] if unreadable else []
    return Detections(
        views,
        src.size,
        examined + len(unreadable),
        not_found,
        unreadable,
        duplicates=len(found) - len(views),
        warnings=warnings,
    )


def _motion_px(a: View, b: View) -> float:
    """Median displacement of the corners two views share (inf when they share few)."""
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if len(common) < 4:
        return math.inf
    return float(np.median(np.linalg.norm(a.corners[ia] - b.corners[ib], axis=1)))


def _chunks(it: Iterable, n: int) -> Iterable[list]:
    chunk = []
    for x in it:
        chunk.append(x)
        if len(chunk) == n:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def default_workers() -> int:
    return max(1, min(4, os.cpu_count() or 1))


# --- calibration --------------------------------------------------------------------------
@dataclass(frozen=True)
class CalibOptions:
    model: int = 5  # 5: k1 k2 p1 p2 k3; 8: rational model k1..k6
    fix_aspect: bool = False
    fix_principal_point: bool = False
    zero_tangent: bool = False
    reject_factor: float = 3.0  # reject views with RMS > max(factor * median, median + margin)
    reject_margin_px: float = 0.5
    max_view_error_px: float | None = None  # absolute per-view limit instead of the rule
    max_views: int = 80  # more views than this are subsampled evenly (speed)

    @property
    def flags(self) -> int:
        f = 0
        if self.model == 8:
            f |= cv2.CALIB_RATIONAL_MODEL
        elif self.model != 5:
            raise InputError(f"distortion model must be 5 or 8 coefficients, got {self.model}")
        if self.fix_aspect:
            f |= cv2.CALIB_FIX_ASPECT_RATIO
        if self.fix_principal_point:
            f |= cv2.CALIB_FIX_PRINCIPAL_POINT
        if self.zero_tangent:
            f |= cv2.CALIB_ZERO_TANGENT_DIST
        return f


@dataclass
class Calibration:
    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    rms_px: float
    views: list[View]  # views used
    view_errors_px: np.ndarray  # per-view RMS of the views used
    rejected: list[tuple[View, float]]  # views dropped as outliers, with their RMS
    std_intrinsics: dict[str, float]  # 1-sigma of fx fy cx cy k1 k2 ...
    tilts_deg: np.ndarray  # angle between board normal and optical axis, per view
    warnings: list[str] = field(default_factory=list)
    threshold_px: float | None = None  # per-view RMS limit used for rejection


def calibrate(det: Detections, board: Board, opts: CalibOptions = CalibOptions()) -> Calibration:
    """Calibrate, drop outlier views, recalibrate; add warnings about weak data."""
    views = list(det.views)
    if len(views) < MIN_VIEWS:
        raise InputError(_too_few_message(det, board))
    warnings: list[str] = []
    if len(views) > opts.max_views:
        keep = np.linspace(0, len(views) - 1, opts.max_views).round().astype(int)
        warnings.append(f"{len(views)} views found; using {opts.max_views} spread evenly")
        views = [views[i] for i in keep]

    rejected: list[tuple[View, float]] = []
    threshold = None
    res = _calibrate_views(views, board, det.image_size, opts)
    for _ in range(3):  # reject, recalibrate; a second round catches masked outliers
        errs = res[-1]
        med = float(np.median(errs))
        threshold = (
            opts.max_view_error_px
            if opts.max_view_error_px is not None
            else max(opts.reject_factor * med, med + opts.reject_margin_px)
        )
        bad = errs > threshold
        if not bad.any() or len(views) - bad.sum() < MIN_VIEWS:
            break
        rejected += [(v, float(e)) for v, e, b in zip(views, errs, bad, strict=True) if b]
        views = [v for v, b in zip(views, bad, strict=True) if not b]
        res = _calibrate_views(views, board, det.image_size, opts)

    rms, K, dist, rvecs, _tvecs, std, errs = res
    n_dist = 8 if opts.model == 8 else 5
    dist = dist.ravel()[:n_dist]
    std = std.ravel()
    names = ("fx", "fy", "cx", "cy", *DIST_NAMES[:n_dist])
    std_map = {n: float(s) for n, s in zip(names, std[: len(names)], strict=True)}
    if opts.fix_aspect:  # fx = ratio * fy is not a free parameter, but it is uncertain
        std_map["fx"] = std_map["fy"] * K[0, 0] / K[1, 1]
    tilts = np.array([_tilt_deg(r) for r in rvecs])
    calib = Calibration(
        K,
        dist,
        det.image_size,
        float(rms),
        views,
        errs,
        rejected,
        std_map,
        tilts,
        warnings,
        threshold,
    )
    calib.warnings += weak_data_warnings(calib)
    return calib


def _calibrate_views(views, board, size, opts):
    obj_all = board.object_points.astype(np.float32)
    obj = [np.ascontiguousarray(obj_all[v.ids]) for v in views]
    img = [np.ascontiguousarray(v.corners.reshape(-1, 1, 2), np.float32) for v in views]
    K0 = np.eye(3)  # with FIX_ASPECT_RATIO only fx/fy of the guess is used: 1
    try:
        with opencv_one_thread():  # the same views give the same camera, to the bit
            rms, K, dist, rvecs, tvecs, std, _ext, errs = cv2.calibrateCameraExtended(
                obj, img, size, K0, None, flags=opts.flags
            )
    except cv2.error as e:
        raise InputError(
            f"calibration failed: {cv_message(e)} (are the views too similar, "
            "or the board size wrong?)"
        ) from None
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError("calibration diverged; use more views, tilted in different directions")
    return rms, K, dist, rvecs, tvecs, std, np.asarray(errs, float).ravel()


def _tilt_deg(rvec) -> float:
    R, _ = cv2.Rodrigues(np.asarray(rvec, float))
    return float(np.degrees(np.arccos(np.clip(abs(R[2, 2]), 0.0, 1.0))))


def coverage(views: Sequence[View], image_size: tuple[int, int], grid=(8, 6)) -> float:
    """Share of cells in a grid over the image that contain at least one corner."""
    w, h = image_size
    pts = np.concatenate([v.corners for v in views])
    cx = np.clip((pts[:, 0] / w * grid[0]).astype(int), 0, grid[0] - 1)
    cy = np.clip((pts[:, 1] / h * grid[1]).astype(int), 0, grid[1] - 1)
    return len(np.unique(cy * grid[0] + cx)) / (grid[0] * grid[1])


def weak_data_warnings(
    c: Calibration, edge_frac: float = 0.15, tilt_deg: float = 15.0, min_views: int = 10
) -> list[str]:
    """Why the result may be poor even though calibration succeeded."""
    out = []
    if len(c.views) < min_views:
        out.append(f"only {len(c.views)} views used; 10-30 views give a reliable calibration")
    w, h = c.image_size
    pts = np.concatenate([v.corners for v in c.views])
    gaps = {
        "left": pts[:, 0].min() / w,
        "right": (w - pts[:, 0].max()) / w,
        "top": pts[:, 1].min() / h,
        "bottom": (h - pts[:, 1].max()) / h,
    }
    far = [k for k, g in gaps.items() if g > edge_frac]
    if far:
        out.append(
            f"corners never come near the {'/'.join(far)} image edge(s); distortion "
            f"there is extrapolated (coverage {coverage(c.views, c.image_size):.0%}); "
            "add views with the board near the edges and corners"
        )
    if c.tilts_deg.max() < tilt_deg:
        out.append(
            f"all views are nearly fronto-parallel (max tilt {c.tilts_deg.max():.0f} "
            "deg); focal length is poorly determined; tilt the board 20-45 deg"
        )
    if c.rms_px > 1.0:
        out.append(
            f"RMS reprojection error {c.rms_px:.2f} px > 1 px; check board size, "
            "square size, focus and motion blur"
        )
    fold = lens_fold_warning(Camera(c.K, c.dist, w, h))
    if fold:
        out.append(fold + "; add views with the board in the corners, or try --model 8")
    return out


def _too_few_message(det: Detections, board: Board) -> str:
    n = len(det.views)
    what = "frames" if det.views and det.views[0].frame is not None else "images"
    if n == 0:
        hint = ""
        if board.pattern == "chessboard":
            hint = "; check --board: it counts inner corners, COLSxROWS"
            if 2 < min(board.cols, board.rows) and max(board.cols, board.rows) <= 60:
                # squares given for corners, most often
                hint += (
                    f" (a board of {board.cols}x{board.rows} squares has "
                    f"{board.cols - 1}x{board.rows - 1} inner corners: try --board "
                    f"{board.cols - 1}x{board.rows - 1})"
                )
        else:
            hint = "; check --board (squares), --dictionary and --marker"
        return f"no {board.label} {board.pattern} found in any of the {det.examined} {what}{hint}"
    return (
        f"only {n} usable view(s) of the {board.label} {board.pattern} in {det.examined} "
        f"{what}; need at least {MIN_VIEWS} (10-30 recommended)"
    )
