"""Mirage-S: camera pose from 3D-2D correspondences, refined from a reference pose (brief 4.1).

Mirage-S starts at a reference pose (a keyframe's pose, the previous frame's pose) and
explains the pixel differences between observed and predicted points by a small pose-error
transform E, actual = exp(E) * current.  Each point gives two linear equations in the six
parameters of E (rotation vector w, translation v, both in the camera frame); the 2n x 6
system is solved by weighted least squares, E is composed on the left and the projection is
re-linearised until the update is tiny.  The reference decides the ambiguities (P3P's up to
four roots, the planar two-fold flip) that make global solvers fail with few points; where a
second minimum can lie near the first (planar targets, 4-5 points) the global solutions are
refined too and every minimum is weighed against the reference (`_resolve_ambiguity`).  The
same normal equations give the pose covariance for free.

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

from . import refine as kernels  # the numba kernels of Mirage-S
from .camera import Camera
from .pose import Pose, rodrigues, rotvec

METHODS = ("mirage-s", "epnp", "sqpnp", "iterative", "ap3p")
_CV_FLAGS = {
    "epnp": cv2.SOLVEPNP_EPNP,
    "sqpnp": cv2.SOLVEPNP_SQPNP,
    "iterative": cv2.SOLVEPNP_ITERATIVE,
    "ap3p": cv2.SOLVEPNP_AP3P,
}
_MIN_ROBUST = 6  # below this many points (<= 4 redundant equations) robust weights only cost
_MINIMAL_SOLVERS = {"ap3p": cv2.SOLVEPNP_AP3P, "p3p": cv2.SOLVEPNP_P3P, "epnp": cv2.SOLVEPNP_EPNP}


@dataclass(frozen=True)
class RansacOptions:
    """Seeded minimal-solver RANSAC before the fit, for real matches that hold outliers.

    threshold_px: inlier reprojection error; the fit also re-classifies every point by it at
    the refined pose. seed makes the sampling repeatable. minimal_solver: ap3p | p3p | epnp.
    """

    threshold_px: float = 4.0
    iterations: int = 500
    confidence: float = 0.999
    seed: int = 0
    minimal_solver: str = "ap3p"


@dataclass(frozen=True)
class RefineOptions:
    """The Mirage-S iterations, the covariance's noise and the final gate.

    robust: "huber" (IRLS with Huber weights, floor `huber_px`, plus rejection of gross
    outliers beyond max(reject_px, 5 robust sigmas)) or "none". reject_px None: the RANSAC
    threshold (RansacOptions' default without RANSAC). reference_sigma_deg: how far (1 sigma,
    rotation) the reference may be from the truth; it weighs the two minima of a planar
    target (see `_resolve_ambiguity`). pixel_sigma: known pixel noise for the covariance;
    None estimates it from the residuals (sum w r^2 / (2n - 6)), falling back to
    `default_pixel_sigma` when n = 3 (no redundancy). max_rmse_px: optional gate; a solution
    whose inlier reprojection RMSE (px) exceeds it is a failure instead of a doubtful pose.
    """

    max_iterations: int = 100
    robust: str = "huber"
    huber_px: float = 3.0
    reject_px: float | None = None
    tol: float = 1e-6
    reference_sigma_deg: float = 10.0
    pixel_sigma: float | None = None
    default_pixel_sigma: float = 1.0
    max_rmse_px: float | None = None


def sigmas(cov: np.ndarray) -> tuple[float, float]:
    """RMS position (m) and rotation (deg) error a (w, v) or (theta, c) covariance predicts:
    sqrt(trace) of each 3x3 block (rotation-invariant, so either frame gives the same)."""
    pos = float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0)))
    return pos, float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))))


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
        return sigmas(self.covariance)[0]

    @property
    def sigma_rot_deg(self) -> float:
        return sigmas(self.covariance)[1]


def _fail(reason: str, n: int, method: str, iterations: int = 0) -> PoseEstimate:
    return PoseEstimate(
        None, False, reason, iterations, float("nan"), np.zeros(n, dtype=bool), method=method
    )


class _Problem:
    """Correspondences: world points (n, 3) and undistorted normalised image points (n, 2),
    contiguous for the compiled kernels in `refine`; residuals are weighted by fx^2 / fy^2
    so costs, RMSE and covariance come out in pixels."""

    def __init__(self, X: np.ndarray, xy: np.ndarray, fx: float, fy: float):
        self.n = len(X)
        self.X = np.ascontiguousarray(X, dtype=np.float64)
        self.xy = np.ascontiguousarray(xy, dtype=np.float64)
        self.fx, self.fy = float(fx), float(fy)

    def residuals(self, R: np.ndarray, t: np.ndarray):
        """(e, r2, pred, iz, zmin): normalised residuals (n, 2), per-point |r|^2 in px^2, the
        predicted points and inverse depths; only meaningful when zmin > MIN_DEPTH."""
        n = self.n
        e, r2, pred, iz = np.empty((n, 2)), np.empty(n), np.empty((n, 2)), np.empty(n)
        R, t = np.ascontiguousarray(R, dtype=np.float64), np.ascontiguousarray(t, dtype=np.float64)
        zmin = kernels.residuals(self.X, self.xy, self.fx, self.fy, R, t, e, r2, pred, iz)
        return e, r2, pred, iz, zmin

    def point_r2(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Per-point squared pixel error; inf for points behind the camera (outliers may be)."""
        Xc = self.X @ R.T + t
        front = Xc[:, 2] > kernels.MIN_DEPTH
        p = Xc[:, :2] / np.where(front, Xc[:, 2], 1.0)[:, None]
        e = self.xy - p
        r2 = (e[:, 0] * self.fx) ** 2 + (e[:, 1] * self.fy) ** 2
        r2[~front] = np.inf
        return r2

    def normal_equations(self, pred, iz, wt, e):
        """H = J^T W J and g = J^T W e (pixel units) at the predicted points `pred`."""
        H, g = np.empty((6, 6)), np.empty(6)
        kernels.normal_equations(
            self.fx, self.fy, pred, iz, np.ascontiguousarray(wt, float), e, H, g
        )
        return H, g


