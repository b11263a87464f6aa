"""Calibration and fiducial boards: one description for calibrate, build-model and synth.

A `Board` is a chessboard, a ChArUco board or an ArUco grid board, plus (for build-model)
where it lies in W. From it come the OpenCV board and detector, the printed image (synth
renders it), the board-file YAML and, through `BoardPoser`, the camera pose from a view.
Every board object in the package is made here, so a board printed by synth, detected by
calibrate and posed by build-model is the same board. Pure core: errors are InputError.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np

from .camera import Camera
from .errors import InputError, cv_message
from .fileio import read_yaml, require_file
from .pose import Pose, matrix_from_rpy

PATTERNS = ("chessboard", "charuco", "aruco_grid")
MARKER_PATTERNS = ("charuco", "aruco_grid")
PLACEMENTS = ("ground", "board")
FILE_DICTIONARY = "DICT_4X4_50"  # a board file without `dictionary`
MARKER_FRACTION = 0.75  # ChArUco marker side / square side when --marker is not given


def parse_size(text) -> tuple[int, int]:
    """'9x6' (or 9X6, 9*6, 9,6) -> (9, 6); ValueError with the reason otherwise."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX*,]\s*(\d+)\s*", str(text))
    if not m:
        raise ValueError(f"'{text}' is not COLSxROWS, e.g. 9x6")
    cols, rows = int(m.group(1)), int(m.group(2))
    if cols < 2 or rows < 2:
        raise ValueError(f"'{text}': both COLS and ROWS must be >= 2")
    return cols, rows


def aruco_dictionary(name: str):
    """The predefined ArUco dictionary called `name` ('DICT_5X5_100' or '5x5_100')."""
    key = str(name).strip().upper()
    key = key if key.startswith("DICT_") else f"DICT_{key}"
    dict_id = getattr(cv2.aruco, key, None)
    if not isinstance(dict_id, int):
        raise InputError(f"unknown ArUco dictionary '{name}' (e.g. DICT_5X5_100)")
    return cv2.aruco.getPredefinedDictionary(dict_id)


