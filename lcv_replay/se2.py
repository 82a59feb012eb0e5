"""SE(2) algebra in numpy: the one place where planar poses are composed, inverted and compared.

Poses are ``[x_m, y_m, yaw_rad]``: ``T_a_b`` is the pose of frame ``b`` in frame ``a`` (see
:mod:`lcv_replay.records`). The array functions take ``(..., 3)`` arrays and broadcast; every
function that produces an angle wraps it to ``[-pi, pi)``, except :func:`inverse`, which negates
the heading exactly (as ``gtsam.Pose2.inverse``). The maths is GTSAM's ``Pose2``: tangent vectors
are ``[v_x, v_y, ω]``, perturbations are on the right (``T Exp(ξ)``), and the chi-square of a
between factor is ``rᵀ Ω r`` with ``r = Logmap(z⁻¹ · (x_i⁻¹ x_j))``, so :func:`between_chi2` equals
GTSAM's ``2 × factor.error`` without building a graph.

Information matrices travel as g2o's upper triangle ``(I_xx, I_xy, I_xθ, I_yy, I_yθ, I_θθ)``
(:func:`information_matrix`, :func:`upper_triangle`).

The ``*_pose`` functions do the same on one pose as plain floats, for per-frame hot paths and the
:class:`~lcv_replay.records.Pose2D` record: numpy costs about 30 µs a call on a single pose.

Pure functions, no I/O; this module imports nothing from lcv_replay, so every layer may use it.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

Information6 = tuple[float, float, float, float, float, float]

# ----------------------------------------------------------------------------------------------
# Arrays of poses, (..., 3)
# ----------------------------------------------------------------------------------------------


def wrap_angles(angles_rad: np.ndarray) -> np.ndarray:
    """Wrap angles to ``[-pi, pi)`` (any shape)."""
    return (np.asarray(angles_rad, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ∘ b`` for ``(..., 3)`` pose arrays (broadcasting): ``T_w_i ∘ T_i_j = T_w_j``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    out[..., 1] = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    out[..., 2] = wrap_angles(a[..., 2] + b[..., 2])
    return out


def between(a: np.ndarray, b: np.ndarray, *, cos_sin_a: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``a⁻¹ ∘ b`` for ``(..., 3)`` pose arrays: with ``a = T_w_i``, ``b = T_w_j`` this is ``T_i_j``.

    ``cos_sin_a``: ``(np.cos(a[..., 2]), np.sin(a[..., 2]))`` computed beforehand (the same values:
    for a caller that evaluates the same ``a`` many times)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = (np.cos(a[..., 2]), np.sin(a[..., 2])) if cos_sin_a is None else cos_sin_a
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    out[..., 2] = wrap_angles(b[..., 2] - a[..., 2])
    return out


def inverse(poses: np.ndarray) -> np.ndarray:
    """``T_a_b⁻¹ = T_b_a`` for ``(..., 3)`` poses; the heading is negated exactly (not re-wrapped)."""
    poses = np.asarray(poses, dtype=np.float64)
    c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    out = np.empty(poses.shape, dtype=np.float64)
    out[..., 0] = -c * poses[..., 0] - s * poses[..., 1]
    out[..., 1] = s * poses[..., 0] - c * poses[..., 1]
    out[..., 2] = -poses[..., 2]
    return out


def logmap(pose: np.ndarray) -> np.ndarray:
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


def expmap(xi: np.ndarray) -> np.ndarray:
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


def adjoint(poses: np.ndarray) -> np.ndarray:
    """``Pose2.AdjointMap`` of ``(..., 3)`` poses -> ``(..., 3, 3)``: ``T Exp(ξ) = Exp(Ad(T) ξ) T``."""
    poses = np.asarray(poses, dtype=np.float64)
    c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    ad = np.zeros(poses.shape[:-1] + (3, 3), dtype=np.float64)
    ad[..., 0, 0], ad[..., 0, 1], ad[..., 0, 2] = c, -s, poses[..., 1]
    ad[..., 1, 0], ad[..., 1, 1], ad[..., 1, 2] = s, c, -poses[..., 0]
    ad[..., 2, 2] = 1.0
    return ad


def adjoint_inverse(poses: np.ndarray) -> np.ndarray:
    """``Ad(T)⁻¹ = Ad(T⁻¹)`` for ``(..., 3)`` poses -> ``(..., 3, 3)``."""
    poses = np.asarray(poses, dtype=np.float64)
    c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    x, y = poses[..., 0], poses[..., 1]
    ad = np.zeros(poses.shape[:-1] + (3, 3), dtype=np.float64)
    ad[..., 0, 0], ad[..., 0, 1], ad[..., 0, 2] = c, s, s * x - c * y
    ad[..., 1, 0], ad[..., 1, 1], ad[..., 1, 2] = -s, c, c * x + s * y
    ad[..., 2, 2] = 1.0
    return ad


def matrices(poses: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` homogeneous matrices ``[[R, t], [0, 1]]`` of ``(N, 3)`` poses."""
    poses = np.asarray(poses, dtype=np.float64)
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    T = np.zeros((len(poses), 3, 3))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = c, -s, poses[:, 0]
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = s, c, poses[:, 1]
    T[:, 2, 2] = 1.0
    return T


