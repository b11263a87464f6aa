"""Mirage-S: camera pose from 3D-2D correspondences, refined from a reference pose (brief 4.1).

Mirage-S starts at a reference pose (a keyframe's pose, the previous frame's pose) and
explains the pixel differences between observed and predicted points by a small pose-error
transform E, actual = exp(E) * current.  Each point gives two linear equations in the six
parameters of E (rotation vector w, translation v, both in the camera frame); the 2n x 6
system is solved by weighted least squares, E is composed on the left and the projection is
re-linearised until the update is tiny.  Starting from the reference resolves the ambiguities
(P3P's up to four roots, the planar two-fold flip) that make global solvers fail with few
points, and the same normal equations give the pose covariance for free.

Everything here is pure computation: no file or terminal I/O, and no exception escapes
from numpy or OpenCV -- every failure is a `PoseEstimate` with success=False and a reason,
never a wrong pose.

Covariance parametrisation (used by every method): the 6-vector (w, v) of the left
perturbation T_CW' = exp([w, v]) T_CW, i.e. R' = exp(w) R, t' = exp(w) t + v.  To first order
the camera centre moves by -R^T v, so the centre covariance is R^T Cov(v) R; the rotation
error angle is |w|.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.linalg import lapack

from .camera import Camera
from .pose import Pose, rodrigues, rotvec

METHODS = ("mirage-s", "epnp", "sqpnp", "iterative", "ap3p")
_CV_FLAGS = {
    "epnp": cv2.SOLVEPNP_EPNP,
    "sqpnp": cv2.SOLVEPNP_SQPNP,
    "iterative": cv2.SOLVEPNP_ITERATIVE,
    "ap3p": cv2.SOLVEPNP_AP3P,
}
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))  # median of |r| for 2D N(0, s^2 I) is 1.1774 s
_MIN_DEPTH = 1e-6  # m: points closer to (or behind) the camera plane are invalid
_MIN_ROBUST = 6  # below this many points (<= 4 redundant equations) robust weights only cost


@dataclass
class PoseEstimate:
    """Result of `solve_pose`.  `pose` is None whenever `success` is False.

    covariance: 6x6, order (w_x, w_y, w_z [rad], v_x, v_y, v_z [m]) of the left perturbation
    exp([w, v]) T_CW in the camera frame (see the module docstring), in the pixel-noise units
    of the residuals.  sigma_pos_m is the RMS 3D camera-centre error it predicts,
    sqrt(trace(Cov_v)) (= sqrt(trace) of the centre covariance, rotation-invariant);
    sigma_rot_deg is the predicted RMS rotation angle error, sqrt(trace(Cov_w)) in degrees.
    """

    pose: Pose | None
    success: bool
    reason: str = ""
    iterations: int = 0
    rmse_px: float = float("nan")
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    method: str = "mirage-s"
    sigma_px: float = float("nan")  # pixel noise sigma used for the covariance

    @property
    def sigma_pos_m(self) -> float:
        return float(np.sqrt(max(np.trace(self.covariance[3:, 3:]), 0.0)))

    @property
    def sigma_rot_deg(self) -> float:
        return float(np.degrees(np.sqrt(max(np.trace(self.covariance[:3, :3]), 0.0))))

    @property
    def center_covariance(self) -> np.ndarray:
        """3x3 covariance of the camera centre in W (m^2)."""
        if self.pose is None:
            return np.full((3, 3), np.nan)
        R = self.pose.R
        return R.T @ self.covariance[3:, 3:] @ R


def _fail(reason: str, n: int, method: str, iterations: int = 0) -> PoseEstimate:
    return PoseEstimate(
        None, False, reason, iterations, float("nan"), np.zeros(n, dtype=bool), method=method
    )


def _exp_so3(w0: float, w1: float, w2: float) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues), lean for the inner loop."""
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-16:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    # R = I + a K + b K^2, with K^2 = w w^T - th2 I
    return np.array(
        [
            [1.0 + b * (w0 * w0 - th2), b * w0 * w1 - a * w2, b * w0 * w2 + a * w1],
            [b * w0 * w1 + a * w2, 1.0 + b * (w1 * w1 - th2), b * w1 * w2 - a * w0],
            [b * w0 * w2 - a * w1, b * w1 * w2 + a * w0, 1.0 + b * (w2 * w2 - th2)],
        ]
    )