_REFINE_FAILURES = {
    kernels.BEHIND_AT_START: "points behind the camera at the start pose",
    kernels.SINGULAR: "singular system (degenerate point configuration)",
    kernels.DIVERGED: "diverged (non-finite pose)",
}


def _refine(prob: _Problem, pose: Pose, opts: RefineOptions, reject_px: float):
    """Gauss-Newton / IRLS on the left perturbation (compiled, see `refine`).  Returns a dict
    or a failure reason."""
    status, R, t, r2, wt, H, iterations = kernels.refine(
        prob.X,
        prob.xy,
        prob.fx,
        prob.fy,
        np.ascontiguousarray(pose.R, dtype=np.float64),
        np.ascontiguousarray(pose.t, dtype=np.float64),
        int(opts.max_iterations),
        opts.robust == "huber" and prob.n >= _MIN_ROBUST,
        float(opts.huber_px),
        float(reject_px),
        float(opts.tol),
    )
    if status == kernels.NOT_CONVERGED:
        return f"did not converge in {opts.max_iterations} iterations"
    if status != kernels.OK:
        return _REFINE_FAILURES[status]
    return {"R": R, "t": t, "r2": r2, "wt": wt, "H": H, "iterations": int(iterations)}


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
    try:
        finite, ev = kernels.inspect_points(X, u)  # scatter eigenvalues, ascending
    except np.linalg.LinAlgError:  # overflow to inf in the scatter matrix
        finite, ev = False, None
    if not finite:
        return "non-finite (NaN/inf) point coordinates"
    if ev[2] <= 1e-24 or ev[1] <= 1e-12 * ev[2]:  # second axis below 1e-6 of the first
        return "degenerate 3D points: all collinear or coincident"
    return X, u, bool(ev[0] <= 1e-6 * ev[2])  # planar: thickness below 0.1% of the extent


