"""The one place that talks to GTSAM: planar pose graphs of odometry plus loop constraints.

Conventions:

* Frame ``k`` is GTSAM key ``k`` (a plain integer). Poses are ``(N, 3)`` float64 arrays
  ``[x_m, y_m, yaw_rad]`` (``T_world_base`` of frames 0..N-1).
* Factor order in every graph built by :func:`build_graph`: factor 0 is the prior on frame 0
  (fixes the gauge at the first odometry pose), factors ``1..N-1`` are the odometry steps
  ``(k, k+1)``, factors ``N..N+C-1`` are the loop constraints in the order given. So
  ``odometry_factor_indices(N) = range(N)`` are the known inliers of a GNC solve, and
  ``loop_factor_index(N, c) = N + c``.
* A loop constraint ``(query, match)`` is ``BetweenFactorPose2(match, query, T_match_query)``.
  Candidates without a relative pose (place recognition says "same place") use the identity with
  the config's ``loop_default_information``.
* Chi-square values are GTSAM's: ``chi2 = r^T Ω r`` with ``r = Logmap(z⁻¹ · (x_i⁻¹ x_j))``,
  i.e. ``2 × factor.error``. The numpy functions here (:func:`between_chi2`, :func:`loop_chi2`,
  :func:`odometry_chi2`) reproduce GTSAM's value without building a graph, for scoring many
  hypotheses cheaply.

``gtsam`` is imported lazily inside the functions that need it, so importing this module is cheap.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, NamedTuple, Sequence

import numpy as np

from lcv_replay.errors import VerificationError
from lcv_replay.records import Pose2D

if TYPE_CHECKING:  # pragma: no cover
    import gtsam

    from lcv_replay.verification.base import Constraint

log = logging.getLogger(__name__)

#: Standard deviation of the prior that fixes frame 0 (gauge freedom), metres and radians.
PRIOR_SIGMA = 1e-6

KernelKind = Literal["dcs", "gm", "cauchy", "huber", "tukey", "welsch"]


class OptimisationFailed(VerificationError):
    """GTSAM could not solve a pose graph (e.g. an indeterminant linear system)."""


@dataclass(frozen=True)
class RobustKernel:
    """An M-estimator wrapped around every loop factor's Gaussian noise model.

    Attributes:
        kind: ``"dcs"`` (dynamic covariance scaling, scale = Φ), ``"gm"`` (Geman-McClure,
            scale = c), ``"cauchy"`` (scale = c), ``"huber"``, ``"tukey"``, ``"welsch"``
            (scale = k), all as in ``gtsam.noiseModel.mEstimator``.
        scale: the kernel parameter, in whitened units.
    """

    kind: KernelKind
    scale: float

    def __post_init__(self) -> None:
        if self.kind not in ("dcs", "gm", "cauchy", "huber", "tukey", "welsch"):
            raise VerificationError(
                f"unknown robust kernel '{self.kind}'",
                fix="use one of dcs, gm, cauchy, huber, tukey, welsch",
            )
        if not self.scale > 0:
            raise VerificationError(f"robust kernel scale {self.scale!r} must be > 0")

    def estimator(self):
        """The ``gtsam.noiseModel.mEstimator`` instance."""
        import gtsam

        m = gtsam.noiseModel.mEstimator
        make = {
            "dcs": m.DCS,
            "gm": m.GemanMcClure,
            "cauchy": m.Cauchy,
            "huber": m.Huber,
            "tukey": m.Tukey,
            "welsch": m.Welsch,
        }[self.kind]
        return make.Create(self.scale)


@dataclass(frozen=True)
class PoseGraphSolution:
    """A solved pose graph.

    Attributes:
        poses: ``(N, 3)`` ``[x_m, y_m, yaw_rad]`` of frames 0..N-1.
        error: GTSAM's graph error at the solution (``0.5 × Σ chi2``, robust loss if robust).
        iterations: optimiser iterations, ``None`` where GTSAM does not report them (GNC).
    """

    poses: np.ndarray
    error: float
    iterations: int | None

    @property
    def chi2(self) -> float:
        """Total whitened chi-square, ``2 × error``."""
        return 2.0 * self.error


# ----------------------------------------------------------------------------------------------
# SE(2) on arrays (vectorised, the same maths as gtsam.Pose2)
# ----------------------------------------------------------------------------------------------


def wrap_angles(angles_rad: np.ndarray) -> np.ndarray:
    """Wrap angles to ``[-pi, pi)`` (any shape)."""
    return (np.asarray(angles_rad) + np.pi) % (2.0 * np.pi) - np.pi


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ∘ b`` for ``(..., 3)`` pose arrays (broadcasting)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    out[..., 1] = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    out[..., 2] = wrap_angles(a[..., 2] + b[..., 2])
    return out


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ ∘ b`` for ``(..., 3)`` pose arrays: with ``a = T_w_i``, ``b = T_w_j`` this is ``T_i_j``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    out[..., 2] = wrap_angles(b[..., 2] - a[..., 2])
    return out


def se2_logmap(pose: np.ndarray) -> np.ndarray:
    """``Pose2.Logmap`` of ``(..., 3)`` poses: tangent vectors ``(..., 3)`` ``[v_x, v_y, ω]``."""
    pose = np.asarray(pose, dtype=np.float64)
    w = wrap_angles(pose[..., 2])
    half = 0.5 * w
    small = np.abs(w) < 1e-6
    safe_half = np.where(small, 1.0, half)
    k = np.where(small, 1.0 - w * w / 12.0, safe_half * np.cos(safe_half) / np.sin(safe_half))
    x, y = pose[..., 0], pose[..., 1]
    out = np.empty(pose.shape, dtype=np.float64)
    out[..., 0] = k * x + half * y
    out[..., 1] = -half * x + k * y
    out[..., 2] = w
    return out


def se2_expmap(xi: np.ndarray) -> np.ndarray:
    """``Pose2.Expmap`` of ``(..., 3)`` tangent vectors ``[v_x, v_y, ω]`` -> poses ``(..., 3)``."""
    xi = np.asarray(xi, dtype=np.float64)
    w = xi[..., 2]
    small = np.abs(w) < 1e-6
    safe_w = np.where(small, 1.0, w)
    a = np.where(small, 1.0 - w * w / 6.0, np.sin(safe_w) / safe_w)  # sin(w)/w
    b = np.where(small, 0.5 * w, (1.0 - np.cos(safe_w)) / safe_w)  # (1-cos(w))/w
    out = np.empty(xi.shape, dtype=np.float64)
    out[..., 0] = a * xi[..., 0] - b * xi[..., 1]
    out[..., 1] = b * xi[..., 0] + a * xi[..., 1]
    out[..., 2] = wrap_angles(w)
    return out


def se2_adjoint(poses: np.ndarray) -> np.ndarray:
    """``Pose2.AdjointMap`` of ``(..., 3)`` poses -> ``(..., 3, 3)``: ``T Exp(ξ) = Exp(Ad(T) ξ) T``."""
    poses = np.asarray(poses, dtype=np.float64)
    c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    ad = np.zeros(poses.shape[:-1] + (3, 3), dtype=np.float64)
    ad[..., 0, 0], ad[..., 0, 1], ad[..., 0, 2] = c, -s, poses[..., 1]
    ad[..., 1, 0], ad[..., 1, 1], ad[..., 1, 2] = s, c, -poses[..., 0]
    ad[..., 2, 2] = 1.0
    return ad


def se2_adjoint_inverse(poses: np.ndarray) -> np.ndarray:
    """``Ad(T)⁻¹ = Ad(T⁻¹)`` for ``(..., 3)`` poses -> ``(..., 3, 3)``."""
    poses = np.asarray(poses, dtype=np.float64)
    c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    x, y = poses[..., 0], poses[..., 1]
    ad = np.zeros(poses.shape[:-1] + (3, 3), dtype=np.float64)
    ad[..., 0, 0], ad[..., 0, 1], ad[..., 0, 2] = c, s, s * x - c * y
    ad[..., 1, 0], ad[..., 1, 1], ad[..., 1, 2] = -s, c, c * x + s * y
    ad[..., 2, 2] = 1.0
    return ad


# ----------------------------------------------------------------------------------------------
# Measurements and noise
# ----------------------------------------------------------------------------------------------


def upper6_to_matrix(upper6: Sequence[float]) -> np.ndarray:
    """g2o upper triangle ``(I_xx, I_xy, I_xθ, I_yy, I_yθ, I_θθ)`` -> symmetric ``(3, 3)``."""
    a, b, c, d, e, f = (float(v) for v in upper6)
    return np.array([[a, b, c], [b, d, e], [c, e, f]], dtype=np.float64)


def as_information_matrix(information, *, what: str) -> np.ndarray:
    """Validate ``information`` (``(3, 3)`` or upper-6) as symmetric positive definite.

    Raises:
        VerificationError: naming ``what`` (e.g. ``"loop constraint 12 (query 530, match 40)"``)
            when the matrix is malformed, not finite or not positive definite.
    """
    arr = np.asarray(information, dtype=np.float64)
    if arr.shape == (6,):
        arr = upper6_to_matrix(arr)
    if arr.shape != (3, 3):
        raise VerificationError(
            f"{what}: information matrix has shape {arr.shape}, expected (3, 3) or 6 upper-triangle values"
        )
    if not np.all(np.isfinite(arr)):
        raise VerificationError(f"{what}: information matrix has non-finite entries", fix="check the source log")
    arr = 0.5 * (arr + arr.T)
    try:
        np.linalg.cholesky(arr)
    except np.linalg.LinAlgError:
        raise VerificationError(
            f"{what}: information matrix is singular or not positive definite "
            f"(eigenvalues {np.round(np.linalg.eigvalsh(arr), 6).tolist()})",
            fix="give it a positive-definite information matrix, or drop it from the source",
        ) from None
    return arr


def information_to_noise(information, *, what: str = "factor"):
    """A ``gtsam.noiseModel.Gaussian`` from a ``(3, 3)`` (or upper-6) information matrix.

    Raises:
        VerificationError: naming ``what`` when the matrix is singular / not positive definite.
    """
    import gtsam

    return gtsam.noiseModel.Gaussian.Information(as_information_matrix(information, what=what))


def describe_constraint(constraint: "Constraint") -> str:
    """``"loop constraint 12 (query 530, match 40)"``: how errors name a constraint."""
    return f"loop constraint {constraint.id} (query {constraint.query_frame}, match {constraint.match_frame})"


def loop_measurement(constraint: "Constraint", default_information: np.ndarray) -> tuple[Pose2D, np.ndarray]:
    """The measured ``T_match_query`` and its ``(3, 3)`` information for a loop constraint.

    A candidate without a relative pose ("same place", from place recognition) is the identity
    with ``default_information``; a candidate without an information matrix uses
    ``default_information`` too.

    Raises:
        VerificationError: naming the constraint when its information is singular.
    """
    cand = constraint.candidate
    measured = cand.T_match_query if cand.T_match_query is not None else Pose2D(0.0, 0.0, 0.0)
    info = cand.information if cand.information is not None else default_information
    return measured, as_information_matrix(info, what=describe_constraint(constraint))


def loop_arrays(
    constraints: Sequence["Constraint"], default_information: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Constraints as arrays for vectorised chi-square.

    Returns:
        ``(match_idx (C,), query_idx (C,), measured (C, 3), information (C, 3, 3))``.
    """
    n = len(constraints)
    match_idx = np.empty(n, dtype=np.int64)
    query_idx = np.empty(n, dtype=np.int64)
    measured = np.empty((n, 3), dtype=np.float64)
    info = np.empty((n, 3, 3), dtype=np.float64)
    for k, c in enumerate(constraints):
        z, omega = loop_measurement(c, default_information)
        match_idx[k], query_idx[k] = c.match_frame, c.query_frame
        measured[k] = z
        info[k] = omega
    return match_idx, query_idx, measured, info


