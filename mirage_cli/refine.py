"""The Mirage-S inner loop, compiled: residuals, the 2n x 6 normal equations, IRLS weights,
the damped Gauss-Newton step and its composition, iterated to convergence.

Why compiled: at n = 100 one solve is about five iterations of a handful of tiny array
operations each, so vectorised numpy spends almost all of its time in per-call overhead
(~300 us a solve, 14x OpenCV's SQPnP).  numba runs the same arithmetic as one machine-code
function (tens of microseconds); `cache=True` stores the compiled code next to this file
(or in numba's user cache), so only the first run on a machine pays the compile.

Conventions as in `solver`: observations are undistorted normalised coordinates (n, 2);
residuals are weighted by fx^2 / fy^2 so costs come out in pixels^2; the pose update is the
left perturbation T <- exp([w, v]) T in the camera frame.
"""

from __future__ import annotations

import math
import os

import numpy as np
from numba import njit

MIN_DEPTH = 1e-6  # m: points closer to (or behind) the camera plane are invalid
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))  # median |r| of 2D N(0, s^2 I) is 1.1774 s


def _jit(f):
    """njit with an on-disk cache; without any writable cache folder, compile per process."""
    try:
        return njit(cache=True)(f)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(f)


FREEZE_WEIGHTS_AFTER = 20  # iterations

# status codes of `refine`, mapped to reasons by the solver
OK = 0
BEHIND_AT_START = 1
SINGULAR = 2
DIVERGED = 3
NOT_CONVERGED = 4


@_jit
def residuals(X, obs, fx, fy, R, t, e, r2, pred, iz):
    """Normalised residuals e (n, 2), per-point squared pixel error r2; the predicted points
    and inverse depths are kept for the Jacobian.  Returns the smallest depth; points at or
    behind MIN_DEPTH are skipped (their entries left unset), so callers check it first."""
    zmin = np.inf
    for i in range(X.shape[0]):
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        z = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + t[2]
        if z < zmin:
            zmin = z
        if z <= MIN_DEPTH:
            continue
        w = 1.0 / z
        px = (R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + t[0]) * w
        py = (R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + t[1]) * w
        ex, ey = obs[i, 0] - px, obs[i, 1] - py
        e[i, 0], e[i, 1] = ex, ey
        r2[i] = fx * fx * ex * ex + fy * fy * ey * ey
        pred[i, 0], pred[i, 1] = px, py
        iz[i] = w
    return zmin


@_jit
def normal_equations(fx, fy, pred, iz, wt, e, H, g):
    """H = J^T W J and g = J^T W e (pixel units) for the left perturbation (w, v).

    d(x, y)/d(w, v) of x = X/Z, y = Y/Z under X_c -> X_c + w x X_c + v:
      x row: [-x y, 1 + x^2, -y, 1/z, 0, -x/z];  y row: [-(1 + y^2), x y, x, 0, 1/z, -y/z]
    """
    H[:] = 0.0
    g[:] = 0.0
    jx = np.empty(6)
    jy = np.empty(6)
    fx2, fy2 = fx * fx, fy * fy
    for i in range(pred.shape[0]):
        wi = wt[i]
        if wi == 0.0:
            continue
        x, y, w = pred[i, 0], pred[i, 1], iz[i]
        jx[0], jx[1], jx[2], jx[3], jx[4], jx[5] = -x * y, 1.0 + x * x, -y, w, 0.0, -x * w
        jy[0], jy[1], jy[2], jy[3], jy[4], jy[5] = -(1.0 + y * y), x * y, x, 0.0, w, -y * w
        ax, ay = wi * fx2, wi * fy2
        ex, ey = ax * e[i, 0], ay * e[i, 1]
        for a in range(6):
            g[a] += jx[a] * ex + jy[a] * ey
            ja, jb = ax * jx[a], ay * jy[a]
            for b in range(a, 6):
                H[a, b] += ja * jx[b] + jb * jy[b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]


