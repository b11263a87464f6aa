"""Pinhole camera with OpenCV lens distortion, and its YAML file (brief, section 3).

The file is written with cv2.FileStorage so OpenCV (and any C++ tool) reads it back.
ROS `camera_info` is read in its common spellings: the calibration YAML of
camera_calibration / camera_info_manager, and `rostopic echo` / `ros2 topic echo` output
(`K`/`D` or `k`/`d`). Two lens models: OpenCV's standard one (ROS `plumb_bob`,
`rational_polynomial`) and its fisheye one (ROS `equidistant`, 4 coefficients), which
must never be read as the other: the same numbers mean a different lens.
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

PINHOLE, FISHEYE = "pinhole", "fisheye"
# distortion_model names (ROS and OpenCV files) -> lens model
LENS_MODELS = {
    "plumb_bob": PINHOLE,
    "rational_polynomial": PINHOLE,
    "pinhole": PINHOLE,
    "radtan": PINHOLE,
    "equidistant": FISHEYE,
    "fisheye": FISHEYE,
}
_CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


@dataclass
class Camera:
    """Intrinsics K (3x3), distortion coefficients (OpenCV order) and image size in px.

    `model` is "pinhole" (OpenCV's standard distortion: k1 k2 p1 p2 [k3 [k4 k5 k6 ...]])
    or "fisheye" (OpenCV's fisheye / ROS equidistant model: k1 k2 k3 k4)."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    rms_px: float | None = None
    meta: dict = field(default_factory=dict)  # board, views used, per-view errors, ...
    model: str = PINHOLE

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=float).reshape(3, 3)
        self.dist = np.asarray(self.dist, dtype=float).ravel()
        if self.dist.size == 0:
            self.dist = np.zeros(4 if self.model == FISHEYE else 5)
        if self.model not in (PINHOLE, FISHEYE):
            raise InputError(f"unknown lens model {self.model!r}: use pinhole or fisheye")
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"camera image size must be positive, got {self.width}x{self.height}")
        if not np.all(np.isfinite(self.K)) or self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise InputError("camera matrix must be finite with positive focal lengths")
        if not np.allclose(self.K[2], [0.0, 0.0, 1.0], rtol=0, atol=1e-9):
            raise InputError(
                f"camera matrix bottom row must be [0, 0, 1], got {np.round(self.K[2], 6).tolist()}"
            )
        if not np.all(np.isfinite(self.dist)):
            raise InputError("distortion coefficients must be finite")
        if self.model == FISHEYE and self.dist.size != 4:
            raise InputError(
                f"the fisheye (equidistant) model has 4 distortion coefficients, "
                f"got {self.dist.size}"
            )
        if self.model == PINHOLE and self.dist.size not in (4, 5, 8, 12, 14):
            raise InputError(
                f"{self.dist.size} distortion coefficients: OpenCV takes 4, 5, 8, 12 or 14"
            )

    # --- accessors ----------------------------------------------------------------------
    fx = property(lambda self: float(self.K[0, 0]), doc="focal length in x (px)")
    fy = property(lambda self: float(self.K[1, 1]), doc="focal length in y (px)")
    cx = property(lambda self: float(self.K[0, 2]), doc="principal point x (px)")
    cy = property(lambda self: float(self.K[1, 2]), doc="principal point y (px)")

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
        if self.model == FISHEYE:
            uv, _ = cv2.fisheye.projectPoints(
                X.reshape(-1, 1, 3),
                pose.rvec.reshape(3, 1),
                pose.t.reshape(3, 1),
                self.K,
                self.dist,
            )
        elif self.dist.size <= 8:  # numpy: OpenCV's projectPoints also works out a
            # Jacobian nobody asked for (0.63 vs 0.1 ms for 3800 points)
            return self._project_standard(X, pose)
        else:
            uv, _ = cv2.projectPoints(X, pose.rvec, pose.t, self.K, self.dist)
        return uv.reshape(-1, 2)

    def _project_standard(self, X: np.ndarray, pose: Pose) -> np.ndarray:
        """cv2.projectPoints of OpenCV's standard model (k1 k2 p1 p2 [k3 [k4 k5 k6]]), its
        operations in its order, so the pixels are the same to the last bit; compiled (one
        pass over the points: 300 points 60-90 -> 18-22 us)."""
        from . import refine  # numba: only the commands that project load it

        R = cv2.Rodrigues(pose.rvec)[0]
        k = np.zeros(8)
        k[: self.dist.size] = self.dist
        out = np.empty((len(X), 2))
        K = self.K
        refine.project_standard(X, R, np.asarray(pose.t, float), k, K[0, 0], K[1, 1], K[0, 2],
                                K[1, 2], out)  # fmt: skip
        return out

    def undistort_points(self, pixels) -> np.ndarray:
        """Normalised image coordinates (N,2) of pixels: lens distortion and K removed."""
        uv = np.ascontiguousarray(np.asarray(pixels, float).reshape(-1, 1, 2))
        if len(uv) == 0:
            return np.zeros((0, 2))
        if self.model == FISHEYE:
            xy = cv2.fisheye.undistortPoints(uv, self.K, self.dist, None, None, None, _CRIT)
        else:
            xy = cv2.undistortPoints(uv, self.K, self.dist, None, None, None, _CRIT)
        return xy.reshape(-1, 2)

    def ideal_pixels(self, pixels) -> np.ndarray:
        """Pixels (N,2) as `standard()` sees them: hands a fisheye camera's points to code
        and OpenCV solvers that know only the standard model (unchanged for pinhole)."""
        if self.model == PINHOLE:
            return np.asarray(pixels, float).reshape(-1, 2)
        xy = self.undistort_points(pixels)
        return xy @ self.K[:2, :2].T + self.K[:2, 2]

    def standard(self) -> Camera:
        """This camera in OpenCV's standard model, seeing `ideal_pixels`: itself for a
        pinhole camera, the distortion-free pinhole with the same K for a fisheye."""
        if self.model == PINHOLE:
            return self
        return Camera(self.K.copy(), np.zeros(5), self.width, self.height, self.rms_px)

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
        return Camera(K, self.dist.copy(), width, height, self.rms_px, dict(self.meta), self.model)

    def same_as(self, other: Camera, tol_px: float = 0.5) -> bool:
        return (
            self.model == other.model
            and self.size == other.size
            and np.allclose(self.K, other.K, atol=tol_px)
            and np.allclose(*self._dists_alike(other), atol=1e-4)
        )

    def _dists_alike(self, other: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Both distortion vectors zero-padded to one length (5 and 8 coefficients of the
        same lens compare equal when the extra ones are 0)."""
        n = max(5, self.dist.size, other.dist.size)
        a, b = np.zeros(n), np.zeros(n)
        a[: self.dist.size], b[: other.dist.size] = self.dist, other.dist
        return a, b

    # --- files --------------------------------------------------------------------------
    def save(self, path) -> None:
        """Write the camera YAML atomically (cv2.FileStorage format)."""
        with atomic_path(path, suffix=".yaml", verify=self._reads_back) as tmp:
            fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
            fs.write("image_width", self.width)
            fs.write("image_height", self.height)
            fs.write("camera_matrix", self.K)
            fs.write("distortion_coefficients", self.dist.reshape(1, -1))
            if self.model == FISHEYE:  # OpenCV has no key for it; ROS's name, read back
                fs.write("distortion_model", "equidistant")
            if self.rms_px is not None:
                fs.write("rms_px", float(self.rms_px))
            for key, value in self.meta.items():
                _fs_write(fs, key, value)
            fs.release()

    def _reads_back(self, path) -> bool:
        """FileStorage reports no write error (a full disk leaves 0 bytes or a cut file):
        the file counts as written only when its camera matrix reads back."""
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        try:
            K = fs.getNode("camera_matrix").mat()
            return K is not None and np.array_equal(K, self.K)
        finally:
            fs.release()

    @classmethod
    def load(cls, path) -> Camera:
        """An OpenCV FileStorage camera YAML or a ROS camera_info in any common spelling.
        Every failure is an InputError naming the file."""
        p = require_file(path, "camera file")
        text = p.read_text(errors="replace")
        try:
            if text.lstrip().startswith("%YAML"):
                return cls._load_opencv(p)
            return _load_camera_info(p, text)
        except InputError as e:
            msg = str(e)
            raise InputError(msg if str(p) in msg else f"camera file {p}: {msg}") from None

    @classmethod
    def _load_opencv(cls, p: Path) -> Camera:
        # FileStorage raises cv2.error, and SystemError on some truncated files
        try:
            fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as e:
            raise InputError(_garbled(p, e)) from None
        try:
            K = fs.getNode("camera_matrix").mat()
            dist = fs.getNode("distortion_coefficients").mat()
            wn, hn = fs.getNode("image_width"), fs.getNode("image_height")
            w, h = wn.real(), hn.real()
            if K is None or K.shape != (3, 3):
                raise InputError(f"camera file {p}: 'camera_matrix' missing or not 3x3")
            if wn.empty() or hn.empty():
                raise InputError(f"camera file {p}: 'image_width'/'image_height' missing")
            if not (w >= 1 and h >= 1):
                raise InputError(
                    f"camera file {p}: image size {w:g}x{h:g}; 'image_width' and "
                    "'image_height' must be positive (pixels of the calibrated images)"
                )
            rms_node = fs.getNode("rms_px")
            rms = rms_node.real() if not rms_node.empty() else None
            meta = {}
            for key in ("board", "views_used", "pattern", "square_m"):
                node = fs.getNode(key)
                if not node.empty():
                    meta[key] = node.string() if node.isString() else node.real()
            node = fs.getNode("distortion_model")
            name = node.string() if not node.empty() and node.isString() else None
            model = _lens_model(p, name)
            dist = np.zeros(0) if dist is None else dist
            return cls(K, dist, int(w), int(h), rms, meta, model)
        except (cv2.error, SystemError) as e:
            raise InputError(_garbled(p, e)) from None
        finally:
            fs.release()


def fold_radius(camera: Camera) -> float:
    """The distorted radius (normalised image coordinates) where the standard model's
    radial term stops growing: a pixel further from the principal point has no ray
    (the polynomial folds back, so iterative undistortion hands it a wrong one). inf
    when it grows up to 70 deg off axis; a fisheye camera's is its own model, not
    checked (inf)."""
    if camera.model != PINHOLE:
        return float("inf")
    d = np.zeros(8)
    d[: min(8, camera.dist.size)] = camera.dist[:8]
    k1, k2, _, _, k3, k4, k5, k6 = d
    r = np.linspace(0.0, np.tan(np.radians(70.0)), 4000)
    r2 = r * r
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    rd = r * num / den
    falls = np.flatnonzero((np.diff(rd) <= 0) | (den[1:] <= 0))
    return float(rd[falls[0]]) if len(falls) else float("inf")


def beyond_fold(camera: Camera) -> float:
    """Share of the image's pixels beyond `fold_radius`: 0 for a lens model valid over
    the whole image. A strong barrel term fitted without views in the corners (k1
    -0.3 at fx 440 px folds 300 px from the centre, inside a 640x480 image's corners)
    maps those pixels to wrong rays."""
    fold = fold_radius(camera)
    if not np.isfinite(fold):
        return 0.0
    u, v = np.meshgrid(np.arange(0, camera.width, 4) + 1.5, np.arange(0, camera.height, 4) + 1.5)
    x = (u - camera.K[0, 2]) / camera.K[0, 0]
    y = (v - camera.K[1, 2]) / camera.K[1, 1]
    return float(np.mean(np.hypot(x, y) >= fold))


def lens_fold_warning(camera: Camera) -> str | None:
    """Why part of the image has no valid ray (`beyond_fold`), or None."""
    share = beyond_fold(camera)
    if share <= 0:
        return None
    px = fold_radius(camera) * camera.K[0, 0]
    return (
        f"the lens distortion folds back {px:.0f} px from the principal point: {share:.1%} "
        "of the image (its corners) maps to no valid ray, so features there give wrong rays"
    )


def _load_camera_info(p: Path, text: str) -> Camera:
    """ROS camera_info: the calibration YAML (image_width, camera_matrix: {rows, cols,
    data}, distortion_coefficients, distortion_model) or `topic echo` output of
    sensor_msgs/CameraInfo (width, height, K/k and D/d as flat lists, then `---`)."""
    try:
        docs = [d for d in yaml.safe_load_all(text) if d is not None]
    except yaml.YAMLError as e:
        raise InputError(
            f"camera file {p} is not valid YAML: {str(e).strip().splitlines()[0]}"
        ) from None
    if not docs or not isinstance(docs[0], dict):
        raise InputError(f"camera file {p} does not hold a camera (expected a mapping)")
    d = docs[0]  # `topic echo` may print several messages; they describe one camera

    def get(*keys):
        key = next((k for k in keys if k in d), None)
        return key, (d[key] if key is not None else None)

    def matrix(keys, size=None):
        key, v = get(*keys)
        if key is None:
            return None, None
        data = v
        if isinstance(v, dict):
            data = v.get("data")
            if data is None:
                raise InputError(f"camera file {p}: '{key}' has no 'data'")
        try:
            a = np.asarray(data, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"camera file {p}: '{key}' is not a list of numbers") from None
        if a.ndim > 2 or (a.ndim == 2 and a.shape[0] * a.shape[1] != a.size):
            raise InputError(f"camera file {p}: '{key}' is not a matrix of numbers")
        if isinstance(v, dict) and "rows" in v and "cols" in v:
            try:
                rows, cols = int(v["rows"]), int(v["cols"])
            except (TypeError, ValueError):
                raise InputError(f"camera file {p}: '{key}' rows/cols not integers") from None
            if rows * cols != a.size:
                raise InputError(
                    f"camera file {p}: '{key}' says {rows}x{cols} but has {a.size} numbers"
                )
        if size is not None and a.size != size:
            raise InputError(f"camera file {p}: '{key}' must have {size} numbers, has {a.size}")
        return key, a.ravel()

    key, K = matrix(("camera_matrix", "K", "k"), 9)
    if key is None:
        raise InputError(f"camera file {p}: 'camera_matrix' (or K / k) missing")
    _, dist = matrix(("distortion_coefficients", "D", "d"))
    try:
        wkey, w = get("image_width", "width")
        hkey, h = get("image_height", "height")
        w, h = int(w), int(h)
    except (TypeError, ValueError):
        raise InputError(
            f"camera file {p}: 'image_width'/'image_height' (or width/height) missing "
            "or not integers"
        ) from None
    if w == 0 and h == 0:
        raise InputError(
            f"camera file {p}: image size is 0x0 (an uncalibrated camera_info message?)"
        )
    rms = d.get("rms_px")
    if rms is not None and not isinstance(rms, int | float):
        raise InputError(f"camera file {p}: 'rms_px' must be a number")
    model = _lens_model(p, d.get("distortion_model"))
    K = K.reshape(3, 3)
    return Camera(K, np.zeros(0) if dist is None else dist, w, h, rms, {}, model)


def _garbled(p: Path, e: Exception) -> str:
    why = "" if isinstance(e, SystemError) else f": {cv_message(e)}"
    return f"camera file {p} is not valid OpenCV YAML (truncated or garbled?){why}"


def _lens_model(p: Path, name) -> str:
    """The lens model of a distortion_model name; an unknown name is refused, because
    reading its coefficients as another model's would silently misplace every pixel."""
    if name is None or name == "":
        return PINHOLE
    model = LENS_MODELS.get(str(name).strip().lower())
    if model is None:
        raise InputError(
            f"camera file {p}: distortion_model {name!r} is not supported "
            f"(use one of {', '.join(LENS_MODELS)})"
        )
    return model


def _fs_write(fs, key, value) -> None:
    if isinstance(value, str | int | float):
        fs.write(key, value)
    elif isinstance(value, np.ndarray):
        fs.write(key, value)
    elif isinstance(value, list | tuple) and all(isinstance(v, int | float) for v in value):
        fs.write(key, np.asarray(value, float).reshape(1, -1))