def odometry_between(odom_poses: np.ndarray) -> np.ndarray:
    """Relative odometry steps ``T_k_k+1``: ``(N, 3)`` cumulative poses -> ``(N-1, 3)``."""
    odom = _check_poses(odom_poses, "odom_poses")
    return se2_between(odom[:-1], odom[1:])


def extend_by_odometry(poses: np.ndarray, odom_poses: np.ndarray) -> np.ndarray:
    """Extend an estimate of frames ``0..M-1`` to frames ``0..N-1`` by chaining odometry.

    Frame ``k >= M`` gets ``poses[M-1] ∘ (odom[M-1]⁻¹ ∘ odom[k])``, which is the chain of the
    odometry steps after ``M-1``.

    Args:
        poses: ``(M, 3)`` estimate, ``1 <= M <= N``.
        odom_poses: ``(N, 3)`` cumulative odometry.

    Returns:
        ``(N, 3)``; the first ``M`` rows are ``poses`` (a copy).
    """
    poses = _check_poses(poses, "poses")
    odom = _check_poses(odom_poses, "odom_poses")
    m, n = len(poses), len(odom)
    if m > n or m == 0:
        raise VerificationError(f"cannot extend an estimate of {m} frames by odometry of {n} frames")
    out = np.empty((n, 3), dtype=np.float64)
    out[:m] = poses
    if n > m:
        out[m:] = se2_compose(poses[m - 1], se2_between(odom[m - 1], odom[m:]))
    return out