@_jit
def robust_weights(r2, use_robust, huber_px, reject_px, wt):
    """IRLS weights: Huber on the 2D residual norm, hard rejection of gross outliers.

    The thresholds adapt to a robust scale (median |r| of a 2D Gaussian is 1.18 sigma), so
    far from the solution, when every residual is large, the weights stay near least squares
    and only real outliers are damped; near the solution the px floors apply.
    """
    n = r2.shape[0]
    if not use_robust:
        wt[:] = 1.0
        return
    s2 = np.sort(r2)[n // 2] / (RAYLEIGH_MEDIAN * RAYLEIGH_MEDIAN)
    k2 = max(huber_px * huber_px, 6.25 * s2)
    cut2 = max(reject_px * reject_px, 25.0 * s2)
    far = 0
    for i in range(n):
        wt[i] = min(math.sqrt(k2 / max(r2[i], 1e-300)), 1.0)
        if r2[i] > cut2:
            far += 1
    if far > 0 and n - far >= 3:
        for i in range(n):
            if r2[i] > cut2:
                wt[i] = 0.0


@_jit
def _cholesky_solve(H, g, lam, out):
    """Solve (H + lam diag(H)) x = g by Cholesky; False if not positive definite."""
    L = np.zeros((6, 6))
    for j in range(6):
        s = H[j, j] * (1.0 + lam)
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, 6):
            s = H[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    for i in range(6):
        s = g[i]
        for k in range(i):
            s -= L[i, k] * out[k]
        out[i] = s / L[i, i]
    for i in range(5, -1, -1):
        s = out[i]
        for k in range(i + 1, 6):
            s -= L[k, i] * out[k]
        out[i] = s / L[i, i]
    return True


@_jit
def exp_so3(w0, w1, w2):
    """Rotation matrix of a rotation vector (Rodrigues)."""
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-16:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    R = np.empty((3, 3))
    R[0, 0] = 1.0 + b * (w0 * w0 - th2)
    R[0, 1] = b * w0 * w1 - a * w2
    R[0, 2] = b * w0 * w2 + a * w1
    R[1, 0] = b * w0 * w1 + a * w2
    R[1, 1] = 1.0 + b * (w1 * w1 - th2)
    R[1, 2] = b * w1 * w2 - a * w0
    R[2, 0] = b * w0 * w2 - a * w1
    R[2, 1] = b * w1 * w2 + a * w0
    R[2, 2] = 1.0 + b * (w2 * w2 - th2)
    return R


@_jit
def _dot(a, b):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@_jit
def _try_step(X, obs, fx, fy, S, cur, k, step, alpha, wt):
    """Weighted cost at exp(alpha step) T_cur, evaluated into slot k of the state S; inf if a
    point goes behind the camera or the step is not finite."""
    Rs, ts, es, r2s, ps, izs = S
    d = step * alpha
    if not np.all(np.isfinite(d)):
        return np.inf
    dR = exp_so3(d[0], d[1], d[2])
    R0, t0, R1, t1 = Rs[cur], ts[cur], Rs[k], ts[k]
    for a in range(3):  # R1 = dR R0, t1 = dR t0 + v (3x3: loops beat a BLAS call)
        for b in range(3):
            R1[a, b] = dR[a, 0] * R0[0, b] + dR[a, 1] * R0[1, b] + dR[a, 2] * R0[2, b]
        t1[a] = dR[a, 0] * t0[0] + dR[a, 1] * t0[1] + dR[a, 2] * t0[2] + d[3 + a]
    if residuals(X, obs, fx, fy, R1, t1, es[k], r2s[k], ps[k], izs[k]) <= MIN_DEPTH:
        return np.inf
    return _dot(wt, r2s[k])


@_jit
def refine(X, obs, fx, fy, R0, t0, max_iterations, use_robust, huber_px, reject_px, tol):
    """Gauss-Newton / IRLS on the left perturbation from (R0, t0).

    Returns (status, R, t, r2, wt, H, iterations).  Each step is Gauss-Newton with an exact
    line search on the parabola through the cost, its slope and the full step (a large-
    residual problem otherwise overshoots along a weak direction and converges only
    linearly), falling back to Levenberg-Marquardt damping until the cost drops; the damping
    persists (shrinking) across iterations so a near-singular direction (small planar
    targets) cannot throw the pose around.
    """
    n = X.shape[0]
    # three slots of (R, t, residuals, r2, predicted points, inverse depths): the current
    # pose, the full step and the line-search step; accepting a trial swaps slot indices
    S = (
        np.empty((3, 3, 3)),
        np.empty((3, 3)),
        np.empty((3, n, 2)),
        np.empty((3, n)),
        np.empty((3, n, 2)),
        np.empty((3, n)),
    )
    Rs, ts, es, r2s, ps, izs = S
    cur = 0
    Rs[0], ts[0] = R0, t0
    wt = np.ones(n)
    H = np.zeros((6, 6))
    g = np.zeros(6)
    step = np.zeros(6)
    if residuals(X, obs, fx, fy, Rs[0], ts[0], es[0], r2s[0], ps[0], izs[0]) <= MIN_DEPTH:
        return BEHIND_AT_START, Rs[0], ts[0], r2s[0], wt, H, 0
    inv_depth = np.mean(izs[0])
    dof = 2 * n - 6
    lam = 0.0
    converged = False
    iterations = 0
    for it in range(1, max_iterations + 1):
        iterations = it
        if it <= FREEZE_WEIGHTS_AFTER:
            # IRLS can cycle between weight sets on a few points (seen on tilted planar
            # targets); with the weights fixed it is plain weighted least squares and converges
            robust_weights(r2s[cur], use_robust, huber_px, reject_px, wt)
        normal_equations(fx, fy, ps[cur], izs[cur], wt, es[cur], H, g)
        cost0 = _dot(wt, r2s[cur])
        ka, kb = (cur + 1) % 3, (cur + 2) % 3
        found = -1  # slot of the accepted trial
        cost1 = slope = 0.0
        alpha_used = 1.0
        while found < 0:
            if not _cholesky_solve(H, g, lam, step):
                return SINGULAR, Rs[cur], ts[cur], r2s[cur], wt, H, iterations
            slope = _dot(step, g)  # cost(a) = cost0 - 2 a slope + O(a^2) along the step
            if not math.isfinite(slope):
                return SINGULAR, Rs[cur], ts[cur], r2s[cur], wt, H, iterations
            ca = _try_step(X, obs, fx, fy, S, cur, ka, step, 1.0, wt)
            k, c, alpha_used = ka, ca, 1.0
            if ca < np.inf and lam == 0.0:
                curv = ca - cost0 + 2.0 * slope
                alpha = min(slope / curv, 8.0) if curv > 0.0 else 4.0
                if alpha >= 0.2 and abs(alpha - 1.0) > 0.15:
                    cb = _try_step(X, obs, fx, fy, S, cur, kb, step, alpha, wt)
                    if cb < ca:
                        k, c, alpha_used = kb, cb, alpha
            if c < np.inf and c <= cost0 * (1.0 + 1e-12) + 1e-30:
                found, cost1 = k, c
            elif lam > 1e8:
                break
            else:
                lam = 1e-6 if lam == 0.0 else lam * 4.0
        if found < 0:
            converged = True  # no descent possible: at a minimum to machine precision
            break
        damped = lam > 0.0
        lam = 0.0 if lam <= 1e-9 else lam / 3.0
        cur = found
        d = step * alpha_used
        small = (
            math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
            + math.sqrt(d[3] * d[3] + d[4] * d[4] + d[5] * d[5]) * inv_depth
        )
        # Converged when the step is tiny, or (with redundancy) when it moves the pose by
        # less than ~1e-3 of its own standard deviation (delta^T H delta vs sigma^2).
        if (
            small < tol
            or cost0 - cost1 <= 1e-14 * cost0
            or (dof > 0 and not damped and slope < 1e-6 * cost0 / dof)
        ):
            converged = True
            break
    R, t, r2 = Rs[cur].copy(), ts[cur].copy(), r2s[cur].copy()
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return DIVERGED, R, t, r2, wt, H, iterations
    robust_weights(r2, use_robust, huber_px, reject_px, wt)
    if not converged:
        # one more linearisation at the final pose so the covariance belongs to it
        normal_equations(fx, fy, ps[cur], izs[cur], wt, es[cur], H, g)
        if not _cholesky_solve(H, g, 0.0, step):
            return SINGULAR, R, t, r2, wt, H, iterations
        sw = math.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2)
        sv = math.sqrt(step[3] ** 2 + step[4] ** 2 + step[5] ** 2)
        if not sw + sv * inv_depth <= 1e-6:
            return NOT_CONVERGED, R, t, r2, wt, H, iterations
    return OK, R, t, r2, wt, H, iterations