class _Problem:
    """Correspondences in normalised coordinates, with buffers reused by every iteration.

    Residuals are kept in normalised units e = [x_obs - x; y_obs - y] (length 2n) and weighted
    by fx^2 / fy^2 so that costs, RMSE and covariance come out in pixels.  The Jacobian is
    stored transposed (6 x 2n) so each row is written contiguously; columns 0 and 5 are
    stored negated (both halves share the sign) and the x half of row 2 likewise, which the
    solve undoes with a sign vector instead of extra negations per iteration.
    """

    _SIGN = np.array([-1.0, 1.0, -1.0, 1.0, 1.0, -1.0])

    def __init__(self, X: np.ndarray, xy: np.ndarray, fx: float, fy: float):
        n = len(X)
        self.n = n
        self.X = X
        self.XT = np.ascontiguousarray(X.T)
        self.obs = np.concatenate((xy[:, 0], xy[:, 1]))
        self.fx, self.fy = fx, fy
        self.fs2 = np.concatenate((np.full(n, fx * fx), np.full(n, fy * fy)))
        self.pred = np.empty(2 * n)
        self.At = np.zeros((6, 2 * n))

    def residuals(self, R: np.ndarray, t: np.ndarray):
        """(e, e2, r2, iz, zmin): normalised residuals, their pixel squares, per-point |r|^2."""
        n = self.n
        Xc = R @ self.XT
        Xc += t[:, None]
        z = Xc[2]
        zmin = float(z.min())
        if zmin <= _MIN_DEPTH:
            return None, None, None, None, zmin
        iz = 1.0 / z
        p = self.pred.reshape(2, n)
        np.multiply(Xc[:2], iz, out=p)
        e = self.obs - self.pred
        e2 = e * e
        e2 *= self.fs2
        r2 = e2[:n] + e2[n:]
        return e, e2, r2, iz, zmin

    def point_r2(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Per-point squared pixel error; inf for points behind the camera (outliers may be)."""
        Xc = R @ self.XT + t[:, None]
        front = Xc[2] > _MIN_DEPTH
        p = Xc[:2] / np.where(front, Xc[2], 1.0)
        e = self.obs.reshape(2, self.n) - p
        r2 = (e[0] * self.fx) ** 2 + (e[1] * self.fy) ** 2
        r2[~front] = np.inf
        return r2

    def normal_equations(self, iz: np.ndarray, wt: np.ndarray, e: np.ndarray):
        """H = J^T W J and g = J^T W e for the left perturbation (w, v), pixel units.

        Uses the predicted points of the last `residuals` call (the linearisation point).
        """
        n = self.n
        At = self.At
        x, y = self.pred[:n], self.pred[n:]
        # d(x, y)/d(w, v) of x = X/Z, y = Y/Z under X_c -> X_c + w x X_c + v:
        #   x row: [-x y, 1 + x^2, -y, 1/z, 0, -x/z];  y row: [-(1 + y^2), x y, x, 0, 1/z, -y/z]
        np.multiply(x, y, out=At[0, :n])
        At[1, n:] = At[0, :n]
        np.multiply(x, x, out=At[1, :n])
        At[1, :n] += 1.0
        np.multiply(y, y, out=At[0, n:])
        At[0, n:] += 1.0
        At[2, :n] = y
        np.negative(x, out=At[2, n:])
        At[3, :n] = iz
        At[4, n:] = iz
        np.multiply(x, iz, out=At[5, :n])
        np.multiply(y, iz, out=At[5, n:])
        w2 = np.concatenate((wt, wt))
        w2 *= self.fs2
        Aw = At * w2
        H = Aw @ At.T
        g = Aw @ e
        s = self._SIGN
        return H * s[:, None] * s, g * s


def _robust_weights(r2: np.ndarray, robust: str, huber_px: float, reject_px: float):
    """IRLS weights: Huber on the 2D residual norm, hard rejection of gross outliers.

    The thresholds adapt to a robust scale (median |r| of a 2D Gaussian is 1.18 sigma), so
    far from the solution, when every residual is large, the weights stay near least squares
    and only real outliers are damped; near the solution the px floors apply.
    """
    if robust == "none":
        return np.ones_like(r2)
    m = len(r2) // 2
    s2 = float(np.partition(r2, m)[m]) / (_RAYLEIGH_MEDIAN * _RAYLEIGH_MEDIAN)
    k2 = max(huber_px * huber_px, 6.25 * s2)
    cut2 = max(reject_px * reject_px, 25.0 * s2)
    wt = np.sqrt(k2 / np.maximum(r2, 1e-300))
    np.minimum(wt, 1.0, out=wt)
    far = r2 > cut2
    if far.any() and len(r2) - int(far.sum()) >= 3:
        wt[far] = 0.0
    return wt


def _spd_solve(H: np.ndarray, g: np.ndarray) -> np.ndarray | None:
    """Cholesky solve of the 6x6 normal equations (LAPACK dposv: ~5x less overhead than
    np.linalg.solve); None when H is not positive definite (degenerate geometry)."""
    _, x, info = lapack.dposv(H, g)
    return x if info == 0 else None


def _try_step(prob: _Problem, R, t, delta, alpha: float, wt):
    """(weighted cost, step, state) at exp(alpha delta) T, or None if points go behind."""
    d = delta * alpha if alpha != 1.0 else delta
    d0, d1, d2, d3, d4, d5 = d.tolist()
    if not math.isfinite(d0 + d1 + d2 + d3 + d4 + d5):
        return None
    dR = _exp_so3(d0, d1, d2)
    R1 = dR @ R
    t1 = dR @ t
    t1[0] += d3
    t1[1] += d4
    t1[2] += d5
    e1, e21, r21, iz1, _ = prob.residuals(R1, t1)
    if e1 is None:
        return None
    return float(np.dot(wt, r21)), d, (R1, t1, e1, e21, r21, iz1)


def _refine(
    prob: _Problem,
    pose: Pose,
    max_iterations: int,
    robust: str,
    huber_px: float,
    reject_px: float,
    tol: float,
):
    """Gauss-Newton / IRLS on the left perturbation.  Returns a dict or a failure reason."""
    R, t = pose.R.copy(), pose.t.copy()
    e, e2, r2, iz, zmin = prob.residuals(R, t)
    if e is None:
        return "points behind the camera at the start pose"
    inv_depth = float(iz.sum()) / prob.n
    dof = 2 * prob.n - 6
    lam = 0.0  # Levenberg-Marquardt damping, 0 = pure Gauss-Newton
    converged = False
    iterations = 0
    H = None
    wt = None
    for it in range(1, max_iterations + 1):
        iterations = it
        wt = _robust_weights(r2, robust if prob.n >= _MIN_ROBUST else "none", huber_px, reject_px)
        H, g = prob.normal_equations(iz, wt, e)
        cost0 = float(np.dot(wt, r2))
        # Gauss-Newton step (lam = 0) with an exact line search, else Levenberg-Marquardt:
        # damp until the cost drops.  The damping persists (shrinking) across iterations, so
        # a near-singular direction (small planar targets) cannot throw the pose around.
        best = None
        while best is None:
            step = _spd_solve(H + np.diag(lam * np.diag(H)) if lam > 0.0 else H, g)
            if step is None:
                return "singular system (degenerate point configuration)"
            slope = float(step @ g)  # cost(a) = cost0 - 2 a slope + O(a^2) along the step
            if not math.isfinite(slope):
                return "singular system (degenerate point configuration)"
            trial = _try_step(prob, R, t, step, 1.0, wt)
            if trial is not None and lam == 0.0:
                # Exact line search on the parabola through cost0, its slope and cost(1):
                # Gauss-Newton on a large-residual problem overshoots (or undershoots) along
                # a weak direction and would otherwise converge only linearly there.
                curv = trial[0] - cost0 + 2.0 * slope
                alpha = min(slope / curv, 8.0) if curv > 0.0 else 4.0
                if alpha >= 0.2 and abs(alpha - 1.0) > 0.15:
                    t2 = _try_step(prob, R, t, step, alpha, wt)
                    if t2 is not None and t2[0] < trial[0]:
                        trial = t2
            if trial is not None and trial[0] <= cost0 * (1.0 + 1e-12) + 1e-30:
                best = trial
            elif lam > 1e8:
                break
            else:
                lam = 1e-6 if lam == 0.0 else lam * 4.0
        if best is None:
            converged = True  # no descent possible: at a minimum to machine precision
            break
        damped = lam > 0.0
        lam = 0.0 if lam <= 1e-9 else lam / 3.0
        cost1, delta, (R1, t1, e1, e21, r21, iz1) = best
        d0, d1, d2, d3, d4, d5 = delta.tolist()
        R, t = R1, t1
        e, r2, iz = e1, r21, iz1
        small = (
            math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            + math.sqrt(d3 * d3 + d4 * d4 + d5 * d5) * inv_depth
        )
        # Converged when the step is tiny, or (with redundancy) when it moves the pose by
        # less than ~1e-3 of its own standard deviation (delta^T H delta vs sigma^2): large-
        # residual problems with a weak direction converge only linearly there.
        if (
            small < tol
            or cost0 - cost1 <= 1e-14 * cost0
            or (dof > 0 and not damped and slope < 1e-6 * cost0 / dof)
        ):
            converged = True
            break
    if not math.isfinite(float(np.sum(R) + np.sum(t))):
        return "diverged (non-finite pose)"
    wt = _robust_weights(r2, robust if prob.n >= _MIN_ROBUST else "none", huber_px, reject_px)
    if not converged:
        # one more linearisation at the final pose so the covariance belongs to it
        H, g = prob.normal_equations(iz, wt, e)
        d = _spd_solve(H, g)
        if d is None:
            return "singular system (degenerate point configuration)"
        if not np.linalg.norm(d[:3]) + np.linalg.norm(d[3:]) * inv_depth <= 1e-6:
            return f"did not converge in {max_iterations} iterations"
    return {"R": R, "t": t, "r2": r2, "wt": wt, "H": H, "iterations": iterations}


def _validate(points_3d, points_2d):
    """Contiguous float64 (N,3)/(N,2) arrays, or a reason string."""
    try:
        X = np.ascontiguousarray(np.asarray(points_3d, dtype=np.float64).reshape(-1, 3))
        u = np.ascontiguousarray(np.asarray(points_2d, dtype=np.float64).reshape(-1, 2))
    except (ValueError, TypeError):
        return "points must be numeric arrays of shape (N,3) and (N,2)"
    if len(X) != len(u):
        return f"point counts differ: {len(X)} 3D vs {len(u)} 2D"
    if len(X) < 3:
        return f"need at least 3 correspondences, got {len(X)}"
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(u))):
        return "non-finite (NaN/inf) point coordinates"
    c = X - X.mean(axis=0)
    ev = np.linalg.eigvalsh(c.T @ c)  # squared singular values, ascending
    if ev[2] <= 1e-24 or ev[1] <= 1e-18 * ev[2]:
        return "degenerate 3D points: all collinear or coincident"
    return X, u, bool(ev[0] <= 1e-6 * ev[2])  # planar: thickness below 0.1% of the extent


def _normalise(camera: Camera, u: np.ndarray):
    """Undistorted normalised coordinates; a direct K^-1 when the lens has no distortion."""
    K = camera.K
    if not np.any(camera.dist) and K[1, 0] == 0.0:
        y = (u[:, 1] - K[1, 2]) / K[1, 1]
        x = (u[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.column_stack((x, y))
    try:
        return camera.undistort_points(u)
    except cv2.error:
        return None


def _finish(
    prob: _Problem,
    res: dict,
    n_all: int,
    inliers: np.ndarray,
    method: str,
    pixel_sigma: float | None,
    default_sigma: float,
) -> PoseEstimate:
    """Checks at the solution, RMSE and covariance (J^T W J)^-1 sigma^2."""
    R, t = res["R"], res["t"]
    pose = Pose(R, t)
    Xc_z = (R[2] @ prob.XT) + t[2]
    if np.any(Xc_z <= _MIN_DEPTH):
        return _fail("points behind the camera at the solution", n_all, method, res["iterations"])
    wt, r2 = res["wt"], res["r2"]
    used = wt > 0
    n_used = int(used.sum())
    if n_used < 3:
        return _fail("fewer than 3 inliers", n_all, method, res["iterations"])
    rmse = float(np.sqrt(np.mean(r2[used])))
    dof = 2 * n_used - 6
    if pixel_sigma is not None:
        s2 = pixel_sigma**2
    elif dof > 0:
        s2 = float(np.sum(wt * r2)) / dof
    else:
        s2 = default_sigma**2
    H = res["H"]
    try:
        ev, V = np.linalg.eigh(H)
        if not np.all(np.isfinite(ev)) or ev[0] <= 1e-14 * ev[-1]:
            return _fail(
                "singular system (degenerate point configuration)", n_all, method, res["iterations"]
            )
        cov = (V * (s2 / ev)) @ V.T
    except np.linalg.LinAlgError:
        return _fail("singular system at the solution", n_all, method, res["iterations"])
    if not np.all(np.isfinite(cov)):
        return _fail("singular system at the solution", n_all, method, res["iterations"])
    cov = 0.5 * (cov + cov.T)
    return PoseEstimate(
        pose, True, "", res["iterations"], rmse, inliers, cov, method, float(np.sqrt(s2))
    )


def _cv_solve(method: str, X, u, camera: Camera, reference_pose: Pose | None):
    """One OpenCV solver run; returns a Pose or a reason string.  Never raises."""
    n = len(X)
    K, dist = camera.K, camera.dist
    try:
        if method == "ap3p":
            # OpenCV's AP3P takes exactly 3 (or 4) points: solve on the first 3 and keep the
            # root that best explains all points (nearest the reference when n == 3).
            cnt, rvecs, tvecs = cv2.solveP3P(X[:3], u[:3], K, dist, cv2.SOLVEPNP_AP3P)
            if not cnt:
                return "ap3p found no solution"
            cands = [Pose.from_rvec_tvec(r, tv) for r, tv in zip(rvecs, tvecs, strict=False)]
            if n == 3:
                if reference_pose is None:
                    return "ap3p with 3 points is ambiguous without a reference pose"
                return min(
                    cands,
                    key=lambda p: p.angle_to(reference_pose) * 0.01 + p.distance_to(reference_pose),
                )
            errs = [np.sum((camera.project(X, p) - u) ** 2) for p in cands]
            return cands[int(np.argmin(errs))]
        flag = _CV_FLAGS[method]
        if method == "epnp" and n < 4:
            return "epnp needs at least 4 points"
        if method == "iterative":
            if reference_pose is not None and n >= 4:
                ok, rv, tv = cv2.solvePnP(
                    X,
                    u,
                    K,
                    dist,
                    reference_pose.rvec.copy(),
                    reference_pose.t.copy(),
                    True,
                    flag,
                )
            elif n >= 6:
                ok, rv, tv = cv2.solvePnP(X, u, K, dist, flags=flag)
            else:
                return "iterative needs at least 6 points (4 with a reference pose)"
        else:
            ok, rv, tv = cv2.solvePnP(X, u, K, dist, flags=flag)
    except cv2.error as e:
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else "OpenCV error"
        return f"{method} failed: {msg[:120]}"
    if not ok or rv is None or not np.all(np.isfinite(rv)) or not np.all(np.isfinite(tv)):
        return f"{method} found no solution"
    return Pose.from_rvec_tvec(rv.ravel(), tv.ravel())


def _ransac(X, u, camera: Camera, threshold_px: float, seed: int, iterations: int, confidence):
    """Minimal-solver RANSAC (OpenCV AP3P), seeded; returns (pose, inlier mask) or a reason."""
    try:
        cv2.setRNGSeed(int(seed))
        ok, rv, tv, idx = cv2.solvePnPRansac(
            X,
            u,
            camera.K,
            camera.dist,
            iterationsCount=int(iterations),
            reprojectionError=float(threshold_px),
            confidence=float(confidence),
            flags=cv2.SOLVEPNP_AP3P,
        )
    except cv2.error as e:
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else "OpenCV error"
        return f"ransac failed: {msg[:120]}"
    if not ok or idx is None or len(idx) < 3:
        return "ransac found no consensus"
    mask = np.zeros(len(X), dtype=bool)
    mask[np.asarray(idx).ravel()] = True
    pose = None
    if rv is not None and np.all(np.isfinite(rv)) and np.all(np.isfinite(tv)):
        pose = Pose.from_rvec_tvec(np.ravel(rv), np.ravel(tv))
    return pose, mask


def cramer_rao_covariance(points_3d, pose: Pose, camera: Camera, sigma_px: float) -> np.ndarray:
    """6x6 Cramer-Rao bound (J^T J)^-1 sigma^2 at `pose`, in the same parametrisation as
    `PoseEstimate.covariance` (left perturbation: rotation vector rad, translation m):
    the best any unbiased estimator can do with these points and isotropic pixel noise."""
    X = np.ascontiguousarray(np.asarray(points_3d, dtype=np.float64).reshape(-1, 3))
    Xc = pose.transform(X)
    x, y, iz = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2], 1.0 / Xc[:, 2]
    z0 = np.zeros_like(x)
    J = np.vstack(
        [
            camera.fx * np.column_stack([-x * y, 1 + x * x, -y, iz, z0, -x * iz]),
            camera.fy * np.column_stack([-(1 + y * y), x * y, x, z0, iz, -y * iz]),
        ]
    )
    return np.linalg.inv(J.T @ J) * sigma_px**2


def solve_pose(
    points_3d,
    points_2d,
    camera: Camera,
    reference_pose: Pose | None = None,
    method: str = "mirage-s",
    ransac: bool = False,
    ransac_threshold_px: float = 4.0,
    seed: int = 0,
    robust: str = "huber",
    max_iterations: int = 100,
    huber_px: float = 3.0,
    pixel_sigma: float | None = None,
    default_pixel_sigma: float = 1.0,
    ransac_iterations: int = 500,
    ransac_confidence: float = 0.999,
    tol: float = 1e-6,
    max_rmse_px: float | None = None,
) -> PoseEstimate:
    """Pose T_CW of a camera from n >= 3 world points and their pixels.

    method: "mirage-s" (default) refines from `reference_pose` (or, without one, from a
    guarded SQPnP/EPnP/AP3P start); "epnp", "sqpnp", "iterative", "ap3p" run OpenCV's
    solver (with `reference_pose` as the guess where it takes one) and report the same
    statistics, so methods can be compared in one pipeline.
    ransac: seeded AP3P RANSAC first (threshold `ransac_threshold_px`); the fit then runs on
    its inliers and inliers are re-classified by final reprojection error.
    robust: "huber" (IRLS with Huber weights, floor `huber_px`, plus rejection of gross
    outliers beyond max(ransac_threshold_px, 5 robust sigmas)) or "none".
    pixel_sigma: known pixel noise for the covariance; None estimates it from the residuals
    (sum w r^2 / (2n - 6)), falling back to `default_pixel_sigma` when n = 3 (no redundancy).
    max_rmse_px: optional gate; a solution whose inlier reprojection RMSE (per-point 2D
    error, px) exceeds it is reported as a failure instead of a doubtful pose.
    Never raises for bad numeric input: failures come back with success=False and a reason.
    """
    args = {k: v for k, v in locals().items() if k != "max_rmse_px"}
    try:
        est = _solve(**args)
    except (np.linalg.LinAlgError, cv2.error, FloatingPointError) as e:  # belt and braces
        return _fail(f"numerical failure: {type(e).__name__}", _count(points_3d), str(method))
    if est.success and max_rmse_px is not None and not est.rmse_px <= max_rmse_px:
        return _fail(
            f"reprojection RMSE {est.rmse_px:.2f} px above max_rmse_px {max_rmse_px:g}",
            len(est.inliers),
            est.method,
            est.iterations,
        )
    return est


def _count(points) -> int:
    try:
        return int(np.size(points) // 3) if np.ndim(points) else 0
    except (ValueError, TypeError):
        return 0


def _solve(
    points_3d,
    points_2d,
    camera: Camera,
    reference_pose: Pose | None,
    method: str,
    ransac: bool,
    ransac_threshold_px: float,
    seed: int,
    robust: str,
    max_iterations: int,
    huber_px: float,
    pixel_sigma: float | None,
    default_pixel_sigma: float,
    ransac_iterations: int,
    ransac_confidence: float,
    tol: float,
) -> PoseEstimate:
    """The body of `solve_pose` (see there for the arguments and their defaults)."""
    method = str(method).lower()
    if method not in METHODS:
        return _fail(f"unknown method '{method}' (choose from {', '.join(METHODS)})", 0, method)
    if robust not in ("huber", "none"):
        return _fail(f"unknown robust loss '{robust}' (huber or none)", 0, method)
    v = _validate(points_3d, points_2d)
    if isinstance(v, str):
        return _fail(v, _count(points_3d), method)
    X, u, planar = v
    n = len(X)
    if reference_pose is not None and not (
        np.all(np.isfinite(reference_pose.R)) and np.all(np.isfinite(reference_pose.t))
    ):
        return _fail("reference pose is not finite", n, method)
    xy = _normalise(camera, u)
    if xy is None or not np.all(np.isfinite(xy)):
        return _fail("image points could not be undistorted", n, method)
    prob = _Problem(X, xy, camera.fx, camera.fy)
    reject_px = ransac_threshold_px

    # --- outlier removal before the fit --------------------------------------------------
    mask = np.ones(n, dtype=bool)
    ransac_pose = None
    if ransac and n > 4:
        rr = _ransac(X, u, camera, ransac_threshold_px, seed, ransac_iterations, ransac_confidence)
        if isinstance(rr, str):
            return _fail(rr, n, method)
        ransac_pose, mask = rr

    def sub(m):
        return _Problem(X[m], xy[m], camera.fx, camera.fy) if not m.all() else prob

    # --- start pose ----------------------------------------------------------------------
    if method != "mirage-s":
        Xi, ui = X[mask], u[mask]
        p0 = _cv_solve(method, Xi, ui, camera, reference_pose)
        if isinstance(p0, str):
            return _fail(p0, n, method)
        return _score_fixed(
            prob, p0, mask, method, ransac_threshold_px, pixel_sigma, default_pixel_sigma, ransac
        )

    starts = []
    if reference_pose is not None:
        starts.append(reference_pose)
    if ransac_pose is not None:
        starts.append(ransac_pose)
    if reference_pose is None:
        Xi, ui = X[mask], u[mask]
        for m in ("sqpnp", "epnp", "ap3p"):
            p0 = _cv_solve(m, Xi, ui, camera, None)
            if isinstance(p0, Pose):
                starts.append(p0)
                break
        if not starts:
            return _fail(
                "no reference pose and no initial solution from SQPnP/EPnP/AP3P", n, method
            )

    reason = "no start pose"
    best = None
    for start in starts:
        res = _refine(sub(mask), start, max_iterations, robust, huber_px, reject_px, tol)
        if isinstance(res, str):
            reason = res
            continue
        if ransac:
            # re-classify every point by its reprojection at the refined pose; refit if changed
            r2all = prob.point_r2(res["R"], res["t"])
            m2 = r2all <= ransac_threshold_px**2
            if m2.sum() >= 3 and not np.array_equal(m2, mask):
                p1 = Pose(res["R"], res["t"])
                res2 = _refine(sub(m2), p1, max_iterations, robust, huber_px, reject_px, tol)
                if not isinstance(res2, str):
                    res2["iterations"] += res["iterations"]
                    res, mask = res2, m2
        est = _from_refine(prob, sub(mask), res, mask, n, pixel_sigma, default_pixel_sigma)
        if not est.success:
            reason = est.reason
            continue
        if best is None or est.rmse_px < best.rmse_px:
            best = est
        if reference_pose is not None and best is est:
            break  # the reference start succeeded: its basin is the one we want
    if best is None:
        return _fail(reason, n, method)
    if planar and reference_pose is not None and best.rmse_px > 0.0:
        best = _other_minimum(
            best,
            planar,
            X,
            u,
            xy,
            mask,
            camera,
            robust,
            huber_px,
            reject_px,
            max_iterations,
            tol,
            pixel_sigma,
            default_pixel_sigma,
        )
    return best


def _other_minimum(
    best,
    planar,
    X,
    u,
    xy,
    mask,
    camera,
    robust,
    huber_px,
    reject_px,
    max_iterations,
    tol,
    pixel_sigma,
    default_sigma,
) -> PoseEstimate:
    """Few points or a planar target leave a second nearby minimum (P3P roots, the planar
    flip) and the reference can sit in its basin.  Refine from the global solutions too (IPPE's
    two planar poses, or SQPnP) and switch only if that minimum is significantly better, so
    that with comparable costs the reference still decides."""
    m = best.inliers if best.inliers.sum() >= 4 else mask
    if m.sum() < 4:
        return best
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            np.ascontiguousarray(X[m]),
            np.ascontiguousarray(u[m]),
            camera.K,
            camera.dist,
            flags=cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_SQPNP,
        )
    except cv2.error:
        return best
    prob = _Problem(X[m], xy[m], camera.fx, camera.fy)
    for rv, tv in zip(rvecs, tvecs, strict=False):
        if not (np.all(np.isfinite(rv)) and np.all(np.isfinite(tv))):
            continue
        start = Pose.from_rvec_tvec(np.ravel(rv), np.ravel(tv))
        if start.angle_to(best.pose) < 0.5:
            continue
        res = _refine(prob, start, max_iterations, robust, huber_px, reject_px, tol)
        if isinstance(res, str):
            continue
        alt = _from_refine(None, prob, res, m, len(X), pixel_sigma, default_sigma)
        if not alt.success or alt.pose.angle_to(best.pose) <= 0.5:
            continue
        # switch only if the other minimum is significantly better: the cost drop exceeds
        # 9 sigma^2 (sigma^2 from the alternative's residuals; noise-free: any drop)
        k = int(m.sum())
        c_alt, c_best = alt.rmse_px**2 * k, best.rmse_px**2 * int(best.inliers.sum())
        s2 = max(c_alt, c_best) / max(2 * k - 6, 1)
        if c_best - c_alt > 9.0 * c_alt / max(2 * k - 6, 1):
            best, alt = alt, best
            c_best, c_alt = c_alt, c_best
        best = _two_minima_covariance(best, alt, c_alt - c_best, s2)
    return best


def _two_minima_covariance(best: PoseEstimate, alt: PoseEstimate, dcost: float, s2: float):
    """Widen the covariance by the other minimum in proportion to its likelihood.

    When the second minimum (the planar flip) explains the pixels almost as well, the
    solution's error is not Gaussian around the chosen pose: with probability
    p = L_alt / (L_best + L_alt) the truth sits near the other one. The moments of that
    two-mode distribution, (1-p) C_best + p C_alt + p (1-p) d d^T, keep sigma honest.
    """
    if s2 <= 0.0 or not np.isfinite(dcost):
        return best
    r = math.exp(-min(max(dcost, 0.0) / (2.0 * s2), 700.0))
    p = r / (1.0 + r)
    if p < 1e-6:
        return best
    w = rotvec(alt.pose.R @ best.pose.R.T)  # left perturbation taking best to alt
    d = np.concatenate([w, alt.pose.t - rodrigues(w) @ best.pose.t])
    cov = (1.0 - p) * best.covariance + p * alt.covariance + p * (1.0 - p) * np.outer(d, d)
    best.covariance = 0.5 * (cov + cov.T)
    return best


def _from_refine(prob_all, prob_used, res, mask, n, pixel_sigma, default_sigma) -> PoseEstimate:
    inl = mask.copy()
    idx = np.flatnonzero(mask)
    inl[idx[res["wt"] <= 0]] = False  # points the robust loss rejected
    return _finish(prob_used, res, n, inl, "mirage-s", pixel_sigma, default_sigma)


def _score_fixed(prob, pose, mask, method, thr, pixel_sigma, default_sigma, ransac):
    """Statistics of a pose found by another solver: residuals, inliers and covariance."""
    if ransac:  # outliers may lie anywhere, even behind the camera: score the inliers only
        inl = (prob.point_r2(pose.R, pose.t) <= thr**2) & mask
        if inl.sum() < 3:
            return _fail(f"{method}: fewer than 3 inliers at its solution", prob.n, method)
        if not inl.all():
            idx = np.flatnonzero(inl)
            sub = _Problem(prob.X[idx], prob.obs.reshape(2, -1).T[idx], prob.fx, prob.fy)
            est = _score_fixed(
                sub, pose, np.ones(len(idx), bool), method, thr, pixel_sigma, default_sigma, False
            )
            if est.success:
                est.inliers = inl
            return est
    e, e2, r2, iz, zmin = prob.residuals(pose.R, pose.t)
    if e is None:
        return _fail(f"{method}: points behind the camera at its solution", prob.n, method)
    if not np.all(np.isfinite(r2)):
        return _fail(f"{method} gave a non-finite pose", prob.n, method)
    inl = (r2 <= thr**2) & mask if ransac else mask.copy()
    wt = inl.astype(float)
    H, _ = prob.normal_equations(iz, wt, e)
    res = {"R": pose.R, "t": pose.t, "r2": r2, "wt": wt, "H": H, "iterations": 1}
    return _finish(prob, res, prob.n, inl, method, pixel_sigma, default_sigma)