def transform_points(pose: Sequence[float], xy: np.ndarray) -> np.ndarray:
    """Apply one pose ``T_a_b`` to ``(N, 2)`` positions in ``b`` (extra columns are ignored) -> ``(N, 2)`` in ``a``."""
    x_m, y_m, yaw_rad = (float(v) for v in pose)
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    xy = np.asarray(xy, dtype=np.float64)[:, :2]
    return np.column_stack([c * xy[:, 0] - s * xy[:, 1] + x_m, s * xy[:, 0] + c * xy[:, 1] + y_m])


# ----------------------------------------------------------------------------------------------
# Chains of poses
# ----------------------------------------------------------------------------------------------


def compose_chain(steps: np.ndarray, start: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Cumulative poses of a chain of relative steps.

    Args:
        steps: ``(M, 3)`` relative poses ``T_{k}_{k+1}``.
        start: the pose ``T_world_0`` of the first node.

    Returns:
        ``(M + 1, 3)`` poses ``T_world_k``; row 0 is ``start``. Yaw is wrapped to ``[-pi, pi)``.
    """
    steps = np.asarray(steps, dtype=np.float64).reshape(-1, 3)
    x0, y0, yaw0 = (float(v) for v in start)
    # Heading before each step; positions are the running sum of the rotated step translations.
    heading = yaw0 + np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    cos_h, sin_h = np.cos(heading[:-1]), np.sin(heading[:-1])
    dx = cos_h * steps[:, 0] - sin_h * steps[:, 1]
    dy = sin_h * steps[:, 0] + cos_h * steps[:, 1]
    poses = np.empty((len(steps) + 1, 3))
    poses[:, 0] = x0 + np.concatenate([[0.0], np.cumsum(dx)])
    poses[:, 1] = y0 + np.concatenate([[0.0], np.cumsum(dy)])
    poses[:, 2] = wrap_angles(heading)
    return poses


def relative_steps(poses: np.ndarray) -> np.ndarray:
    """Inverse of :func:`compose_chain`: ``(N, 3)`` poses -> ``(N - 1, 3)`` steps ``T_{k}_{k+1}``."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    return between(poses[:-1], poses[1:])


# ----------------------------------------------------------------------------------------------
# Measurements: information matrices and chi-square
# ----------------------------------------------------------------------------------------------


def information_matrix(upper6: Sequence[float]) -> np.ndarray:
    """g2o upper triangle ``(I_xx, I_xy, I_xθ, I_yy, I_yθ, I_θθ)`` -> symmetric ``(3, 3)``."""
    a, b, c, d, e, f = (float(v) for v in upper6)
    return np.array([[a, b, c], [b, d, e], [c, e, f]], dtype=np.float64)


def upper_triangle(matrix: np.ndarray) -> Information6:
    """``(3, 3)`` matrix (symmetrised) -> its upper triangle in g2o order."""
    m = 0.5 * (np.asarray(matrix, dtype=np.float64) + np.asarray(matrix, dtype=np.float64).T)
    return (float(m[0, 0]), float(m[0, 1]), float(m[0, 2]), float(m[1, 1]), float(m[1, 2]), float(m[2, 2]))


def invert_measurement(T_a_b: Sequence[float], information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A measurement ``T_a_b`` with ``(3, 3)`` information ``Λ`` as ``T_b_a`` with ``Ad⁻ᵀ Λ Ad⁻¹``.

    With the error ``ξ = Log(T̂⁻¹ T)`` of the measurement, the reversed edge has error
    ``ξ' = -Ad(T_a_b) ξ``, so its information is ``Ad(T_a_b)⁻ᵀ Λ Ad(T_a_b)⁻¹`` (first order, the
    convention of GTSAM's ``BetweenFactor``).

    Returns:
        ``(T_b_a (3,), information (3, 3))``.
    """
    pose = np.asarray(T_a_b, dtype=np.float64)
    ad_inv = np.linalg.inv(adjoint(pose))
    return inverse(pose), ad_inv.T @ np.asarray(information, dtype=np.float64) @ ad_inv


def between_residuals(
    poses: np.ndarray, i_idx: np.ndarray, j_idx: np.ndarray, measured: np.ndarray, *, measured_cos_sin: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray:
    """Residuals ``Logmap(z⁻¹ · (x_i⁻¹ x_j))`` of between factors: ``(K,)`` indices -> ``(K, 3)``
    (``measured_cos_sin``: see :func:`between`'s ``cos_sin_a``)."""
    rel = between(poses[i_idx], poses[j_idx])
    return logmap(between(measured, rel, cos_sin_a=measured_cos_sin))


def between_chi2(
    poses: np.ndarray,
    i_idx: np.ndarray,
    j_idx: np.ndarray,
    measured: np.ndarray,
    information: np.ndarray,
    *,
    measured_cos_sin: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Whitened chi-square ``rᵀ Ω r`` of between factors (GTSAM's ``2 × factor.error``).

    Args:
        poses: ``(N, 3)``; ``i_idx``, ``j_idx``: ``(K,)`` frame indices; ``measured``: ``(K, 3)``
            ``T_i_j``; ``information``: ``(3, 3)`` shared or ``(K, 3, 3)`` per factor.
        measured_cos_sin: the cosines and sines of ``measured[:, 2]``, if computed beforehand
            (for factors evaluated at many estimates).

    Returns:
        ``(K,)`` chi-square values (3 degrees of freedom each).
    """
    r = between_residuals(poses, i_idx, j_idx, measured, measured_cos_sin=measured_cos_sin)
    if information.ndim == 2:
        return np.einsum("ki,ij,kj->k", r, information, r)
    return np.einsum("ki,kij,kj->k", r, information, r)


# ----------------------------------------------------------------------------------------------
# One pose as floats (hot paths, the Pose2D record)
# ----------------------------------------------------------------------------------------------


def wrap_angle(angle_rad: float) -> float:
    """Wrap one angle to ``[-pi, pi)`` (the same arithmetic as :func:`wrap_angles`)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def compose_pose(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
    """:func:`compose` of two single poses, as floats."""
    ax, ay, ayaw = a
    bx, by, byaw = b
    c, s = math.cos(ayaw), math.sin(ayaw)
    return (ax + c * bx - s * by, ay + s * bx + c * by, wrap_angle(ayaw + byaw))


def between_pose(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
    """:func:`between` of two single poses, as floats."""
    ax, ay, ayaw = a
    bx, by, byaw = b
    c, s = math.cos(ayaw), math.sin(ayaw)
    dx, dy = bx - ax, by - ay
    return (c * dx + s * dy, -s * dx + c * dy, wrap_angle(byaw - ayaw))


def inverse_pose(pose: Sequence[float]) -> tuple[float, float, float]:
    """:func:`inverse` of a single pose, as floats."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return (-c * x - s * y, s * x - c * y, -yaw)