# ----------------------------------------------------------------------------------------------
# The odometry chain as a random walk: O(1) covariance of any segment, Brownian-bridge interpolation
# ----------------------------------------------------------------------------------------------


class OdometryChain:
    """A growing cumulative odometry ``O_0..O_{N-1}`` with its first-order uncertainty model.

    Model (linearised at the odometry): the pose of frame k is ``x_k = Exp(ξ_k) O_k`` with ``ξ``
    a world-frame left perturbation; each step adds its noise ``ε_k ~ N(0, Σ)`` (right
    perturbation, GTSAM's ``BetweenFactor`` convention), so ``ξ_{k+1} = ξ_k + Ad(O_{k+1}) ε_k``
    is a random walk with ``ξ_0 = 0`` (the prior) and ``Cov(ξ_a, ξ_b) = S[min(a, b)]`` where
    ``S[k] = Σ_{j<k} Ad(O_{j+1}) Σ Ad(O_{j+1})ᵀ``. The prefix sums ``S`` make the covariance of
    any segment, and of any pair of loop residuals, O(1).

    Args:
        odom_information: ``(3, 3)`` information of one odometry step.
    """

    def __init__(self, odom_information: np.ndarray):
        self.information = as_information_matrix(odom_information, what="odometry")
        self.step_covariance = np.linalg.inv(self.information)
        self._poses = np.zeros((0, 3))
        self._prefix = np.zeros((0, 3, 3))
        self._n = 0

    def __len__(self) -> int:
        return self._n

    @property
    def poses(self) -> np.ndarray:
        """``(N, 3)`` cumulative odometry (a read-only view)."""
        view = self._poses[: self._n]
        view.flags.writeable = False
        return view

    @property
    def prefix(self) -> np.ndarray:
        """``(N, 3, 3)`` ``S[k] = Cov(ξ_k)`` (a read-only view)."""
        view = self._prefix[: self._n]
        view.flags.writeable = False
        return view

    def extend(self, poses: np.ndarray) -> None:
        """Append ``(K, 3)`` cumulative odometry poses (amortised O(K))."""
        poses = _check_poses(poses, "poses")
        k = len(poses)
        if k == 0:
            return
        if self._n + k > len(self._poses):
            capacity = max(2 * len(self._poses), self._n + k, 64)
            self._poses = _grow(self._poses, capacity)
            self._prefix = _grow(self._prefix, capacity)
        self._poses[self._n : self._n + k] = poses
        base = self._prefix[self._n - 1] if self._n else None
        self._prefix[self._n : self._n + k] = random_walk_prefix(poses, self.step_covariance, base)
        self._n += k

    def segment_covariance(self, a: np.ndarray, b: np.ndarray, prefix: np.ndarray | None = None) -> np.ndarray:
        """Covariance of the composed odometry ``O_a⁻¹ O_b`` (right perturbation at ``b``, the
        convention of GTSAM's ``BetweenFactor``): ``Ad(O_b)⁻¹ (S[b] - S[a]) Ad(O_b)⁻ᵀ``.

        Args:
            a, b: ``(K,)`` frame indices with ``a < b``.
            prefix: ``(N, 3, 3)`` prefix sums of another step covariance
                (:func:`random_walk_prefix` of the chain's poses), or ``None`` for the chain's own.

        Returns:
            ``(K, 3, 3)``.
        """
        a = np.asarray(a, dtype=np.int64)
        b = np.asarray(b, dtype=np.int64)
        prefix = self._prefix if prefix is None else prefix
        inv_ad = se2_adjoint_inverse(self._poses[b])
        return inv_ad @ (prefix[b] - prefix[a]) @ np.swapaxes(inv_ad, -1, -2)

    def interpolate(self, node_frames: np.ndarray, node_poses: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Poses of ``frames`` given the estimated poses of ``node_frames``.

        Between two nodes ``a < k < b`` the correction to the odometry is the conditional mean of
        the random walk given both ends (a Brownian bridge, expressed in the frame of ``a``):
        ``x_k = x_a Exp(ζ_k) O_a⁻¹ O_k`` with ``ζ_k = Ad(O_a)⁻¹ (S[k]-S[a]) (S[b]-S[a])⁻¹ Ad(O_a) ζ_b``
        and ``ζ_b = Log(x_a⁻¹ x_b (O_a⁻¹ O_b)⁻¹)``. After the last node, frames are extended by
        odometry (``ζ = 0``). This is the MAP of the full chain given the nodes, to first order.

        Args:
            node_frames: ``(K,)`` strictly increasing frame indices, ``node_frames[0] == 0``.
            node_poses: ``(K, 3)`` their estimated poses.
            frames: ``(F,)`` frame indices in ``0..N-1``.

        Returns:
            ``(F, 3)`` poses.
        """
        node_frames = np.asarray(node_frames, dtype=np.int64)
        frames = np.asarray(frames, dtype=np.int64)
        odom = self._poses
        seg = np.searchsorted(node_frames, frames, side="right") - 1
        a = node_frames[seg]
        xa = node_poses[seg]
        rel = se2_between(odom[a], odom[frames])  # O_a⁻¹ O_k
        out = se2_compose(xa, rel)  # extension by odometry from node a
        interior = (seg + 1 < len(node_frames)) & (frames != a)
        if np.any(interior):
            s_idx = seg[interior]
            a_i, b_i, k_i = node_frames[s_idx], node_frames[s_idx + 1], frames[interior]
            x_a, x_b = node_poses[s_idx], node_poses[s_idx + 1]
            odo_ab = se2_between(odom[a_i], odom[b_i])
            zeta_b = se2_logmap(se2_compose(se2_between(x_a, x_b), _se2_inverse(odo_ab)))
            ad_a = se2_adjoint(odom[a_i])
            inv_ad_a = se2_adjoint_inverse(odom[a_i])
            S = self._prefix
            gain = np.linalg.solve(S[b_i] - S[a_i], (ad_a @ zeta_b[:, :, None]))  # (K, 3, 1)
            zeta_k = (inv_ad_a @ (S[k_i] - S[a_i]) @ gain)[:, :, 0]
            out[interior] = se2_compose(se2_compose(x_a, se2_expmap(zeta_k)), rel[interior])
        return out


def random_walk_prefix(poses: np.ndarray, step_covariance: np.ndarray, base: np.ndarray | None = None) -> np.ndarray:
    """Prefix sums ``S[k] = Σ_{j<k} Ad(X_{j+1}) Σ Ad(X_{j+1})ᵀ`` of the odometry random walk
    linearised at the poses ``X`` (see :class:`OdometryChain`).

    Args:
        poses: ``(K, 3)`` poses ``X`` of consecutive frames.
        step_covariance: ``(3, 3)`` covariance of one odometry step.
        base: ``(3, 3)`` prefix sum of the frame before ``poses[0]``, or ``None`` when
            ``poses[0]`` is frame 0 (fixed by the prior, ``S[0] = 0``).

    Returns:
        ``(K, 3, 3)``.
    """
    ad = se2_adjoint(poses)
    q = ad @ step_covariance @ np.swapaxes(ad, -1, -2)
    if base is None:
        q[0] = 0.0
        base = np.zeros((3, 3))
    return base + np.cumsum(q, axis=0)


def _se2_inverse(poses: np.ndarray) -> np.ndarray:
    return se2_between(poses, np.zeros_like(poses))


def _grow(array: np.ndarray, capacity: int) -> np.ndarray:
    out = np.zeros((capacity,) + array.shape[1:], dtype=array.dtype)
    out[: len(array)] = array
    return out


# ----------------------------------------------------------------------------------------------
# Chi-square without a graph (numpy; equals GTSAM's 2 × factor.error for Gaussian factors)
# ----------------------------------------------------------------------------------------------


def between_residuals(poses: np.ndarray, i_idx: np.ndarray, j_idx: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """Residuals ``Logmap(z⁻¹ · (x_i⁻¹ x_j))`` of between factors: ``(K,)`` indices -> ``(K, 3)``."""
    rel = se2_between(poses[i_idx], poses[j_idx])
    return se2_logmap(se2_between(measured, rel))


def between_chi2(
    poses: np.ndarray, i_idx: np.ndarray, j_idx: np.ndarray, measured: np.ndarray, information: np.ndarray
) -> np.ndarray:
    """Whitened chi-square ``r^T Ω r`` of between factors.

    Args:
        poses: ``(N, 3)``; ``i_idx``, ``j_idx``: ``(K,)`` frame indices; ``measured``: ``(K, 3)``
            ``T_i_j``; ``information``: ``(3, 3)`` shared or ``(K, 3, 3)`` per factor.

    Returns:
        ``(K,)`` chi-square values (3 degrees of freedom each).
    """
    r = between_residuals(poses, i_idx, j_idx, measured)
    if information.ndim == 2:
        return np.einsum("ki,ij,kj->k", r, information, r)
    return np.einsum("ki,kij,kj->k", r, information, r)


def loop_chi2(poses: np.ndarray, constraint: "Constraint", information: np.ndarray) -> float:
    """Whitened chi-square of one loop constraint at ``poses`` (``information`` is the default
    used when the candidate carries none)."""
    measured, omega = loop_measurement(constraint, information)
    idx_m = np.array([constraint.match_frame])
    idx_q = np.array([constraint.query_frame])
    return float(between_chi2(poses, idx_m, idx_q, np.asarray(measured)[None, :], omega)[0])


def odometry_chi2(poses: np.ndarray, odom_poses: np.ndarray, odom_information: np.ndarray) -> np.ndarray:
    """Whitened chi-square of every odometry factor ``(k, k+1)``: ``(N, 3)`` -> ``(N-1,)``."""
    n = len(odom_poses)
    idx = np.arange(n - 1)
    return between_chi2(poses[:n], idx, idx + 1, odometry_between(odom_poses), odom_information)


# ----------------------------------------------------------------------------------------------
# GTSAM graphs and solvers
# ----------------------------------------------------------------------------------------------


def odometry_factor_indices(num_frames: int) -> list[int]:
    """Indices of the prior and odometry factors in a graph from :func:`build_graph`."""
    return list(range(num_frames))


def loop_factor_index(num_frames: int, position: int) -> int:
    """Index of the ``position``-th loop constraint's factor in a graph from :func:`build_graph`."""
    return num_frames + position


def build_graph(
    odom_poses: np.ndarray,
    odom_information: np.ndarray,
    constraints: Sequence["Constraint"],
    *,
    loop_default_information: np.ndarray,
    robust: RobustKernel | None = None,
):
    """Pose graph of odometry plus ``constraints`` (see the module docstring for factor order).

    Args:
        odom_poses: ``(N, 3)`` cumulative odometry, N >= 1; the prior fixes frame 0 there.
        odom_information: ``(3, 3)`` information of one odometry step.
        constraints: loop constraints with both frames in ``0..N-1``.
        loop_default_information: ``(3, 3)`` information of a candidate that carries none.
        robust: kernel wrapped around every loop factor, or ``None`` for plain Gaussian.

    Returns:
        ``gtsam.NonlinearFactorGraph`` with ``N + len(constraints)`` factors.

    Raises:
        VerificationError: a constraint references a frame outside ``0..N-1``, or an
            information matrix is singular (naming the constraint).
    """
    import gtsam

    odom = _check_poses(odom_poses, "odom_poses")
    n = len(odom)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*odom[0]), gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
    odom_noise = information_to_noise(odom_information, what="odometry")
    for k, step in enumerate(odometry_between(odom)):
        graph.add(gtsam.BetweenFactorPose2(k, k + 1, gtsam.Pose2(*step), odom_noise))
    for c in constraints:
        if not (0 <= c.match_frame < n and 0 <= c.query_frame < n):
            raise VerificationError(
                f"{describe_constraint(c)} references a frame outside 0..{n - 1}",
                fix="add the frames before the constraints that reference them",
            )
    add_loop_factors(graph, [loop_factor(c, loop_default_information) for c in constraints], robust=robust)
    return graph