def _normalise(camera: Camera, u: np.ndarray):
    """Undistorted normalised coordinates; a direct K^-1 when the lens has no distortion."""
    K = camera.K
    if not camera.dist.any() and K[1, 0] == 0.0:
        return kernels.normalise_pinhole(u, K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1])
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
    it = res["iterations"]
    zmin, n_used, sum_r2, cost = kernels.solution_stats(prob.X, R, t, res["wt"], res["r2"])
    if not zmin > kernels.MIN_DEPTH:
        return _fail("points behind the camera at the solution", n_all, method, it)
    if n_used < 3:
        return _fail("fewer than 3 inliers", n_all, method, it)
    rmse = math.sqrt(sum_r2 / n_used)
    dof = 2 * n_used - 6
    if pixel_sigma is not None:
        s2 = pixel_sigma**2
    elif dof > 0:
        s2 = cost / dof
    else:
        s2 = default_sigma**2
    try:
        ok, cov = kernels.covariance(res["H"], s2)
    except np.linalg.LinAlgError:  # non-finite normal equations
        ok, cov = False, None
    if not ok:
        return _fail("singular system (degenerate point configuration)", n_all, method, it)
    return PoseEstimate(Pose(R, t), True, "", it, rmse, inliers, cov, method, math.sqrt(s2))


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


