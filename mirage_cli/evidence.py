"""How likely a pose's support is to be chance: the a-contrario test that decides whether a
frame's inliers are evidence of the landmark. Pure core.

A rendered scene gives SIFT matches that are mostly right, so "half the matches agree" once
separated true poses from false ones; on real photographs taken 10-40 deg apart, a third
of the matches agreeing is common for a correct pose (dtu_scan37: 35 of 81, 45 of 96 at
0.8-1.0 px RMS, all within 1.2 mm of the truth), and that rule refused them. What decides
here instead is the number of false alarms (Moisan & Stival's a-contrario RANSAC): if the
matches were wrong (scattered at random over the area they were searched in), how many of
the hypotheses RANSAC tried would collect this much support by chance?

    NFA = hypotheses * P(Binomial(n - s, p) >= k - s)

with n matches, k inliers, s = 3 points per minimal sample, and p the chance that a wrongly
matched point lands within the inlier threshold of where the pose projects it: the
threshold disc over the area searched (the guided radius's disc while tracking; the
matched keypoints' bounding box when relocalising). A pose is evidence when NFA is below
`max_false_alarms` (1e-3: one chance acceptance in a thousand frames without the landmark).
"""

from __future__ import annotations

import numpy as np

MINIMAL_SAMPLE = 3


def chance_inlier_probability(threshold_px: float, area_px2: float) -> float:
    """The chance that a wrongly matched point lies within `threshold_px` of its projection,
    when wrong matches fall anywhere in `area_px2` (at least the threshold disc)."""
    disc = np.pi * threshold_px**2
    return float(min(1.0, disc / max(area_px2, disc)))


def search_area(uv: np.ndarray, min_side_px: float = 64.0) -> float:
    """The area (px^2) wrong matches are spread over when relocalising: the bounding box of
    the matched keypoints (a landmark filling a corner of the frame is searched there)."""
    if len(uv) < 2:
        return min_side_px**2
    lo, hi = np.percentile(uv, [1, 99], axis=0)
    side = np.maximum(hi - lo, min_side_px)
    return float(side[0] * side[1])


def log_binomial_tail(n: int, m: int, p: float) -> float:
    """Natural log of P(Binomial(n, p) >= m), summed in the log domain (no underflow; numpy
    only: scipy.stats costs 40 MB and half a second to import in every `mirage track`)."""
    if m <= 0:
        return 0.0
    if m > n or p <= 0.0:
        return -np.inf
    if p >= 1.0:
        return 0.0
    j = np.arange(m, n + 1)
    k = np.arange(1, n + 1)
    log_c = np.concatenate([[0.0], np.cumsum(np.log(n - k + 1) - np.log(k))])  # log C(n, k)
    terms = log_c[j] + j * np.log(p) + (n - j) * np.log1p(-p)
    top = terms.max()
    return float(top + np.log(np.exp(terms - top).sum()))


def log10_false_alarms(n: int, k: int, p: float, hypotheses: int) -> float:
    """log10 of the expected number of hypotheses with `k` or more of `n` matches agreeing
    by chance (each agreeing with probability `p`)."""
    s = MINIMAL_SAMPLE
    if k <= s or p >= 1.0:
        return float(np.log10(max(hypotheses, 1)))
    tail = log_binomial_tail(max(n - s, 0), k - s, p)  # P(X >= k - s), natural log
    return float(np.log10(max(hypotheses, 1)) + tail / np.log(10))


def is_evidence(n: int, k: int, p: float, hypotheses: int, max_false_alarms: float) -> bool:
    """Do `k` agreeing matches of `n` rule out chance (NFA <= `max_false_alarms`)?"""
    return log10_false_alarms(n, k, p, hypotheses) <= np.log10(max_false_alarms)