def add_loop_factors(graph, loops: Sequence["LoopFactor"], *, robust: RobustKernel | None = None) -> None:
    """Append ``BetweenFactorPose2(match, query, measured)`` for each loop to ``graph`` (in order)."""
    import gtsam

    estimator = robust.estimator() if robust is not None else None
    for loop in loops:
        noise = gtsam.noiseModel.Gaussian.Information(loop.information)
        if estimator is not None:
            noise = gtsam.noiseModel.Robust.Create(estimator, noise)
        graph.add(gtsam.BetweenFactorPose2(int(loop.match_frame), int(loop.query_frame), gtsam.Pose2(*loop.measured), noise))


class LoopFactor(NamedTuple):
    """A loop factor ready for a graph: ``BetweenFactorPose2(match_frame, query_frame, measured)``.

    ``measured`` is ``(3,)`` ``T_match_query``; ``information`` is ``(3, 3)``.
    """

    match_frame: int
    query_frame: int
    measured: np.ndarray
    information: np.ndarray


def loop_factor(constraint: "Constraint", default_information: np.ndarray) -> LoopFactor:
    """The :class:`LoopFactor` of a constraint (see :func:`loop_measurement`)."""
    measured, omega = loop_measurement(constraint, default_information)
    return LoopFactor(constraint.match_frame, constraint.query_frame, np.asarray(measured, dtype=np.float64), omega)