@dataclass(frozen=True)
class Board:
    """A board. `cols` x `rows` count what board generators ask for: inner corners of a
    chessboard (a 10x7-square board is 9x6), squares of a ChArUco board, markers of an
    ArUco grid. `origin_m`, `yaw_deg` and `placement` say where it lies in W (build-model)."""

    cols: int
    rows: int
    square_m: float  # square side (unused by an ArUco grid)
    pattern: str = "chessboard"  # chessboard | charuco | aruco_grid
    marker_m: float | None = None  # marker side; ChArUco default MARKER_FRACTION * square
    dictionary: str = "DICT_5X5_100"
    legacy_pattern: bool = False  # ChArUco boards made with OpenCV < 4.6 (even row count)
    separation_m: float = 0.0  # ArUco grid: gap between markers
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # printed top-left corner in W
    yaw_deg: float = 0.0  # rotation about W's z of the printed x axis
    placement: str = "ground"  # ground: face up, W z up | board: W = OpenCV's board frame

    def __post_init__(self):
        if self.pattern not in PATTERNS:
            raise InputError(f"unknown pattern '{self.pattern}' ({', '.join(PATTERNS)})")
        if self.cols < 2 or self.rows < 2:
            raise InputError(f"board must be at least 2x2, got {self.label}")
        if self.pattern != "aruco_grid" and not self.square_m > 0:
            raise InputError(f"square size must be > 0, got {self.square_m}")
        if self.pattern == "charuco" and not 0 < self.marker_size_m < self.square_m:
            raise InputError(f"marker size must be in (0, square size), got {self.marker_size_m}")
        if self.pattern == "aruco_grid" and not (self.marker_m or 0) > 0:
            raise InputError(f"marker size must be > 0, got {self.marker_m}")
        if self.pattern in MARKER_PATTERNS:
            aruco_dictionary(self.dictionary)
        origin = tuple(float(v) for v in self.origin_m)
        if len(origin) != 3:
            raise InputError(f"origin_m needs 3 numbers, got {len(origin)}")
        if self.placement not in PLACEMENTS:
            raise InputError(f"placement must be ground or board, got {self.placement!r}")
        object.__setattr__(self, "origin_m", origin)
        for name in ("square_m", "separation_m", "yaw_deg"):  # one spelling in files
            object.__setattr__(self, name, float(getattr(self, name)))

    # --- what it is ---------------------------------------------------------------------
    @property
    def label(self) -> str:
        return f"{self.cols}x{self.rows}"

    @property
    def squares(self) -> tuple[int, int]:
        return self.cols, self.rows

    @property
    def marker_size_m(self) -> float | None:
        if self.pattern == "charuco" and self.marker_m is None:
            return MARKER_FRACTION * self.square_m
        return self.marker_m

    @property
    def cell_m(self) -> float:
        """The side `image` scales by: a square, or an ArUco grid's marker."""
        return self.marker_m if self.pattern == "aruco_grid" else self.square_m

    @property
    def size_m(self) -> tuple[float, float]:
        """Width and height of the printed pattern in metres (a chessboard's squares
        included, without a margin)."""
        if self.pattern == "aruco_grid":
            sep = self.separation_m
            return (
                self.cols * self.marker_m + (self.cols - 1) * sep,
                self.rows * self.marker_m + (self.rows - 1) * sep,
            )
        extra = 1 if self.pattern == "chessboard" else 0
        return (self.cols + extra) * self.square_m, (self.rows + extra) * self.square_m

    @property
    def object_points(self) -> np.ndarray:
        """(N, 3) corner positions in metres in OpenCV's board frame (z = 0): the inner
        corners, row by row (chessboard, ChArUco), or the markers' corners (ArUco grid)."""
        if self.pattern == "chessboard":
            j, i = np.mgrid[0 : self.rows, 0 : self.cols]
            return np.column_stack(
                [i.ravel() * self.square_m, j.ravel() * self.square_m, np.zeros(i.size)]
            )
        b = self.cv_board()
        pts = b.getChessboardCorners() if self.pattern == "charuco" else b.getObjPoints()
        return np.asarray(pts, np.float64).reshape(-1, 3)

    @property
    def T_wb(self) -> Pose:
        """Board frame -> W. OpenCV's board frame has x along the printed rows, y down the
        printed image and z into the board; lying face up, that is W's x, -y, -z."""
        flip = np.diag([1.0, -1.0, -1.0]) if self.placement == "ground" else np.eye(3)
        R = matrix_from_rpy(0, 0, np.radians(self.yaw_deg)) @ flip
        return Pose(R, np.asarray(self.origin_m, float))

    # --- OpenCV -------------------------------------------------------------------------
    def cv_board(self):
        """The cv2.aruco CharucoBoard / GridBoard (made on demand: it is not picklable)."""
        if self.pattern not in MARKER_PATTERNS:
            raise InputError(f"a {self.pattern} has no ArUco board")
        d = aruco_dictionary(self.dictionary)
        try:
            if self.pattern == "charuco":
                b = cv2.aruco.CharucoBoard(self.squares, self.square_m, self.marker_size_m, d)
                b.setLegacyPattern(bool(self.legacy_pattern))
            else:
                b = cv2.aruco.GridBoard(self.squares, self.marker_m, self.separation_m, d)
        except cv2.error as e:
            msg = f"cannot build {self.pattern} board {self.label}: {cv_message(e)}"
            raise InputError(msg) from None
        return b

    def cv_detector(self):
        """CharucoDetector (ChArUco) or ArucoDetector (ArUco grid) for this board."""
        board = self.cv_board()
        try:
            if self.pattern == "charuco":
                return cv2.aruco.CharucoDetector(board)
            return cv2.aruco.ArucoDetector(board.getDictionary())
        except cv2.error as e:
            raise InputError(f"board: cannot create detector: {cv_message(e)}") from None

    def image(self, px_per_square: int, margin_squares: int = 0) -> np.ndarray:
        """The board as printed: grey uint8, black 0 on white 255, `px_per_square` pixels a
        square (ArUco grid: a marker side), with a white margin of `margin_squares`."""
        px, m = int(px_per_square), int(margin_squares)
        if self.pattern == "chessboard":  # (cols + 1) x (rows + 1) squares, top-left black
            nx, ny = self.cols + 1 + 2 * m, self.rows + 1 + 2 * m
            a = np.arange(nx * px) // px - m
            b = np.arange(ny * px) // px - m
            inside = ((a >= 0) & (a <= self.cols))[None, :] & ((b >= 0) & (b <= self.rows))[:, None]
            dark = inside & ((a[None, :] + b[:, None]) % 2 == 0)
            return np.where(dark, 0, 255).astype(np.uint8)
        w, h = (int(round(v / self.cell_m * px)) + 2 * m * px for v in self.size_m)
        try:
            return self.cv_board().generateImage((w, h), marginSize=m * px, borderBits=1)
        except cv2.error as e:
            raise InputError(f"cannot draw board {self.label}: {cv_message(e)}") from None

    # --- files --------------------------------------------------------------------------
    def to_yaml(self) -> dict:
        """The board-file mapping (what `load_board` reads; written by synth --ground-board
        and stored in a model's manifest)."""
        if self.pattern not in MARKER_PATTERNS:
            raise InputError("a board file describes a charuco or aruco_grid board")
        d = {
            "type": self.pattern,
            "squares": list(self.squares),
            "square_m": self.square_m,
            "marker_m": self.marker_size_m,
            "dictionary": self.dictionary,
        }
        if self.pattern == "aruco_grid":
            d["separation_m"] = self.separation_m
        else:
            d["legacy_pattern"] = self.legacy_pattern
        d.update(origin_m=[float(v) for v in self.origin_m], yaw_deg=self.yaw_deg)
        d["placement"] = self.placement
        return d

    @classmethod
    def from_yaml(cls, d) -> Board:
        """A board from a board-file mapping (ChArUco or ArUco grid)."""
        if not isinstance(d, dict):
            raise InputError("expected a mapping with type, squares, ...")
        t = str(d.get("type", "charuco")).lower()
        if t not in MARKER_PATTERNS:
            raise InputError(f"type must be charuco or aruco_grid, got {t!r}")
        try:
            cols, rows = (int(v) for v in d["squares"])
            return cls(
                cols,
                rows,
                square_m=float(d.get("square_m", 0.0)),
                pattern=t,
                marker_m=float(d["marker_m"]),
                dictionary=str(d.get("dictionary", FILE_DICTIONARY)).upper(),
                legacy_pattern=bool(d.get("legacy_pattern", False)),
                separation_m=float(d.get("separation_m", 0.0)),
                origin_m=tuple(float(v) for v in d.get("origin_m", (0, 0, 0))),
                yaw_deg=float(d.get("yaw_deg", 0.0)),
                placement=str(d.get("placement", "ground")),
            )
        except KeyError as e:
            raise InputError(f"missing key {e}") from None
        except (TypeError, ValueError) as e:
            raise InputError(f"bad value ({e})") from None


