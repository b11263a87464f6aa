"""The nearest-neighbour searches of a landmark model, built once and stored in its file.

Tracking needs, before its first frame, an index over every keyframe's linked descriptors
(global recognition) and the per-point table of descriptor twins (repeated texture). Both
grow with the model: for 144 keyframes (52k linked descriptors) building them took 5 s at
every `mirage track` start. `build-model` now builds them once and the model file holds
them (`model.py`); a model file without them still loads and gets them built here.
"""

from __future__ import annotations

import os
import tempfile

import cv2
import numpy as np

# FLANN's randomised KD-trees: 20-50x faster than brute force over ~20k SIFT descriptors
FLANN_PARAMS = {"algorithm": 1, "trees": 4}
FLANN_CHECKS = 32


class DescriptorIndex:
    """k-nearest-neighbour search over fixed descriptors (`data`, kept alive here): FLANN's
    KD-trees for float descriptors, brute force for binary ones (`hamming`). `stored`: the
    trees as `to_bytes` wrote them (a model file's), used when they load; else built."""

    def __init__(
        self,
        data: np.ndarray,
        hamming: bool = False,
        stored: np.ndarray | None = None,
        seed: int | None = 0,
    ):
        self.data = np.ascontiguousarray(data if hamming else data.astype(np.float32, copy=False))
        self.hamming = hamming
        self.loaded = False
        if hamming or not len(self.data):
            self._bf = cv2.BFMatcher(cv2.NORM_HAMMING if hamming else cv2.NORM_L2)
            return
        if stored is not None and len(stored):
            self.flann = cv2.flann_Index()
            with tempfile.TemporaryDirectory() as d:
                path = os.path.join(d, "index")
                np.asarray(stored, np.uint8).tofile(path)
                try:
                    self.loaded = bool(self.flann.load(self.data, path))
                except cv2.error:  # another FLANN's format: build it again
                    self.loaded = False
        if not self.loaded:
            # FLANN draws its trees from OpenCV's RNG: from a `seed` (0: a new process's
            # state) the trees and every search depend on the data alone (a build and a
            # track of one model find the same twins); None: go on from its state (the
            # recognition trees after the twins', as `track` made them before they were
            # stored); RANSAC seeds it anew anyway
            if seed is not None:
                cv2.setRNGSeed(seed)
            self.flann = cv2.flann_Index(self.data, FLANN_PARAMS)

    def to_bytes(self) -> np.ndarray:
        """The KD-trees as bytes (empty for brute force), for the model file."""
        if self.hamming or not len(self.data):
            return np.zeros(0, np.uint8)
        with tempfile.TemporaryDirectory() as d:
            path = os.path.join(d, "index")
            self.flann.save(path)
            return np.fromfile(path, np.uint8)

    def knn(self, query: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(indices, distances), each (N, k): -1 / inf where there is no such neighbour;
        distances as OpenCV's matchers give them (L2, not squared; Hamming)."""
        q = np.ascontiguousarray(query, dtype=self.data.dtype)
        idx = np.full((len(q), k), -1, np.int64)
        dist = np.full((len(q), k), np.inf)
        if not len(q) or not len(self.data):
            return idx, dist
        if self.hamming:  # binary descriptors (ORB, AKAZE): brute force, as before
            for r, ms in enumerate(self._bf.knnMatch(q, self.data, k=k)):
                for j, m in enumerate(ms[:k]):  # one short list per row
                    idx[r, j], dist[r, j] = m.trainIdx, m.distance
            return idx, dist
        kk = min(k, len(self.data))
        i, d2 = self.flann.knnSearch(q, kk, params={"checks": FLANN_CHECKS})
        i = np.asarray(i, np.int64).reshape(len(q), kk)
        d2 = np.asarray(d2, np.float64).reshape(len(q), kk)
        found = (i >= 0) & (i < len(self.data))
        idx[:, :kk] = np.where(found, i, -1)
        dist[:, :kk] = np.where(found, np.sqrt(np.maximum(d2, 0.0)), np.inf)
        return idx, dist


def point_twins(
    D: np.ndarray,
    P: np.ndarray,
    points: np.ndarray,
    hamming: bool = False,
    separation_m: float = 0.05,
    k: int = 4,
) -> np.ndarray:
    """Per 3D point: True when one of its descriptors has a near twin at another 3D place.

    `D` are the linked descriptors (`hamming`: binary ones), `P` their point ids. Repeated
    texture (floor tiles, look-alike faces) makes a feature match the wrong copy as readily
    as the right one, so such points must not decide a pose on their own. A twin is a
    descriptor of a point more than `separation_m` away that is closer than the model's
    typical distance between two views of one point divided by the Lowe ratio (0.8): a
    query of this point would match the twin or fail the ratio test. One k-nearest-neighbour
    pass over the model's own descriptors, vectorised (52k of 144 keyframes: about 1 s).
    """
    twins = np.zeros(len(points), bool)
    if len(D) < 2:
        return twins
    P = np.asarray(P, np.int64)
    try:
        idx, dist = DescriptorIndex(D, hamming).knn(D, k)
    except cv2.error:
        return twins
    valid = idx >= 0
    pj = P[np.clip(idx, 0, None)]
    rows = np.arange(len(D))[:, None]
    same = valid & (pj == P[:, None]) & (idx != rows)
    sep = np.linalg.norm(points[pj] - points[P][:, None], axis=2)
    other = valid & (sep > separation_m)
    d_same = np.where(same, dist, np.inf).min(1)
    typical = np.median(d_same[np.isfinite(d_same)]) if np.isfinite(d_same).any() else 0.0
    if not typical > 0:
        typical = float(np.median(dist[valid]))
    near = np.where(other, dist, np.inf).min(1) < typical / 0.8
    twins[P[near]] = True
    return twins