def build_reduced_graph(chain: OdometryChain, node_frames: np.ndarray, loops: Sequence[LoopFactor]):
    """Pose graph on ``node_frames`` only: the odometry between consecutive nodes is composed
    into one factor (exact measurement ``O_a⁻¹ O_b``, covariance from
    :meth:`OdometryChain.segment_covariance`, first order), plus the loops.

    Solving it gives the poses of the nodes; :meth:`OdometryChain.interpolate` gives the other
    frames. With the nodes at the loop endpoints this is the full graph's solution to first order,
    at a cost that depends on the number of loops, not of frames.

    Args:
        chain: the odometry.
        node_frames: ``(K,)`` strictly increasing, ``node_frames[0] == 0``, containing every
            endpoint of ``loops``.
        loops: loop factors.

    Returns:
        ``gtsam.NonlinearFactorGraph``: prior on frame 0, ``K - 1`` chain factors, then the loops.
    """
    import gtsam

    node_frames = np.asarray(node_frames, dtype=np.int64)
    if len(node_frames) == 0 or node_frames[0] != 0 or np.any(np.diff(node_frames) <= 0) or node_frames[-1] >= len(chain):
        raise VerificationError(f"reduced graph nodes must be increasing frames from 0 to < {len(chain)}")
    odom = chain.poses
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*odom[0]), gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
    a, b = node_frames[:-1], node_frames[1:]
    if len(a):
        steps = se2_between(odom[a], odom[b])
        covariances = chain.segment_covariance(a, b)
        for k in range(len(a)):
            noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (covariances[k] + covariances[k].T))
            graph.add(gtsam.BetweenFactorPose2(int(a[k]), int(b[k]), gtsam.Pose2(*steps[k]), noise))
    nodes = set(node_frames.tolist())
    for loop in loops:
        if loop.match_frame not in nodes or loop.query_frame not in nodes:
            raise VerificationError(f"loop ({loop.query_frame}, {loop.match_frame}) has an endpoint that is not a node")
    add_loop_factors(graph, loops)
    return graph


