"""Local image features: detector settings stored in the model, detection, ratio matching.

The model stores the detector settings so that `track` detects the same kind of features
in the video as `build-model` stored for the keyframes. Everything returns plain numpy
arrays (pixel coordinates in the *distorted* image), never cv2.KeyPoint lists.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from .errors import InputError

DETECTORS = ("sift", "orb", "akaze")


@dataclass
class DetectorSettings:
    """Which detector and how many features; `params` go to the OpenCV constructor."""

    name: str = "sift"
    nfeatures: int = 2000
    params: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> DetectorSettings:
        s = cls(
            str(d.get("name", "sift")), int(d.get("nfeatures", 2000)), dict(d.get("params", {}))
        )
        if s.name not in DETECTORS:
            raise InputError(f"unknown detector {s.name!r}; choose from {', '.join(DETECTORS)}")
        return s


@dataclass
class Detector:
    """An OpenCV feature detector plus the cap on features (AKAZE has no cap of its own)."""

    settings: DetectorSettings
    impl: object

    def detectAndCompute(self, image, mask=None):  # noqa: N802 - OpenCV's name
        """OpenCV's API, for code that wants cv2.KeyPoint lists."""
        return self.impl.detectAndCompute(image, mask)


def make_detector(settings: DetectorSettings) -> Detector:
    name, n, params = settings.name.lower(), int(settings.nfeatures), dict(settings.params)
    if n < 1:
        raise InputError(f"nfeatures must be >= 1, got {n}")
    try:
        if name == "sift":
            # OpenCV's 0.04 finds too few features on small, low-contrast landmarks in
            # webcam images; 0.02 roughly doubles them at little cost in repeatability.
            params.setdefault("contrastThreshold", 0.02)
            impl = cv2.SIFT_create(nfeatures=n, **params)
        elif name == "orb":
            params.setdefault("scaleFactor", 1.2)
            params.setdefault("nlevels", 8)
            impl = cv2.ORB_create(nfeatures=n, **params)
        elif name == "akaze":
            impl = cv2.xfeatures2d.AKAZE_create(**params)
        else:
            raise InputError(f"unknown detector {name!r}; choose from {', '.join(DETECTORS)}")
    except (cv2.error, TypeError) as e:
        raise InputError(f"cannot create {name} detector with {params}: {e}") from None
    return Detector(settings, impl)


def to_gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return img


def detect(gray: np.ndarray, detector: Detector) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (N,2) float32 px and descriptors (N,D): float32 (SIFT) or uint8 (ORB, AKAZE).

    Keeps the `nfeatures` strongest responses (AKAZE has no such option itself).
    """
    gray = to_gray(np.asarray(gray))
    settings = detector.settings
    try:
        kps, desc = detector.impl.detectAndCompute(gray, None)
    except cv2.error as e:
        raise InputError(f"feature detection failed: {str(e).strip().splitlines()[-1]}") from None
    binary = settings.name != "sift"
    if desc is None or not kps:
        d = 32 if settings.name == "orb" else 61 if settings.name == "akaze" else 128
        return np.zeros((0, 2), np.float32), np.zeros((0, d), np.uint8 if binary else np.float32)
    pts = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float32)
    if len(kps) > settings.nfeatures:
        resp = np.array([k.response for k in kps])
        keep = np.sort(np.argsort(-resp, kind="stable")[: settings.nfeatures])
        pts, desc = pts[keep], desc[keep]
    desc = np.ascontiguousarray(desc, dtype=np.uint8 if binary else np.float32)
    return pts, desc


def norm_type(settings: DetectorSettings) -> int:
    return cv2.NORM_L2 if settings.name == "sift" else cv2.NORM_HAMMING


def make_matcher(desc: np.ndarray):
    """Brute-force matcher with the right norm for this kind of descriptor."""
    return cv2.BFMatcher(cv2.NORM_HAMMING if desc.dtype == np.uint8 else cv2.NORM_L2)


def knn2(desc_query: np.ndarray, desc_train: np.ndarray | None, matcher=None) -> np.ndarray:
    """(N,4) array of (train index 1, distance 1, train index 2, distance 2) per query row.

    Index -1 / distance inf where there is no such neighbour. `desc_train` may be None
    when `matcher` already holds trained descriptors (a prebuilt index).
    """
    n = len(desc_query)
    out = np.full((n, 4), np.inf)
    out[:, 0] = out[:, 2] = -1
    if n == 0 or (desc_train is not None and len(desc_train) == 0):
        return out
    matcher = matcher if matcher is not None else make_matcher(desc_query)
    try:
        if hasattr(matcher, "getTrainDescriptors") and len(matcher.getTrainDescriptors()):
            knn = matcher.knnMatch(desc_query, k=2)
        else:
            knn = matcher.knnMatch(desc_query, desc_train, k=2)
    except cv2.error as e:
        raise InputError(f"feature matching failed: {str(e).strip().splitlines()[-1]}") from None
    for m in knn:  # one short list per query: cheap compared to the matching itself
        if not m:
            continue
        out[m[0].queryIdx, 0:2] = m[0].trainIdx, m[0].distance
        if len(m) > 1:
            out[m[0].queryIdx, 2:4] = m[1].trainIdx, m[1].distance
    return out


def ratio_match(
    desc_query: np.ndarray,
    desc_train: np.ndarray,
    ratio: float = 0.8,
    matcher=None,
    mutual: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Lowe-ratio matches (qi, ti) as int arrays; each train feature used at most once.

    With `mutual`, when several queries pick the same train feature only the closest
    survives (a cheap one-to-one constraint that removes most repeated-texture errors).
    """
    k = knn2(desc_query, desc_train, matcher)
    ok = (k[:, 0] >= 0) & (k[:, 1] < ratio * k[:, 3])
    qi = np.flatnonzero(ok).astype(np.int64)
    ti = k[ok, 0].astype(np.int64)
    if mutual and len(qi):
        order = np.lexsort((k[qi, 1], ti))  # by train index, then distance
        qi, ti = qi[order], ti[order]
        first = np.ones(len(ti), bool)
        first[1:] = ti[1:] != ti[:-1]
        qi, ti = qi[first], ti[first]
        order = np.argsort(qi)
        qi, ti = qi[order], ti[order]
    return qi, ti