@_jit
def inspect_points(X, u):
    """(all finite, eigenvalues of the 3D points' scatter matrix ascending): the checks
    `solve_pose` makes before solving (degenerate, planar), in one pass."""
    n = X.shape[0]
    m = np.zeros(3)
    for i in range(n):
        for a in range(3):
            if not math.isfinite(X[i, a]):
                return False, np.zeros(3)
            m[a] += X[i, a]
        if not (math.isfinite(u[i, 0]) and math.isfinite(u[i, 1])):
            return False, np.zeros(3)
    m /= n
    S = np.zeros((3, 3))
    for i in range(n):
        d0, d1, d2 = X[i, 0] - m[0], X[i, 1] - m[1], X[i, 2] - m[2]
        S[0, 0] += d0 * d0
        S[0, 1] += d0 * d1
        S[0, 2] += d0 * d2
        S[1, 1] += d1 * d1
        S[1, 2] += d1 * d2
        S[2, 2] += d2 * d2
    S[1, 0], S[2, 0], S[2, 1] = S[0, 1], S[0, 2], S[1, 2]
    return True, np.linalg.eigvalsh(S)


@_jit
def normalise_pinhole(u, fx, fy, cx, cy, skew):
    """Normalised coordinates of pixels through K^-1 (no lens distortion)."""
    n = u.shape[0]
    xy = np.empty((n, 2))
    for i in range(n):
        y = (u[i, 1] - cy) / fy
        xy[i, 0] = (u[i, 0] - cx - skew * y) / fx
        xy[i, 1] = y
    return xy