def _ransac(X, u, camera: Camera, opts: RansacOptions):
    """Minimal-solver RANSAC (OpenCV, AP3P by default), seeded; returns (pose, inlier mask)
    or a reason."""
    try:
        cv2.setRNGSeed(int(opts.seed))
        ok, rv, tv, idx = cv2.solvePnPRansac(
            X,
            u,
            camera.K,
            camera.dist,
            iterationsCount=int(opts.iterations),
            reprojectionError=float(opts.threshold_px),
            confidence=float(opts.confidence),
            flags=_MINIMAL_SOLVERS[opts.minimal_solver],
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


def _pixel_terms(X: np.ndarray, xy: np.ndarray, pose: Pose, camera: Camera, huber_px=None):
    """Per point the (n,2,6) Jacobian of the pixel projection (left perturbation) and the
    pixel residual of the normalised observations `xy`, the Huber weights (1 without
    `huber_px`) and H = sum w J^T J (compiled, `refine.sandwich_terms`); None when a
    point is at or behind the camera."""
    n = len(X)
    J, r, w, H = np.empty((n, 2, 6)), np.empty((n, 2)), np.empty(n), np.empty((6, 6))
    huber = float(huber_px) if huber_px is not None else 0.0
    R, t = np.ascontiguousarray(pose.R, float), np.asarray(pose.t, float)
    if not kernels.sandwich_terms(X, np.ascontiguousarray(xy, float), camera.fx, camera.fy, R, t,
                             huber, huber_px is not None, J, r, w, H):  # fmt: skip
        return None
    return J, r, w, H


def cramer_rao_covariance(points_3d, pose: Pose, camera: Camera, sigma_px: float) -> np.ndarray:
    """6x6 Cramer-Rao bound (J^T J)^-1 sigma^2 at `pose`, in the same parametrisation as
    `PoseEstimate.covariance` (left perturbation: rotation vector rad, translation m):
    the best any unbiased estimator can do with these points and isotropic pixel noise
    (NaNs when a point is at or behind the camera)."""
    X = np.ascontiguousarray(np.asarray(points_3d, dtype=np.float64).reshape(-1, 3))
    terms = _pixel_terms(X, np.zeros((len(X), 2)), pose, camera)
    if terms is None:
        return np.full((6, 6), np.nan)
    return np.linalg.inv(terms[3]) * sigma_px**2


def sandwich_covariance(
    points_3d, points_2d, pose: Pose, camera: Camera, huber_px: float | None = None
) -> np.ndarray:
    """6x6 pose covariance from the residuals themselves (same parametrisation as
    `PoseEstimate.covariance`): the leverage-corrected (HC3, close to the jackknife)
    sandwich H^-1 (sum J_i^T e_i e_i^T J_i) H^-1 with e_i = (I - J_i H^-1 J_i^T)^-1 r_i.

    (J^T J)^-1 s^2 assumes every point is as good as the average one. When a few points
    are off and carry the pose (an isolated point, a small cluster at the image edge),
    the fit bends towards them, their residuals shrink and s^2 looks fine; the leverage
    correction restores what each point's residual would be without it, so such a pose
    gets the large uncertainty it has. With `huber_px`, the Huber weights Mirage-S fitted
    with (`RefineOptions.huber_px`): (J^T W J)^-1 (sum w_i^2 J_i^T e_i e_i^T J_i) (J^T W
    J)^-1. NaNs when the points cannot fix a pose.
    """
    X = np.ascontiguousarray(np.asarray(points_3d, dtype=np.float64).reshape(-1, 3))
    nan = np.full((6, 6), np.nan)
    n = len(X)
    if n < 4:
        return nan
    terms = _pixel_terms(X, camera.undistort_points(points_2d), pose, camera, huber_px)
    if terms is None:
        return nan  # a point at or behind the camera
    J, r, w, H = terms
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return nan
    M = np.empty((6, 6))
    kernels.sandwich_meat(J, r, w, Hi, M)
    cov = Hi @ M @ Hi
    return 0.5 * (cov + cov.T)


def solve_pose(
    points_3d,
    points_2d,
    camera: Camera,
    reference_pose: Pose | None = None,
    method: str = "mirage-s",
    ransac: RansacOptions | None = None,
    refine: RefineOptions = RefineOptions(),  # noqa: B008 - frozen: one shared default
) -> PoseEstimate:
    """Pose T_CW of a camera from n >= 3 world points and their pixels.

    method: "mirage-s" (default) refines from `reference_pose` (or, without one, from a
    guarded SQPnP/EPnP/AP3P start); "epnp", "sqpnp", "iterative", "ap3p" run OpenCV's
    solver (with `reference_pose` as the guess where it takes one) and report the same
    statistics, so methods can be compared in one pipeline.
    ransac: seeded RANSAC first (`RansacOptions`); the fit then runs on its inliers and
    inliers are re-classified by final reprojection error. None: every point is fitted.
    refine: the iterations, robust loss, covariance noise and RMSE gate (`RefineOptions`).
    Never raises for bad numeric input: failures come back with success=False and a reason.
    """
    try:
        est = _solve(points_3d, points_2d, camera, reference_pose, method, ransac, refine)
    except (np.linalg.LinAlgError, cv2.error, FloatingPointError) as e:  # belt and braces
        return _fail(f"numerical failure: {type(e).__name__}", _count(points_3d), str(method))
    gate = refine.max_rmse_px
    if est.success and gate is not None and not est.rmse_px <= gate:
        return _fail(
            f"reprojection RMSE {est.rmse_px:.2f} px above max_rmse_px {gate:g}",
            len(est.inliers),
            est.method,
            est.iterations,
        )
    return est


LEVERAGE_ROUNDS = 2  # dropping a point can leave its partner (a pair far off) alone


def leverages(points_3d, points_2d, pose: Pose, camera: Camera, huber_px=None) -> np.ndarray:
    """Per point, its leverage: the largest eigenvalue of its 2x2 block of the hat matrix
    w J_i (J^T W J)^-1 J_i^T (0: one of many, 1: the fit follows it wherever it is). A
    point's residual is (1 - h) times its error: near 1, no residual can show the error,
    and the pose's covariance, from residuals or from J, claims a direction that rests on
    that one point (far orbit, tuning seed 35: one ground point 1.5 m from the landmark's
    others, 3.9 px off, leverage 0.99, bent the pose 146 mm off with a sigma of 23 mm
    where the frames before had 136). NaNs when the points cannot fix a pose."""
    X = np.ascontiguousarray(np.asarray(points_3d, dtype=np.float64).reshape(-1, 3))
    nan = np.full(len(X), np.nan)
    terms = _pixel_terms(X, camera.undistort_points(points_2d), pose, camera, huber_px)
    if terms is None or len(X) < 4:
        return nan
    J, _, w, H = terms
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return nan
    JH = J @ Hi  # the 2x2 blocks w J_i Hi J_i^T, entry by entry (3x faster than one einsum)
    a, b, d = (w * np.einsum("na,na->n", JH[:, i], J[:, j]) for i, j in ((0, 0), (0, 1), (1, 1)))
    return (a + d) / 2 + np.sqrt(((a - d) / 2) ** 2 + b * b)


def verifiable(
    est: PoseEstimate,
    points_3d,
    points_2d,
    camera: Camera,
    max_leverage: float,
    refine: RefineOptions = RefineOptions(),  # noqa: B008 - frozen: one shared default
) -> PoseEstimate:
    """`est` (a fit of these points) fitted again from its pose without its inliers of
    leverage above `max_leverage` (`leverages`), as often as `LEVERAGE_ROUNDS`; a failure
    when fewer than 6 points would remain (the rest cannot fix the pose). For the pose a
    caller keeps, not within RANSAC: a hypothesis with few inliers often has such a point
    and is checked by what follows."""
    if not est.success:
        return est
    X = np.asarray(points_3d, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(points_2d, dtype=np.float64).reshape(-1, 2)
    if len(est.inliers) != len(X):
        return est
    for _ in range(LEVERAGE_ROUNDS):
        idx = np.flatnonzero(est.inliers)
        h = leverages(X[idx], uv[idx], est.pose, camera, refine.huber_px)
        high = h > max_leverage
        if not high.any():  # (NaNs: a point at or behind the camera; nothing to judge by)
            return est
        keep = idx[~high]
        if len(keep) < 6:
            return _fail("the pose rests on single points", len(X), est.method, est.iterations)
        sub = solve_pose(X[keep], uv[keep], camera, est.pose, est.method, None, refine)
        if not sub.success:
            return sub
        sub.inliers = np.bincount(keep[sub.inliers], minlength=len(X)).astype(bool)
        est = sub
    return est


def _count(points) -> int:
    try:
        return int(np.size(points) // 3) if np.ndim(points) else 0
    except (ValueError, TypeError):
        return 0


def _option_error(method: str, ransac: RansacOptions | None, opts: RefineOptions) -> str | None:
    """Why these options cannot be solved with (None: they can)."""
    if method not in METHODS:
        return f"unknown method '{method}' (choose from {', '.join(METHODS)})"
    if opts.robust not in ("huber", "none"):
        return f"unknown robust loss '{opts.robust}' (huber or none)"
    if not opts.reference_sigma_deg > 0.0:
        return f"reference_sigma_deg must be > 0, got {opts.reference_sigma_deg}"
    if ransac is not None and ransac.minimal_solver not in _MINIMAL_SOLVERS:
        return (
            f"unknown minimal solver '{ransac.minimal_solver}' "
            f"(choose from {', '.join(_MINIMAL_SOLVERS)})"
        )
    return None


def _start_poses(Xi, ui, camera: Camera, reference_pose, ransac_pose) -> list[Pose]:
    """Where Mirage-S starts: the reference and RANSAC's pose; without a reference, the
    first of SQPnP, EPnP and AP3P that gives one (on the points RANSAC kept)."""
    starts = []
    if reference_pose is not None:
        starts.append(reference_pose)
    if ransac_pose is not None:
        starts.append(ransac_pose)
    if reference_pose is None:
        for m in ("sqpnp", "epnp", "ap3p"):
            p0 = _cv_solve(m, Xi, ui, camera, None)
            if isinstance(p0, Pose):
                starts.append(p0)
                break
    return starts


def _refine_starts(
    prob, sub, starts, mask, opts, reject_px, reclassify_px, stop_at_first,
    pixel_sigma, default_pixel_sigma,
):  # fmt: skip
    """Mirage-S from each start pose in turn: the best estimate (least RMSE), why the last
    start failed, and the points used. With `reclassify_px` (RANSAC ran) every point is
    re-classified by its reprojection at the refined pose and the fit redone if that
    changed; `stop_at_first`: the reference start succeeded, its basin is the one wanted."""
    n = len(mask)
    reason, best = "no start pose", None
    for start in starts:
        m = mask
        res = _refine(sub(m), start, opts, reject_px)
        if isinstance(res, str):
            reason = res
            continue
        if reclassify_px is not None:
            m2 = prob.point_r2(res["R"], res["t"]) <= reclassify_px**2
            if m2.sum() >= 3 and not np.array_equal(m2, m):
                res2 = _refine(sub(m2), Pose(res["R"], res["t"]), opts, reject_px)
                if not isinstance(res2, str):
                    res2["iterations"] += res["iterations"]
                    res, m = res2, m2
        mask = m  # as before: a re-classified mask carries over to the next start
        est = _from_refine(prob, sub(m), res, m, n, pixel_sigma, default_pixel_sigma)
        if not est.success:
            reason = est.reason
            continue
        if best is None or est.rmse_px < best.rmse_px:
            best = est
        if stop_at_first and best is est:
            break
    return best, reason, mask


def _solve(
    points_3d,
    points_2d,
    camera: Camera,
    reference_pose: Pose | None,
    method: str,
    ransac: RansacOptions | None,
    opts: RefineOptions,
) -> PoseEstimate:
    """The body of `solve_pose` (see there for the arguments)."""
    method = str(method).lower()
    wrong = _option_error(method, ransac, opts)
    if wrong is not None:
        return _fail(wrong, 0, method)
    v = _validate(points_3d, points_2d)
    if isinstance(v, str):
        return _fail(v, _count(points_3d), method)
    X, u, planar = v
    n = len(X)
    if camera.model != "pinhole":  # OpenCV's PnP solvers and the fast path: one lens model
        u, camera = camera.ideal_pixels(u), camera.standard()
    if reference_pose is not None and not (
        np.isfinite(reference_pose.R).all() and np.isfinite(reference_pose.t).all()
    ):
        return _fail("reference pose is not finite", n, method)
    xy = _normalise(camera, u)
    if xy is None or not np.isfinite(xy).all():
        return _fail("image points could not be undistorted", n, method)
    prob = _Problem(X, xy, camera.fx, camera.fy)
    thr = (ransac or RansacOptions()).threshold_px
    reject_px = opts.reject_px if opts.reject_px is not None else thr
    pixel_sigma, default_pixel_sigma = opts.pixel_sigma, opts.default_pixel_sigma

    # --- outlier removal before the fit --------------------------------------------------
    mask = np.ones(n, dtype=bool)
    ransac_pose = None
    if ransac is not None and n > 4:
        rr = _ransac(X, u, camera, ransac)
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
            prob, p0, mask, method, thr, pixel_sigma, default_pixel_sigma, ransac is not None
        )

    starts = _start_poses(X[mask], u[mask], camera, reference_pose, ransac_pose)
    if not starts:
        return _fail("no reference pose and no initial solution from SQPnP/EPnP/AP3P", n, method)

    best, reason, mask = _refine_starts(
        prob, sub, starts, mask, opts, reject_px, thr if ransac is not None else None,
        reference_pose is not None, pixel_sigma, default_pixel_sigma,
    )  # fmt: skip
    if reference_pose is not None and (planar or (n <= _FEW_POINTS and mask.sum() >= 4)):
        # the planar flip or a P3P-like second root: weigh the other minima too (even when
        # the reference start failed)
        best = _resolve_ambiguity(
            best, X, u, xy, mask, camera, reference_pose, opts, reject_px, planar
        )
    if best is None:
        return _fail(reason, n, method)
    return best


_SAME_MINIMUM_DEG = 0.1
_FEW_POINTS = 5  # up to here a non-planar scene can hold a second minimum near the first


def _global_starts(X, u, camera: Camera, planar: bool) -> list[Pose]:
    """Poses from OpenCV's global solvers, one in each basin that could hold the answer:
    IPPE's two planar solutions, or SQPnP plus every P3P root of the three points spanning
    the largest image triangle."""
    runs = [(X, u, cv2.SOLVEPNP_IPPE)] if planar else [(X, u, cv2.SOLVEPNP_SQPNP)]
    if not planar:
        tri = np.array([(i, j, k) for i in range(len(X)) for j in range(i) for k in range(j)])
        a, b = u[tri[:, 1]] - u[tri[:, 0]], u[tri[:, 2]] - u[tri[:, 0]]
        best = tri[np.argmax(np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))]
        runs.append((X[best], u[best], cv2.SOLVEPNP_AP3P))
    poses = []
    for Xs, us, flag in runs:
        try:
            _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                np.ascontiguousarray(Xs),
                np.ascontiguousarray(us),
                camera.K,
                camera.dist,
                flags=flag,
            )
        except cv2.error:
            continue
        for rv, tv in zip(rvecs, tvecs, strict=False):
            if np.isfinite(rv).all() and np.isfinite(tv).all():
                poses.append(Pose.from_rvec_tvec(np.ravel(rv), np.ravel(tv)))
    return poses


