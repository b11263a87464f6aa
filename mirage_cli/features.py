"""Local image features: detector settings stored in the model, detection, ratio matching.

The model stores the detector settings so that `track` detects the same kind of features
in the video as `build-model` stored for the keyframes. Everything returns plain numpy
arrays (pixel coordinates in the *distorted* image), never cv2.KeyPoint lists.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from .errors import InputError


@dataclass(frozen=True)
class DetectorSpec:
    """What the rest of mirage needs to know about a detector, so that nothing checks names.

    `create(nfeatures, params)` builds the OpenCV object (`params` already merged over
    `defaults`); `norm` is the OpenCV distance for matching; `dtype` and `width` describe
    one descriptor row; `transform`, when set, maps OpenCV's descriptors to the stored ones.
    """

    create: Callable[[int, dict], object]
    norm: int
    dtype: type
    width: int
    defaults: dict = field(default_factory=dict)
    transform: Callable[[np.ndarray], np.ndarray] | None = None


def root_sift(desc: np.ndarray) -> np.ndarray:
    """RootSIFT (Arandjelovic & Zisserman 2012): L1-normalise, then square root, so that
    the L2 distance of the results compares histograms by the Hellinger kernel."""
    d = np.asarray(desc, np.float32)
    return np.sqrt(d / np.maximum(np.abs(d).sum(axis=1, keepdims=True), 1e-12))


def _sift(n: int, params: dict):
    return cv2.SIFT_create(nfeatures=n, **params)


# OpenCV's SIFT contrastThreshold 0.04 finds too few features on small, low-contrast
# landmarks in webcam images; 0.02 roughly doubles them at little cost in repeatability.
_SIFT_DEFAULTS = {"contrastThreshold": 0.02}

REGISTRY: dict[str, DetectorSpec] = {
    "sift": DetectorSpec(_sift, cv2.NORM_L2, np.float32, 128, _SIFT_DEFAULTS),
    "rootsift": DetectorSpec(_sift, cv2.NORM_L2, np.float32, 128, _SIFT_DEFAULTS, root_sift),
    "orb": DetectorSpec(
        lambda n, p: cv2.ORB_create(nfeatures=n, **p),
        cv2.NORM_HAMMING,
        np.uint8,
        32,
        {"scaleFactor": 1.2, "nlevels": 8},
    ),
    "akaze": DetectorSpec(  # no feature cap of its own: `detect` keeps the strongest
        lambda n, p: cv2.xfeatures2d.AKAZE_create(**p), cv2.NORM_HAMMING, np.uint8, 61
    ),
}
DETECTORS = tuple(REGISTRY)


def detector_spec(name: str) -> DetectorSpec:
    try:
        return REGISTRY[str(name).lower()]
    except KeyError:
        raise InputError(f"unknown detector {name!r}; choose from {', '.join(DETECTORS)}") from None


@dataclass
class DetectorSettings:
    """Which detector and how many features; `params` go to the OpenCV constructor."""

    name: str = "sift"
    nfeatures: int = 2000
    params: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def spec(self) -> DetectorSpec:
        return detector_spec(self.name)

    @classmethod
    def from_dict(cls, d: dict) -> DetectorSettings:
        s = cls(
            str(d.get("name", "sift")), int(d.get("nfeatures", 2000)), dict(d.get("params", {}))
        )
        detector_spec(s.name)  # an unknown name is an error here, not at first use
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
    spec, n = settings.spec, int(settings.nfeatures)
    params = {**spec.defaults, **settings.params}
    if n < 1:
        raise InputError(f"nfeatures must be >= 1, got {n}")
    try:
        impl = spec.create(n, params)
    except (cv2.error, TypeError) as e:
        raise InputError(f"cannot create {settings.name} detector with {params}: {e}") from None
    return Detector(settings, impl)


def to_gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return img


def detect(gray: np.ndarray, detector: Detector) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (N,2) float32 px and descriptors (N, spec.width) of the spec's dtype.

    Keeps the `nfeatures` strongest responses (AKAZE has no such option itself).
    """
    gray = to_gray(np.asarray(gray))
    settings = detector.settings
    try:
        kps, desc = detector.impl.detectAndCompute(gray, None)
    except cv2.error as e:
        raise InputError(f"feature detection failed: {str(e).strip().splitlines()[-1]}") from None
    spec = settings.spec
    if desc is None or not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, spec.width), spec.dtype)
    pts = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float32)
    if len(kps) > settings.nfeatures:
        resp = np.array([k.response for k in kps])
        keep = np.sort(np.argsort(-resp, kind="stable")[: settings.nfeatures])
        pts, desc = pts[keep], desc[keep]
    if spec.transform is not None:
        desc = spec.transform(desc)
    return pts, np.ascontiguousarray(desc, dtype=spec.dtype)