@_jit
def solution_stats(X, R, t, wt, r2):
    """(smallest depth, points used, their sum of squared px error, weighted cost)."""
    zmin = np.inf
    used = 0
    s = 0.0
    sw = 0.0
    for i in range(X.shape[0]):
        z = R[2, 0] * X[i, 0] + R[2, 1] * X[i, 1] + R[2, 2] * X[i, 2] + t[2]
        zmin = min(zmin, z)
        if wt[i] > 0.0:
            used += 1
            s += r2[i]
            sw += wt[i] * r2[i]
    return zmin, used, s, sw


@_jit
def covariance(H, s2):
    """(ok, (H)^-1 s2): eigen-decomposition so a (near-)singular H is refused rather than
    inverted into huge numbers."""
    ev, V = np.linalg.eigh(H)
    if not (np.all(np.isfinite(ev)) and ev[0] > 1e-14 * ev[5]):
        return False, np.full((6, 6), np.nan)
    C = np.zeros((6, 6))
    for a in range(6):
        for b in range(a, 6):
            s = 0.0
            for k in range(6):
                s += V[a, k] * V[b, k] / ev[k]
            C[a, b] = s * s2
            C[b, a] = C[a, b]
    return bool(np.all(np.isfinite(C))), C


def cached_on_disk() -> bool:
    """Whether the compiled solver is in numba's on-disk cache; if not, the first solve in
    this process compiles it (~8 s), which the CLI announces.  True when unknown."""
    try:
        return os.path.exists(refine._cache._cache_file._index_path)
    except AttributeError:  # caching unavailable, or numba internals moved
        return True


