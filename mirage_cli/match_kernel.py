"""Guided matching compiled: for each query feature, the descriptor distances to the model
features predicted within the radius, and Lowe's ratio test against the best *other* 3D
point, in one pass.

Why compiled, and why exact: SIFT's descriptors are integers 0..255 (OpenCV rounds them),
so squared distances are integers below 2^24 and every way of summing them gives the same
float32 -- the dense BLAS path of `features.guided_match` and this loop agree to the bit.
The loop computes only the pairs inside the radius (about a third of a cell's pairs) with
integer arithmetic that vectorises, instead of a matrix per cell plus its masking.
"""

from __future__ import annotations

import numpy as np

from .refine import _jit  # numba with the solver kernels' on-disk cache


@_jit
def ratio_within_radius(qp, qd, cp, cd, cpt, by_x, xs, reach, r2, ratio2, best_c, best_d):
    """Per query q: best_c[q] the candidate (lowest index on a tie) with the smallest
    squared descriptor distance among those whose pixel is within sqrt(r2) (float32, as
    the dense path computes it) and best_d[q] that distance, or -1 when none is within the
    radius or the ratio test against the nearest candidate of another point fails.
    Candidates are scanned in x order (`by_x`, `xs` their sorted x) from x - reach to
    x + reach."""
    nq, dim = qd.shape
    buf_c = np.empty(cp.shape[0], np.int64)
    buf_d = np.empty(cp.shape[0], np.float32)
    inf = np.float32(np.inf)
    for q in range(nq):
        qx, qy = qp[q, 0], qp[q, 1]
        lo = np.searchsorted(xs, qx - reach)
        hi = np.searchsorted(xs, qx + reach, side="right")
        m = 0
        bd = inf
        bi = -1
        for s in range(lo, hi):
            c = by_x[s]
            dx = qx - cp[c, 0]
            dy = qy - cp[c, 1]
            if dx * dx + dy * dy > r2:
                continue
            acc = 0
            for k in range(dim):
                v = np.int32(qd[q, k]) - np.int32(cd[c, k])
                acc += v * v
            d = np.float32(acc)
            buf_c[m] = c
            buf_d[m] = d
            m += 1
            if d < bd or (d == bd and c < bi):
                bd = d
                bi = c
        best_c[q] = -1
        if bi < 0:
            continue
        pt = cpt[bi]
        second = inf
        for j in range(m):
            if cpt[buf_c[j]] != pt and buf_d[j] < second:
                second = buf_d[j]
        if bd < ratio2 * second:
            best_c[q] = bi
            best_d[q] = bd