def make_matcher(settings: DetectorSettings):
    """Brute-force matcher with this detector's norm."""
    return cv2.BFMatcher(settings.spec.norm)


def knn2(desc_query: np.ndarray, desc_train: np.ndarray | None, matcher) -> np.ndarray:
    """(N,4) array of (train index 1, distance 1, train index 2, distance 2) per query row.

    Index -1 / distance inf where there is no such neighbour. `matcher` comes from
    `make_matcher`; `desc_train` may be None when it already holds trained descriptors.
    """
    n = len(desc_query)
    out = np.full((n, 4), np.inf)
    out[:, 0] = out[:, 2] = -1
    if n == 0 or (desc_train is not None and len(desc_train) == 0):
        return out
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
    ratio: float,
    matcher,
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
    keep_px: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Matches (qi, ci) of query features to candidates predicted within `radius_px`.

    Candidates are model features at their predicted pixels; several may share a 3D point
    (`cand_point`, one row per keyframe that saw it), so the ratio test compares the best
    point with the best *other* point inside the radius (a point seen by four keyframes
    no longer fails against itself), and a repeated texture elsewhere in the model never
    competes because it is predicted far away. One query per point (the closest) survives.
    SIFT's integer descriptors within a finite radius go to a compiled loop over the pairs
    inside the radius (`match_kernel`, exact). Other descriptors, or no radius: blockwise
    dense, the queries grouped in cells of twice the radius, each cell's descriptor
    distances (a BLAS product) computed only to the candidates that can lie within the
    radius of one of its queries (on the sample's calls 3x faster than one matrix of every
    pair, the same matches).

    `keep_px` (< `radius_px`): keep only the matches within it of their prediction, the
    ratio test still over `radius_px`: narrowed with the window, it let a text or tiled
    floor match whichever copy the pose being tested put there (near tuning seed 9: 13
    floor matches agreed with a pose 9 cm off and shrank its sigma from 4.3 to 0.4 cm).
    """
    if keep_px is not None and keep_px < radius_px:
        qi, ci = guided_match(
            query_px, query_desc, cand_px, cand_desc, cand_point, radius_px, ratio
        )
        d = np.asarray(query_px, np.float64)[qi] - np.asarray(cand_px, np.float64)[ci]
        near = np.einsum("ij,ij->i", d, d) <= keep_px**2
        return qi[near], ci[near]
    empty = np.zeros(0, np.int64)
    nq, nc = len(query_px), len(cand_px)
    if nq == 0 or nc == 0:
        return empty, empty
    cand_point = np.asarray(cand_point)
    finite = bool(np.isfinite(radius_px))
    qp = np.ascontiguousarray(query_px, np.float32)
    cp = np.ascontiguousarray(cand_px, np.float32)
    if finite and query_desc.dtype != np.uint8:
        qb, cb = _as_bytes(query_desc), _as_bytes(cand_desc)
        if qb is not None and cb is not None:  # SIFT's: integers, exact in any order
            return _guided_compiled(qp, qb, cp, cb, cand_point, float(radius_px), ratio)
    if query_desc.dtype == np.uint8:
        q = c = qn = cn = None
    else:
        q, c = np.asarray(query_desc, np.float32), np.asarray(cand_desc, np.float32)
        qn, cn = np.einsum("ij,ij->i", q, q), np.einsum("ij,ij->i", c, c)
        q = q * np.float32(-2.0)  # exact: (-2 q) . c is -2 (q . c) to the bit
    blocks = _cells(qp, cp, float(radius_px)) if finite else [(np.arange(nq), np.arange(nc))]
    found = []
    for qi, ci in blocks:
        if q is None:
            xor = query_desc[qi][:, None, :] ^ cand_desc[ci][None, :, :]
            d2 = np.bitwise_count(xor).sum(axis=2, dtype=np.int32).astype(np.float32) ** 2
        else:
            d2 = q[qi] @ c[ci].T
            d2 += qn[qi][:, None]
            d2 += cn[ci][None, :]
        if finite:
            dx = np.subtract.outer(qp[qi, 0], cp[ci, 0])
            dy = np.subtract.outer(qp[qi, 1], cp[ci, 1])
            np.copyto(d2, np.float32(np.inf), where=dx * dx + dy * dy > np.float32(radius_px**2))
        col = np.argmin(d2, axis=1)
        best = d2[np.arange(len(d2)), col]
        pts = cand_point[ci]
        pt = pts[col]
        np.copyto(d2, np.float32(np.inf), where=pts[None, :] == pt[:, None])  # other points
        keep = np.isfinite(best) & (best < ratio**2 * d2.min(axis=1))
        found.append((qi[keep], ci[col[keep]], pt[keep], best[keep]))
    if not found:
        return empty, empty
    qi, ci, pt, d = (np.concatenate(x) for x in zip(*found, strict=True))
    return _one_query_per_point(qi, ci, pt, d)


def _one_query_per_point(qi, ci, pt, d) -> tuple[np.ndarray, np.ndarray]:
    """The closest descriptor wins each 3D point (on a tie, the first query); by query."""
    s = np.lexsort((qi, d, pt))
    qi, ci, pt = qi[s], ci[s], pt[s]
    first = np.ones(len(qi), bool)
    first[1:] = pt[1:] != pt[:-1]
    qi, ci = qi[first], ci[first]
    s = np.argsort(qi)
    return qi[s], ci[s]


def _as_bytes(desc: np.ndarray) -> np.ndarray | None:
    """The descriptors as uint8 when they are integers 0..255 held as float (OpenCV's SIFT
    rounds them), else None."""
    with np.errstate(invalid="ignore"):  # NaN or out of range: not equal below
        b = np.asarray(desc).astype(np.uint8)
    return b if np.array_equal(b, desc) else None


def _guided_compiled(qp, qb, cp, cb, cand_point, radius, ratio):
    """`guided_match` for integer descriptors: only the pairs inside the radius, in one
    compiled pass (`match_kernel`); the same matches as the blockwise matrices (on the
    sample's 109 recorded calls: identical, 5.4 -> 2.9 ms a call)."""
    from .match_kernel import ratio_within_radius  # numba: loaded by the commands that track

    by_x = np.argsort(cp[:, 0], kind="stable")
    best_c = np.empty(len(qp), np.int64)
    best_d = np.empty(len(qp), np.float32)
    ratio_within_radius(
        qp, qb, cp, cb, cand_point.astype(np.int64), by_x, np.ascontiguousarray(cp[by_x, 0]),
        radius + 1.0, np.float32(radius**2), np.float32(ratio**2), best_c, best_d,
    )  # fmt: skip
    qi = np.flatnonzero(best_c >= 0)
    ci = best_c[qi]
    return _one_query_per_point(qi, ci, cand_point[ci], best_d[qi])


def _cells(qp: np.ndarray, cp: np.ndarray, radius: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(query rows, candidate rows) per cell of queries (side 2 * radius): every candidate
    within `radius` of one of the cell's queries is among its candidate rows."""
    cell = max(2.0 * radius, 16.0)
    lo = qp.min(axis=0)
    key = np.floor((qp - lo) / cell).astype(np.int64)
    ncx = int(key[:, 0].max()) + 1
    flat = key[:, 1] * ncx + key[:, 0]
    order = np.argsort(flat, kind="stable")
    _, starts = np.unique(flat[order], return_index=True)
    ends = np.append(starts[1:], len(qp))
    by_x = np.argsort(cp[:, 0], kind="stable")
    xs = cp[by_x, 0]
    out = []
    # each cell's candidates: within `radius` of the box its queries span
    reach = radius + 1.0  # a pixel more: float32 rounding never drops a candidate
    q_lo = np.minimum.reduceat(qp[order], starts) - reach
    q_hi = np.maximum.reduceat(qp[order], starts) + reach
    i_lo = np.searchsorted(xs, q_lo[:, 0])
    i_hi = np.searchsorted(xs, q_hi[:, 0], side="right")
    spans = zip(starts, ends, i_lo, i_hi, q_lo[:, 1], q_hi[:, 1], strict=True)
    for a, b, i, j, y0, y1 in spans:
        ci = by_x[i:j]
        y = cp[ci, 1]
        ci = np.sort(ci[(y >= y0) & (y <= y1)])
        if len(ci):
            out.append((order[a:b], ci))
    return out