def _resolve_ambiguity(
    best,
    X,
    u,
    xy,
    mask,
    camera,
    reference,
    opts: RefineOptions,
    reject_px,
    planar,
) -> PoseEstimate | None:
    """A planar target has two minima (the flip), and near fronto-parallel both explain the
    pixels almost equally, so a pick by cost alone (or by the reference's basin alone) is
    wrong in a few percent of scenes, each time by tens of degrees; 4-5 points in space can
    likewise hold a second minimum, and a reference far enough off sits in its basin.

    Refine from the global solvers' poses as well (`_global_starts`), then weigh the
    distinct minima by their posterior mass (Laplace approximation: likelihood times
    sqrt(det C) of the minimum): likelihood exp(-cost / 2 sigma^2), with cost the
    plain squared pixel error over the same points (all of `mask`, also those a minimum's
    robust loss rejected, so a minimum cannot look cheap by rejecting points), times a
    Gaussian prior of width `opts.reference_sigma_deg` on the rotation from the reference.
    For the planar flip, return the minimum-mean-square-error pose, the most probable
    minimum moved toward the other by the other's probability p, with the mixture's
    covariance (1-p) C_a + p C_b + p (1-p) d d^T; with few points in space (where blending
    measured slightly worse) the most probable minimum.
    Unambiguous scenes have p ~ 0 and get the most probable minimum unchanged.
    """
    m = mask
    if m.sum() < 4:
        return best
    pixel_sigma, default_sigma = opts.pixel_sigma, opts.default_pixel_sigma
    prob = _Problem(X[m], xy[m], camera.fx, camera.fy)
    cands = [best] if best is not None else []
    for start in _global_starts(X[m], u[m], camera, planar):
        if any(start.angle_to(c.pose) < _SAME_MINIMUM_DEG for c in cands):
            continue
        res = _refine(prob, start, opts, reject_px)
        if isinstance(res, str):
            continue
        est = _from_refine(None, prob, res, m, len(X), pixel_sigma, default_sigma)
        if est.success and all(est.pose.angle_to(c.pose) >= _SAME_MINIMUM_DEG for c in cands):
            cands.append(est)
    if len(cands) < 2:
        return cands[0] if cands else None
    k = int(m.sum())
    cost = np.array([float(np.sum(prob.point_r2(c.pose.R, c.pose.t))) for c in cands])
    if pixel_sigma is not None:
        s2 = pixel_sigma**2
    else:
        s2 = max(float(cost.min()) / max(2 * k - 6, 1), 1e-30)
    theta = np.array([c.pose.angle_to(reference) for c in cands])  # deg
    # Laplace approximation of each minimum's posterior mass: peak height times the volume
    # of its basin, sqrt(det C) (a flatter minimum holds more probability)
    log_det = np.array([np.linalg.slogdet(c.covariance)[1] for c in cands])
    log_p = -cost / (2.0 * s2) - theta**2 / (2.0 * opts.reference_sigma_deg**2) + 0.5 * log_det
    order = np.argsort(-log_p)
    a, b = cands[order[0]], cands[order[1]]
    p = 1.0 / (1.0 + math.exp(min(log_p[order[0]] - log_p[order[1]], 700.0)))
    if not p > 1e-6:
        return a
    w = rotvec(b.pose.R @ a.pose.R.T)  # left perturbation taking a to b
    d = np.concatenate([w, b.pose.t - rodrigues(w) @ a.pose.t])
    if not planar:  # blending measured better only for the planar flip: keep the mode
        cov = (1.0 - p) * a.covariance + p * b.covariance + p * np.outer(d, d)
        a.covariance = 0.5 * (cov + cov.T)
        return a
    R = rodrigues(p * w) @ a.pose.R
    pose = Pose.from_center(R.T, (1.0 - p) * a.pose.center + p * b.pose.center)
    cov = (1.0 - p) * a.covariance + p * b.covariance + p * (1.0 - p) * np.outer(d, d)
    r2 = prob.point_r2(pose.R, pose.t)[a.inliers[m]]
    a.pose, a.covariance = pose, 0.5 * (cov + cov.T)
    a.rmse_px = float(np.sqrt(np.mean(r2)))
    return a


