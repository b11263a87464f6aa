"""Pinhole camera with OpenCV lens distortion, and its YAML file (brief, section 3).

The file is written with cv2.FileStorage so OpenCV (and any C++ tool) reads it back;
ROS `camera_info` YAML files are read too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from .errors import InputError, cv_message
from .fileio import atomic_path, require_file
from .pose import Pose


@dataclass
class Camera:
    """Intrinsics K (3x3), distortion coefficients (OpenCV order) and image size in px."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    rms_px: float | None = None
    meta: dict = field(default_factory=dict)  # board, views used, per-view errors, ...

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=float).reshape(3, 3)
        self.dist = np.asarray(self.dist, dtype=float).ravel()
        if self.dist.size == 0:
            self.dist = np.zeros(5)
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"camera image size must be positive, got {self.width}x{self.height}")
        if not np.all(np.isfinite(self.K)) or self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise InputError("camera matrix must be finite with positive focal lengths")

    # --- accessors ----------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    @classmethod
    def from_params(cls, width, height, fx, fy=None, cx=None, cy=None, dist=()) -> Camera:
        fy = fx if fy is None else fy
        cx = (width - 1) / 2.0 if cx is None else cx
        cy = (height - 1) / 2.0 if cy is None else cy
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        return cls(K, np.asarray(dist, float), width, height)

    # --- geometry -----------------------------------------------------------------------
    def project(self, points_w, pose: Pose) -> np.ndarray:
        """Pixel coordinates (N,2) of world points seen from `pose`, with distortion."""
        X = np.ascontiguousarray(np.asarray(points_w, float).reshape(-1, 3))
        if len(X) == 0:
            return np.zeros((0, 2))
        uv, _ = cv2.projectPoints(X, pose.rvec, pose.t, self.K, self.dist)
        return uv.reshape(-1, 2)

    def undistort_points(self, pixels) -> np.ndarray:
        """Normalised image coordinates (N,2) of pixels: lens distortion and K removed."""
        uv = np.ascontiguousarray(np.asarray(pixels, float).reshape(-1, 1, 2))
        if len(uv) == 0:
            return np.zeros((0, 2))
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        xy = cv2.undistortPoints(uv, self.K, self.dist, None, None, None, crit)
        return xy.reshape(-1, 2)

    def pixel_rays(self, pixels) -> np.ndarray:
        """Unit viewing rays (N,3) in the camera frame through the given pixels."""
        xy = self.undistort_points(pixels)
        d = np.column_stack([xy, np.ones(len(xy))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def scaled(self, width: int, height: int) -> Camera:
        """The same lens at another resolution (same aspect ratio expected)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        # pixel centres: OpenCV's cx refers to pixel centres at integer coordinates
        K[0, 2] = (self.cx + 0.5) * sx - 0.5
        K[1, 2] = (self.cy + 0.5) * sy - 0.5
        return Camera(K, self.dist.copy(), width, height, self.rms_px, dict(self.meta))

    def same_as(self, other: Camera, tol_px: float = 0.5) -> bool:
        return (
            self.size == other.size
            and np.allclose(self.K, other.K, atol=tol_px)
            and np.allclose(self._dist5(), other._dist5(), atol=1e-4)
        )

    def _dist5(self) -> np.ndarray:
        d = np.zeros(max(5, self.dist.size))
        d[: self.dist.size] = self.dist
        return d

    # --- files --------------------------------------------------------------------------
    def save(self, path) -> None:
        """Write the camera YAML atomically (cv2.FileStorage format)."""
        with atomic_path(path, suffix=".yaml") as tmp:
            fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
            fs.write("image_width", self.width)
            fs.write("image_height", self.height)
            fs.write("camera_matrix", self.K)
            fs.write("distortion_coefficients", self.dist.reshape(1, -1))
            if self.rms_px is not None:
                fs.write("rms_px", float(self.rms_px))
            for key, value in self.meta.items():
                _fs_write(fs, key, value)
            fs.release()

    @classmethod
    def load(cls, path) -> Camera:
        p = require_file(path, "camera file")
        text = p.read_text(errors="replace")
        if text.lstrip().startswith("%YAML"):
            return cls._load_opencv(p)
        return cls._load_plain(p, text)

    @classmethod
    def _load_opencv(cls, p: Path) -> Camera:
        try:
            fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        except cv2.error as e:
            raise InputError(f"camera file {p} is not valid OpenCV YAML: {cv_message(e)}") from None
        try:
            K = fs.getNode("camera_matrix").mat()
            dist = fs.getNode("distortion_coefficients").mat()
            w, h = fs.getNode("image_width").real(), fs.getNode("image_height").real()
            if K is None or K.shape != (3, 3):
                raise InputError(f"camera file {p}: 'camera_matrix' missing or not 3x3")
            if not w or not h:
                raise InputError(f"camera file {p}: 'image_width'/'image_height' missing")
            rms_node = fs.getNode("rms_px")
            rms = rms_node.real() if not rms_node.empty() else None
            meta = {}
            for key in ("board", "views_used", "pattern", "square_m"):
                node = fs.getNode(key)
                if not node.empty():
                    meta[key] = node.string() if node.isString() else node.real()
            return cls(K, np.zeros(5) if dist is None else dist, int(w), int(h), rms, meta)
        finally:
            fs.release()

    @classmethod
    def _load_plain(cls, p: Path, text: str) -> Camera:
        """ROS camera_info YAML (camera_matrix: {rows, cols, data}) or plain lists."""
        try:
            d = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise InputError(
                f"camera file {p} is not valid YAML: {str(e).strip().splitlines()[0]}"
            ) from None
        if not isinstance(d, dict):
            raise InputError(f"camera file {p} does not hold a camera (expected a mapping)")

        def matrix(key, required=True):
            v = d.get(key)
            if v is None:
                if required:
                    raise InputError(f"camera file {p}: '{key}' missing")
                return None
            data = v.get("data") if isinstance(v, dict) else v
            try:
                return np.asarray(data, dtype=float)
            except (TypeError, ValueError):
                raise InputError(f"camera file {p}: '{key}' is not numeric") from None

        K = matrix("camera_matrix")
        if K is None or K.size != 9:
            raise InputError(f"camera file {p}: 'camera_matrix' must have 9 numbers")
        dist = matrix("distortion_coefficients", required=False)
        try:
            w, h = int(d["image_width"]), int(d["image_height"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"camera file {p}: 'image_width'/'image_height' missing") from None
        rms = d.get("rms_px")
        return cls(K.reshape(3, 3), np.zeros(5) if dist is None else dist, w, h, rms)


def _fs_write(fs, key, value) -> None:
    if isinstance(value, str | int | float):
        fs.write(key, value)
    elif isinstance(value, np.ndarray):
        fs.write(key, value)
    elif isinstance(value, list | tuple) and all(isinstance(v, int | float) for v in value):
        fs.write(key, np.asarray(value, float).reshape(1, -1))