def relative_covariances(graph, poses: np.ndarray, keys: Sequence[int], match: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Laplace covariances of relative poses ``x_m⁻¹ x_q`` from GTSAM's marginals of ``graph``
    linearised at ``poses``.

    With ``x = x̄ Exp(δ)`` (GTSAM's right perturbation), ``x_m⁻¹ x_q ≈ x̄_mq Exp(δ_q - A δ_m)`` with
    ``A = Ad(x̄_mq⁻¹)``, so the covariance is ``[-A I] Σ_{mq} [-A I]ᵀ`` of the joint marginal of
    ``(x_m, x_q)``. This is the covariance of a loop's prediction under the graph: add the loop's
    own measurement covariance for its innovation covariance.

    Args:
        graph: a ``gtsam.NonlinearFactorGraph`` over Pose2 ``keys``.
        poses: ``(K, 3)`` linearisation point of ``keys`` (e.g. the graph's solution).
        keys: ``(K,)`` the graph's keys, increasing.
        match, query: ``(L,)`` keys (each in ``keys``), ``match < query``.

    Returns:
        ``(L, 3, 3)`` covariances in the tangent space at ``x̄_q`` of the relative pose.

    Raises:
        OptimisationFailed: GTSAM cannot factor the graph (e.g. an under-constrained key).
    """
    import gtsam

    match = np.asarray(match, dtype=np.int64)
    query = np.asarray(query, dtype=np.int64)
    out = np.empty((len(match), 3, 3))
    if len(match) == 0:
        return out
    keys = np.asarray(keys, dtype=np.int64)
    joints = np.empty((len(match), 6, 6))
    try:
        marginals = gtsam.Marginals(graph, initial_values(poses, keys))
        # One joint marginal per chunk of pairs: several times faster than one query per pair.
        for start in range(0, len(match), _MARGINAL_CHUNK):
            chunk = range(start, min(start + _MARGINAL_CHUNK, len(match)))
            wanted = sorted({int(match[k]) for k in chunk} | {int(query[k]) for k in chunk})
            joint = marginals.jointMarginalCovariance(gtsam.KeyVector(wanted))
            for k in chunk:
                m, q = int(match[k]), int(query[k])
                joints[k, :3, :3], joints[k, :3, 3:] = joint.at(m, m), joint.at(m, q)
                joints[k, 3:, :3], joints[k, 3:, 3:] = joint.at(q, m), joint.at(q, q)
    except RuntimeError as exc:
        raise OptimisationFailed(f"marginal covariances failed: {_first_line(exc)}") from exc
    index = np.searchsorted(keys, np.concatenate([match, query]))
    x_m, x_q = np.split(np.asarray(poses, dtype=np.float64)[index], 2)
    jac = np.zeros((len(match), 3, 6))
    jac[:, :, :3] = -se2_adjoint_inverse(se2_between(x_m, x_q))
    jac[:, :, 3:] = np.eye(3)
    out[:] = jac @ joints @ np.swapaxes(jac, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


#: Pairs per joint-marginal query in :func:`relative_covariances` (measured fastest on KITTI and
#: Manhattan graphs: one query per pair costs about 1 ms each, one per 32 pairs about 0.3 ms a pair).
_MARGINAL_CHUNK = 32


class IncrementalGraph:
    """The odometry chain plus a changing set of loop factors, kept solved by iSAM2
    (``gtsam.ISAM2``): ``ilv+``'s working hypothesis.

    Frame ``k`` is key ``k``; frame 0 has the usual prior. Frames are appended with
    :meth:`extend` (initialised by odometry from the last estimate) and loops are added or removed
    by their constraint id with :meth:`update`. Each update re-eliminates only the part of the
    Bayes tree the change touches, then relinearises until no variable moves by more than
    ``relinearize_threshold`` (at most ``max_relinearizations`` extra steps), so the estimate is
    converged to that threshold. Cost of an update: the cliques between the changed keys and the
    root, not the whole history.

    Args:
        odom_information: ``(3, 3)`` information of one odometry step.
        relinearize_threshold: iSAM2's relinearisation threshold (tangent-space units).
        max_relinearizations: extra relinearisation steps after each update.
    """

    def __init__(self, odom_information: np.ndarray, *, relinearize_threshold: float = 0.05, max_relinearizations: int = 2):
        import gtsam

        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(float(relinearize_threshold))
        params.relinearizeSkip = 2**30  # relinearise only when asked (force_relinearize)
        self._isam = gtsam.ISAM2(params)
        self._odom_noise = information_to_noise(odom_information, what="odometry")
        self._odom = np.zeros((0, 3))
        self._pending_from = 0  # first frame not yet in iSAM2
        self._slots: dict[int, int] = {}  # loop id -> iSAM2 factor index
        self._loops: dict[int, LoopFactor] = {}
        self._params = params
        self._estimate: np.ndarray | None = None
        self.max_relinearizations = int(max_relinearizations)
        self.updates = 0  # iSAM2 update calls so far (for timings)

    def __len__(self) -> int:
        return len(self._odom)

    @property
    def loop_ids(self) -> frozenset[int]:
        """Ids of the loops in the graph."""
        return frozenset(self._slots)

    def extend(self, odom_poses: np.ndarray) -> None:
        """Set the cumulative odometry to ``odom_poses`` (``(N, 3)``; the first frames must equal
        the ones given before); the new frames join the graph at the next :meth:`update`."""
        odom = _check_poses(odom_poses, "odom_poses")
        if len(odom) < len(self._odom):
            raise VerificationError(f"odometry cannot shrink from {len(self._odom)} to {len(odom)} frames")
        self._odom = odom.copy()

    def update(self, add: Sequence[tuple[int, "LoopFactor"]] = (), remove: Sequence[int] = (), *, relinearize: bool = True) -> None:
        """Add loops ``(id, factor)`` and remove loops by id (and append the frames given to
        :meth:`extend`); then relinearise to convergence, or (``relinearize=False``) not.

        Raises:
            VerificationError: a loop id added twice, removed while absent, or referencing a
                frame outside the graph.
            OptimisationFailed: iSAM2 failed.
        """
        import gtsam

        n = len(self._odom)
        factors = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        start = self._pending_from
        if start < n:
            if start == 0:
                factors.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*self._odom[0]), gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
                values.insert(0, gtsam.Pose2(*self._odom[0]))
                first, last = 1, self._odom[0]
            else:
                first, last = start, self.estimate()[start - 1]
            steps = se2_between(self._odom[first - 1 : n - 1], self._odom[first:n])
            extended = se2_compose(last, se2_between(self._odom[first - 1], self._odom[first:n]))
            for k, (step, pose) in enumerate(zip(steps.tolist(), extended.tolist()), start=first):
                factors.add(gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(*step), self._odom_noise))
                values.insert(k, gtsam.Pose2(*pose))
        added_ids = []
        for loop_id, loop in add:
            if loop_id in self._slots or loop_id in added_ids:
                raise VerificationError(f"loop {loop_id} is already in the graph")
            if not (0 <= loop.match_frame < n and 0 <= loop.query_frame < n):
                raise VerificationError(f"loop {loop_id} references a frame outside 0..{n - 1}")
            added_ids.append(int(loop_id))
        add_loop_factors(factors, [loop for _, loop in add])
        removed = []
        for loop_id in remove:
            if loop_id not in self._slots:
                raise VerificationError(f"loop {loop_id} is not in the graph")
            removed.append(self._slots.pop(loop_id))
        if factors.size() == 0 and not removed and not relinearize:
            return
        try:
            result = self._isam.update(factors, values, removed, force_relinearize=relinearize)
            self.updates += 1
            new_slots = list(result.getNewFactorsIndices())
            for _ in range(self.max_relinearizations if relinearize and result.getVariablesRelinearized() else 0):
                again = self._isam.update(force_relinearize=True)
                self.updates += 1
                if again.getVariablesRelinearized() == 0:
                    break
        except RuntimeError as exc:
            raise OptimisationFailed(f"iSAM2 update failed: {_first_line(exc)}") from exc
        offset = factors.size() - len(added_ids)  # the odometry factors come first
        for k, (loop_id, (_, loop)) in enumerate(zip(added_ids, add)):
            self._slots[loop_id] = int(new_slots[offset + k])
            self._loops[loop_id] = loop
        for loop_id in remove:
            self._loops.pop(loop_id, None)
        self._pending_from = n
        self._estimate = None

    def restart(self, initial: np.ndarray) -> None:
        """Rebuild the iSAM2 state from scratch with the same factors, linearised at ``initial``
        (``(N, 3)``, e.g. an earlier estimate of the same loop set): a way back to a known
        solution after changes that relinearised far away from it."""
        import gtsam

        initial = _check_poses(initial, "initial")
        n = len(self._odom)
        if len(initial) != n:
            raise VerificationError(f"restart needs {n} poses, got {len(initial)}")
        loops = sorted(self._loops.items())
        self._isam = gtsam.ISAM2(self._params)
        self._slots, self._loops = {}, {}
        self._pending_from, self._estimate = 0, None
        factors = gtsam.NonlinearFactorGraph()
        factors.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*self._odom[0]), gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
        steps = se2_between(self._odom[:-1], self._odom[1:])
        for k, step in enumerate(steps.tolist(), start=1):
            factors.add(gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(*step), self._odom_noise))
        add_loop_factors(factors, [loop for _, loop in loops])
        try:
            result = self._isam.update(factors, initial_values(initial), [], force_relinearize=True)
            self.updates += 1
        except RuntimeError as exc:
            raise OptimisationFailed(f"iSAM2 restart failed: {_first_line(exc)}") from exc
        new_slots = list(result.getNewFactorsIndices())
        offset = factors.size() - len(loops)
        for k, (loop_id, loop) in enumerate(loops):
            self._slots[loop_id] = int(new_slots[offset + k])
            self._loops[loop_id] = loop
        self._pending_from = n

    def marginal_covariance(self, frame: int) -> np.ndarray:
        """``(3, 3)`` marginal covariance of frame ``frame`` (right perturbation at its estimate),
        from iSAM2's Bayes tree (cheap for recent frames, near the root)."""
        try:
            return np.asarray(self._isam.marginalCovariance(int(frame)), dtype=np.float64)
        except RuntimeError as exc:
            raise OptimisationFailed(f"marginal covariance of frame {frame} failed: {_first_line(exc)}") from exc

    def relative_covariance(self, match: int, query: int) -> np.ndarray:
        """``(3, 3)`` covariance of the relative pose ``x_match⁻¹ x_query`` under the graph
        (GTSAM's joint marginal of the two frames from iSAM2's Bayes tree, transported as in
        :func:`relative_covariances`; costly for two frames deep in the tree)."""
        import gtsam

        m, q = int(match), int(query)
        try:
            joint = self._isam.jointMarginalCovariance(gtsam.KeyVector([m, q]))
            block = np.block([[joint.at(m, m), joint.at(m, q)], [joint.at(q, m), joint.at(q, q)]])
        except RuntimeError as exc:
            raise OptimisationFailed(f"joint marginal of frames {m} and {q} failed: {_first_line(exc)}") from exc
        x = self.estimate()
        jac = np.zeros((3, 6))
        jac[:, :3] = -se2_adjoint_inverse(se2_between(x[m], x[q]))
        jac[:, 3:] = np.eye(3)
        out = jac @ block @ jac.T
        return 0.5 * (out + out.T)

    def estimate(self) -> np.ndarray:
        """``(N', 3)`` current estimate of the frames in the graph (cached until the next update)."""
        if self._estimate is None:
            import gtsam

            if self._pending_from == 0:
                return np.zeros((0, 3))
            poses = np.asarray(gtsam.utilities.extractPose2(self._isam.calculateEstimate()), dtype=np.float64)
            if not np.isfinite(poses.sum()):
                raise OptimisationFailed("iSAM2 produced a non-finite estimate")
            self._estimate = poses
        return self._estimate


def initial_values(poses: np.ndarray, keys: Sequence[int] | None = None):
    """``gtsam.Values`` with ``Pose2`` key ``keys[i]`` (default ``i``) = ``poses[i]`` for ``(N, 3)`` poses."""
    import gtsam

    poses = _check_poses(poses, "poses")
    keys = range(len(poses)) if keys is None else [int(k) for k in keys]
    values = gtsam.Values()
    for k, (x, y, yaw) in zip(keys, poses.tolist()):
        values.insert(k, gtsam.Pose2(x, y, yaw))
    return values


def values_to_poses(values, num_frames: int) -> np.ndarray:
    """``(N, 3)`` array of the ``N`` ``Pose2`` values, in increasing key order."""
    import gtsam

    if num_frames == 0:
        return np.zeros((0, 3))
    poses = np.asarray(gtsam.utilities.extractPose2(values), dtype=np.float64)
    if poses.shape != (num_frames, 3):
        raise OptimisationFailed(f"expected {num_frames} Pose2 values, GTSAM returned {poses.shape[0]}")
    return poses


def optimise_lm(
    graph,
    initial: np.ndarray,
    *,
    keys: Sequence[int] | None = None,
    max_iterations: int = 100,
    relative_error_tol: float = 1e-5,
) -> PoseGraphSolution:
    """Levenberg-Marquardt from ``initial`` (``(N, 3)``, e.g. the parent hypothesis' estimate).

    ``keys`` are the graph keys of the rows of ``initial`` (increasing; default ``0..N-1``); the
    solution's poses are in the same order.

    GTSAM's LM damps an indeterminant system instead of throwing; a GTSAM exception or a
    non-finite solution (overflowing information, NaN start) is reported as a failure.

    Raises:
        OptimisationFailed: GTSAM raised (e.g. an indeterminant linear system) or the solution
            is not finite.
    """
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(float(relative_error_tol))
    values = initial_values(initial, keys)
    try:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = optimizer.optimize()
    except RuntimeError as exc:
        raise OptimisationFailed(f"Levenberg-Marquardt failed: {_first_line(exc)}") from exc
    poses, error = values_to_poses(result, len(initial)), float(graph.error(result))
    _finite_solution(poses, error, "Levenberg-Marquardt")
    return PoseGraphSolution(poses, error, int(optimizer.iterations()))


def optimise_gnc_tls(
    graph,
    initial: np.ndarray,
    known_inliers: Sequence[int],
    *,
    weights_tol: float = 1e-9,
    max_iterations: int = 100,
    inlier_probability: float | None = None,
) -> tuple[PoseGraphSolution, np.ndarray]:
    """Graduated non-convexity with the truncated-least-squares loss (``gtsam.GncLMOptimizer``).

    Args:
        graph: Gaussian factors (no robust kernels); ``known_inliers`` (e.g.
            :func:`odometry_factor_indices`) are never down-weighted.
        initial: ``(N, 3)`` start.
        weights_tol: GNC stops when weights change less than this; GTSAM's default 1e-4 stops
            after 1-2 iterations on KITTI loop candidates with every weight ~1e-5, so 1e-9 runs the
            schedule to binary weights.
        inlier_probability: if given, the TLS barrier is the chi-square quantile of this
            probability (3 dof), else GTSAM's default.

    Returns:
        ``(solution, weights (F,))``: ``weights[f]`` in [0, 1] for factor ``f`` (1 = inlier).

    Raises:
        OptimisationFailed: GTSAM failed.
    """
    import gtsam

    params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(list(int(i) for i in known_inliers))
    params.setWeightsTol(float(weights_tol))
    if int(max_iterations) != params.maxIterations:  # GTSAM prints a warning on every call
        params.setMaxIterations(int(max_iterations))
    values = initial_values(initial)
    try:
        optimizer = gtsam.GncLMOptimizer(graph, values, params)
        if inlier_probability is not None:
            optimizer.setInlierCostThresholdsAtProbability(float(inlier_probability))
        result = optimizer.optimize()
    except RuntimeError as exc:
        raise OptimisationFailed(f"GNC-TLS failed: {_first_line(exc)}") from exc
    weights = np.asarray(optimizer.getWeights(), dtype=np.float64)
    poses, error = values_to_poses(result, len(initial)), float(graph.error(result))
    _finite_solution(poses, error, "GNC-TLS")
    return PoseGraphSolution(poses, error, None), weights


# ----------------------------------------------------------------------------------------------


def _check_poses(poses: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise VerificationError(f"{name} must have shape (N, 3) [x_m, y_m, yaw_rad], got {arr.shape}")
    return arr


def _first_line(exc: BaseException) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return " ".join(lines[:2]) if lines else type(exc).__name__


def _finite_solution(poses: np.ndarray, error: float, what: str) -> None:
    if not (np.all(np.isfinite(poses)) and np.isfinite(error)):
        raise OptimisationFailed(f"{what} produced a non-finite solution (error {error})")
