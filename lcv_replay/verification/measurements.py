"""Loop and odometry measurements in numpy: what the pose graphs are built from, without GTSAM.

* Information matrices are validated once (:func:`as_information_matrix`), naming the constraint.
* A loop constraint ``(query, match)`` measures ``T_match_query``; a candidate without a relative
  pose ("same place", from place recognition) is the identity with the config's default
  information (:func:`loop_measurement`).
* :class:`OdometryChain` is the odometry's first-order uncertainty: the covariance of any segment
  in O(1) and the Brownian-bridge interpolation between solved frames.

Poses are ``(N, 3)`` float64 ``[x_m, y_m, yaw_rad]``; the algebra is :mod:`lcv_replay.se2`, the
graphs and solvers are :mod:`lcv_replay.verification.pose_graph`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from lcv_replay import se2
from lcv_replay.errors import VerificationError
from lcv_replay.records import Pose2D

if TYPE_CHECKING:  # pragma: no cover
    from lcv_replay.verification.base import Constraint


def check_poses(poses: np.ndarray, name: str) -> np.ndarray:
    """``poses`` as an ``(N, 3)`` float64 array; :class:`VerificationError` naming ``name`` otherwise."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise VerificationError(f"{name} must have shape (N, 3) [x_m, y_m, yaw_rad], got {arr.shape}")
    return arr



# ----------------------------------------------------------------------------------------------
# Information matrices and loop measurements
# ----------------------------------------------------------------------------------------------


def as_information_matrix(information, *, what: str) -> np.ndarray:
    """Validate ``information`` (``(3, 3)`` or upper-6) as symmetric positive definite.

    Raises:
        VerificationError: naming ``what`` (e.g. ``"loop constraint 12 (query 530, match 40)"``)
            when the matrix is malformed, not finite or not positive definite.
    """
    arr = np.asarray(information, dtype=np.float64)
    if arr.shape == (6,):
        arr = se2.information_matrix(arr)
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
    """Constraints as arrays for vectorised chi-square (each measurement validated:
    :func:`loop_measurement`).

    Returns:
        ``(match_idx (C,), query_idx (C,), measured (C, 3), information (C, 3, 3))``.
    """
    return measurement_arrays(constraints, [loop_measurement(c, default_information) for c in constraints])


def measurement_arrays(
    constraints: Sequence["Constraint"], measurements: Sequence[tuple[Pose2D, np.ndarray]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`loop_arrays` from the measurements of ``constraints`` already validated
    (:func:`loop_measurement`'s results, in the same order)."""
    n = len(constraints)
    match_idx = np.array([c.match_frame for c in constraints], dtype=np.int64)
    query_idx = np.array([c.query_frame for c in constraints], dtype=np.int64)
    measured = np.array([np.asarray(z, dtype=np.float64) for z, _ in measurements], dtype=np.float64).reshape(n, 3)
    info = np.array([omega for _, omega in measurements], dtype=np.float64).reshape(n, 3, 3)
    return match_idx, query_idx, measured, info


def loop_chi2(poses: np.ndarray, constraint: "Constraint", information: np.ndarray) -> float:
    """Whitened chi-square of one loop constraint at ``poses`` (``information`` is the default
    used when the candidate carries none)."""
    measured, omega = loop_measurement(constraint, information)
    idx_m = np.array([constraint.match_frame])
    idx_q = np.array([constraint.query_frame])
    return float(se2.between_chi2(poses, idx_m, idx_q, np.asarray(measured)[None, :], omega)[0])


def odometry_chi2(poses: np.ndarray, odom_poses: np.ndarray, odom_information: np.ndarray) -> np.ndarray:
    """Whitened chi-square of every odometry factor ``(k, k+1)``: ``(N, 3)`` -> ``(N-1,)``."""
    n = len(odom_poses)
    idx = np.arange(n - 1)
    return se2.between_chi2(poses[:n], idx, idx + 1, odometry_between(odom_poses), odom_information)



# ----------------------------------------------------------------------------------------------
# Odometry
# ----------------------------------------------------------------------------------------------


def odometry_between(odom_poses: np.ndarray) -> np.ndarray:
    """Relative odometry steps ``T_k_k+1``: ``(N, 3)`` cumulative poses -> ``(N-1, 3)``."""
    odom = check_poses(odom_poses, "odom_poses")
    return se2.relative_steps(odom)


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
    poses = check_poses(poses, "poses")
    odom = check_poses(odom_poses, "odom_poses")
    m, n = len(poses), len(odom)
    if m > n or m == 0:
        raise VerificationError(f"cannot extend an estimate of {m} frames by odometry of {n} frames")
    out = np.empty((n, 3), dtype=np.float64)
    out[:m] = poses
    if n > m:
        out[m:] = se2.compose(poses[m - 1], se2.between(odom[m - 1], odom[m:]))
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
        poses = check_poses(poses, "poses")
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
        inv_ad = se2.adjoint_inverse(self._poses[b])
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
        rel = se2.between(odom[a], odom[frames])  # O_a⁻¹ O_k
        out = se2.compose(xa, rel)  # extension by odometry from node a
        interior = (seg + 1 < len(node_frames)) & (frames != a)
        if np.any(interior):
            s_idx = seg[interior]
            a_i, b_i, k_i = node_frames[s_idx], node_frames[s_idx + 1], frames[interior]
            x_a, x_b = node_poses[s_idx], node_poses[s_idx + 1]
            odo_ab = se2.between(odom[a_i], odom[b_i])
            # (O_a⁻¹ O_b)⁻¹ as O_a⁻¹O_b relative to the identity: its heading re-wrapped, as the
            # measured figures were computed (se2.inverse negates it exactly; the last bits differ).
            odo_ba = se2.between(odo_ab, np.zeros_like(odo_ab))
            zeta_b = se2.logmap(se2.compose(se2.between(x_a, x_b), odo_ba))
            ad_a = se2.adjoint(odom[a_i])
            inv_ad_a = se2.adjoint_inverse(odom[a_i])
            S = self._prefix
            gain = np.linalg.solve(S[b_i] - S[a_i], (ad_a @ zeta_b[:, :, None]))  # (K, 3, 1)
            zeta_k = (inv_ad_a @ (S[k_i] - S[a_i]) @ gain)[:, :, 0]
            out[interior] = se2.compose(se2.compose(x_a, se2.expmap(zeta_k)), rel[interior])
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
    ad = se2.adjoint(poses)
    q = ad @ step_covariance @ np.swapaxes(ad, -1, -2)
    if base is None:
        q[0] = 0.0
        base = np.zeros((3, 3))
    return base + np.cumsum(q, axis=0)



def _grow(array: np.ndarray, capacity: int) -> np.ndarray:
    out = np.zeros((capacity,) + array.shape[1:], dtype=array.dtype)
    out[: len(array)] = array
    return out