def load_board(path) -> Board:
    """A board file (YAML, see the README); every problem is one InputError naming the file."""
    p = require_file(path, "board file")
    d = read_yaml(p, "board file")
    try:
        return Board.from_yaml(d)
    except InputError as e:
        raise InputError(f"board file {p}: {e}") from None


# --------------------------------------------------------------------------------------
# the camera pose from a board in view
# --------------------------------------------------------------------------------------
class BoardPoser:
    """Pose of the camera in W from the board in one image (None + reason when unreliable:
    fewer than 6 corners, corners nearly in a line, reprojection RMS above `max_rms_px`)."""

    def __init__(self, board: Board, camera: Camera, max_rms_px: float = 1.5):
        self.spec, self.camera, self.max_rms = board, camera, max_rms_px
        self.board = board.cv_board()
        self.det = board.cv_detector()

    def correspondences(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) board points and their (N, 2) pixels; empty when too little is seen."""
        none = np.zeros((0, 3)), np.zeros((0, 2))
        try:
            if self.spec.pattern == "charuco":
                ch_corners, ch_ids, _, _ = self.det.detectBoard(gray)
                if ch_ids is None or len(ch_ids) < 4:
                    return none
                obj = self.board.getChessboardCorners()[ch_ids.ravel()]
                return obj.astype(float), ch_corners.reshape(-1, 2).astype(float)
            corners, ids, _ = self.det.detectMarkers(gray)
            if ids is None or len(ids) == 0:
                return none
            obj, img = self.board.matchImagePoints(corners, ids)
            if obj is None:
                return none
            return obj.reshape(-1, 3).astype(float), img.reshape(-1, 2).astype(float)
        except cv2.error:
            return none

    def pose(self, gray: np.ndarray) -> tuple[Pose | None, str]:
        """T_CW of the view (W from the board's placement), and what was found or why not."""
        obj, img = self.correspondences(gray)
        if len(obj) < 6:
            return None, f"board not found ({len(obj)} corners detected, need 6)"
        spread = np.linalg.svd(obj[:, :2] - obj[:, :2].mean(0), compute_uv=False)
        if spread[1] < 0.5 * max(self.spec.square_m, self.spec.marker_m):
            return None, "board corners nearly collinear"
        cam, ideal = self.camera.standard(), self.camera.ideal_pixels(img)  # any lens model
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, ideal, cam.K, cam.dist, flags=cv2.SOLVEPNP_IPPE)
            if ok:
                rvec, tvec = cv2.solvePnPRefineLM(obj, ideal, cam.K, cam.dist, rvec, tvec)
        except cv2.error as e:
            return None, f"pose from board failed ({cv_message(e)})"
        if not ok:
            return None, "pose from board failed"
        T_cb = Pose.from_rvec_tvec(rvec, tvec)
        rms = float(np.sqrt(np.mean(np.sum((self.camera.project(obj, T_cb) - img) ** 2, 1))))
        if rms > self.max_rms:
            return None, f"board reprojection error {rms:.1f} px > {self.max_rms:g} px"
        return T_cb @ self.spec.T_wb.inverse(), f"{len(obj)} corners, {rms:.2f} px"