@_jit
def sandwich_terms(X, xy, fx, fy, R, t, huber_px, use_huber, J, r, w, H):
    """The sandwich covariance's first pass: per point the 2x6 pixel Jacobian J (n, 2, 6) of
    the left perturbation and the pixel residual r (n, 2) at (R, t), the Huber weights w
    (1 without `use_huber`) and H = sum w J^T J. False if a point is at or behind the
    camera (no Jacobian there)."""
    n = X.shape[0]
    r2 = np.empty(n)
    for i in range(n):
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        z = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + t[2]
        if not z > MIN_DEPTH:
            return False
        iz = 1.0 / z
        x = (R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + t[0]) * iz
        y = (R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + t[1]) * iz
        J[i, 0, 0], J[i, 0, 1], J[i, 0, 2] = -fx * x * y, fx * (1.0 + x * x), -fx * y
        J[i, 0, 3], J[i, 0, 4], J[i, 0, 5] = fx * iz, 0.0, -fx * x * iz
        J[i, 1, 0], J[i, 1, 1], J[i, 1, 2] = -fy * (1.0 + y * y), fy * x * y, fy * x
        J[i, 1, 3], J[i, 1, 4], J[i, 1, 5] = 0.0, fy * iz, -fy * y * iz
        r[i, 0] = (xy[i, 0] - x) * fx
        r[i, 1] = (xy[i, 1] - y) * fy
        r2[i] = r[i, 0] * r[i, 0] + r[i, 1] * r[i, 1]
    if use_huber:  # the fit's own weights, without its gross-outlier cut
        robust_weights(r2, True, huber_px, math.inf, w)
    else:
        w[:] = 1.0
    H[:] = 0.0
    for i in range(n):
        for a in range(6):
            ja0, ja1 = w[i] * J[i, 0, a], w[i] * J[i, 1, a]
            for b in range(a, 6):
                H[a, b] += ja0 * J[i, 0, b] + ja1 * J[i, 1, b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return True


@_jit
def sandwich_meat(J, r, w, Hi, M):
    """The sandwich's middle: M = sum g g^T with g = w J^T e and e = (I - w J Hi J^T)^-1 r,
    the residual as it would be without the point (HC3 leverage correction)."""
    n = J.shape[0]
    M[:] = 0.0
    JH = np.empty((2, 6))
    g = np.empty(6)
    for i in range(n):
        for k in range(2):
            for b in range(6):
                s = 0.0
                for a in range(6):
                    s += J[i, k, a] * Hi[a, b]
                JH[k, b] = s * w[i]
        h00 = h01 = h10 = h11 = 0.0
        for b in range(6):
            h00 += JH[0, b] * J[i, 0, b]
            h01 += JH[0, b] * J[i, 1, b]
            h10 += JH[1, b] * J[i, 0, b]
            h11 += JH[1, b] * J[i, 1, b]
        a00, a01, a10, a11 = 1.0 - h00, -h01, -h10, 1.0 - h11
        det = a00 * a11 - a01 * a10
        if not abs(det) > 1e-3:
            det = 1e-3  # a point that alone fixes a direction
        e0 = (a11 * r[i, 0] - a01 * r[i, 1]) / det
        e1 = (-a10 * r[i, 0] + a00 * r[i, 1]) / det
        for a in range(6):
            g[a] = w[i] * (J[i, 0, a] * e0 + J[i, 1, a] * e1)
        for a in range(6):
            for b in range(a, 6):
                M[a, b] += g[a] * g[b]
    for a in range(6):
        for b in range(a):
            M[a, b] = M[b, a]


@_jit
def project_standard(X, R, t, k, fx, fy, cx, cy, out):
    """Pixels (n, 2) of OpenCV's standard lens model (k1 k2 p1 p2 k3 k4 k5 k6 in `k`), each
    operation in the order of cv2.projectPoints (a point at depth 0 divided by 1, as there),
    so the pixels are the same to the last bit; one pass instead of twenty array
    operations."""
    for i in range(X.shape[0]):
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        Y0 = R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + t[0]
        Y1 = R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + t[1]
        z = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + t[2]
        iz = 1.0 / (z if z != 0 else 1.0)
        x, y = Y0 * iz, Y1 * iz
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        cdist = 1 + k[0] * r2 + k[1] * r4 + k[4] * r6
        icdist2 = 1.0 / (1 + k[5] * r2 + k[6] * r4 + k[7] * r6)
        a1, a2, a3 = 2 * x * y, r2 + 2 * x * x, r2 + 2 * y * y
        xd = x * cdist * icdist2 + k[2] * a1 + k[3] * a2
        yd = y * cdist * icdist2 + k[2] * a3 + k[3] * a1
        out[i, 0] = xd * fx + cx
        out[i, 1] = yd * fy + cy