def guided_match(
    query_px: np.ndarray,
    query_desc: np.ndarray,
    cand_px: np.ndarray,
    cand_desc: np.ndarray,
    cand_point: np.ndarray,
    radius_px: float,
    ratio: float = 0.8,
) -> tuple[np.ndarray, np.ndarray]:
    """Matches (qi, ci) of query features to candidates predicted within `radius_px`.

    Candidates are model features at their predicted pixels; several may share a 3D point
    (`cand_point`, one row per keyframe that saw it), so the ratio test compares the best
    point with the best *other* point inside the radius (a point seen by four keyframes
    no longer fails against itself), and a repeated texture elsewhere in the model never
    competes because it is predicted far away. One query per point (the closest) survives.
    Dense: one descriptor distance matrix (a BLAS product, as cheap as brute-force
    matching) masked by the pixel distance.
    """
    empty = np.zeros(0, np.int64)
    nq, nc = len(query_px), len(cand_px)
    if nq == 0 or nc == 0:
        return empty, empty
    if query_desc.dtype == np.uint8:
        d2 = cv2.batchDistance(query_desc, cand_desc, -1, None, cv2.NORM_HAMMING)[0]
        d2 = d2.astype(np.float32) ** 2
    else:
        q, c = query_desc.astype(np.float32), cand_desc.astype(np.float32)
        d2 = q @ c.T
        d2 *= -2.0
        d2 += (q * q).sum(1)[:, None]
        d2 += (c * c).sum(1)[None, :]
    if np.isfinite(radius_px):
        qp, cp = np.asarray(query_px, np.float32), np.asarray(cand_px, np.float32)
        dx, dy = np.subtract.outer(qp[:, 0], cp[:, 0]), np.subtract.outer(qp[:, 1], cp[:, 1])
        d2[dx * dx + dy * dy > radius_px**2] = np.inf
    col = np.argmin(d2, axis=1)
    best = d2[np.arange(nq), col]
    pt = np.asarray(cand_point)[col]
    d2[np.asarray(cand_point)[None, :] == pt[:, None]] = np.inf  # other 3D points only
    second = d2.min(axis=1)
    keep = np.isfinite(best) & (best < ratio**2 * second)
    qi, ci, pt, d = np.flatnonzero(keep), col[keep], pt[keep], best[keep]
    # one query per 3D point: the closest descriptor wins
    s = np.lexsort((d, pt))
    qi, ci, pt = qi[s], ci[s], pt[s]
    first = np.ones(len(qi), bool)
    first[1:] = pt[1:] != pt[:-1]
    qi, ci = qi[first], ci[first]
    s = np.argsort(qi)
    return qi[s], ci[s]