def _from_refine(prob_all, prob_used, res, mask, n, pixel_sigma, default_sigma) -> PoseEstimate:
    inl = mask.copy()
    inl[mask] = res["wt"] > 0  # drop the points the robust loss rejected
    return _finish(prob_used, res, n, inl, "mirage-s", pixel_sigma, default_sigma)


def _score_fixed(prob, pose, mask, method, thr, pixel_sigma, default_sigma, ransac):
    """Statistics of a pose found by another solver: residuals, inliers and covariance."""
    if ransac:  # outliers may lie anywhere, even behind the camera: score the inliers only
        inl = (prob.point_r2(pose.R, pose.t) <= thr**2) & mask
        if inl.sum() < 3:
            return _fail(f"{method}: fewer than 3 inliers at its solution", prob.n, method)
        if not inl.all():
            idx = np.flatnonzero(inl)
            sub = _Problem(prob.X[idx], prob.xy[idx], prob.fx, prob.fy)
            est = _score_fixed(
                sub, pose, np.ones(len(idx), bool), method, thr, pixel_sigma, default_sigma, False
            )
            if est.success:
                est.inliers = inl
            return est
    if not (np.isfinite(pose.R).all() and np.isfinite(pose.t).all()):
        return _fail(f"{method} gave a non-finite pose", prob.n, method)
    e, r2, pred, iz, zmin = prob.residuals(pose.R, pose.t)
    if zmin <= kernels.MIN_DEPTH:  # (residuals of such points are not computed)
        return _fail(f"{method}: points behind the camera at its solution", prob.n, method)
    inl = (r2 <= thr**2) & mask if ransac else mask.copy()
    wt = inl.astype(float)
    H, _ = prob.normal_equations(pred, iz, wt, e)
    R, t = np.ascontiguousarray(pose.R), np.ascontiguousarray(pose.t)  # one compiled layout
    res = {"R": R, "t": t, "r2": r2, "wt": wt, "H": H, "iterations": 1}
    return _finish(prob, res, prob.n, inl, method, pixel_sigma, default_sigma)


def warm_up() -> None:
    """Compile (or load from the cache) the kernels of the common Mirage-S path, so that a
    caller can do it up front instead of inside its first timed frame."""
    X = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0], [0, 0, 0.2], [0.2, 0.2, 0.1], [0.1, 0, 0.2]])
    cam = Camera.from_params(640, 480, 500.0)
    truth = Pose(np.eye(3), np.array([0.0, 0.0, 2.0]))
    uv = cam.project(X, truth)
    solve_pose(X, uv, cam, Pose(np.eye(3), np.array([0.01, 0.0, 2.0])))
    sandwich_covariance(X, uv, truth, cam, 0.5)
