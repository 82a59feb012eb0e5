"""PCA plus binary codes (paper sec. II-B, steps 2 and 3).

The paper compresses each CNN descriptor to 128-D with PCA and then to an ``N_b = 20``-bit binary
code with an incremental compact projection. We use **ITQ, iterative quantisation** (Gong &
Lazebnik, "Iterative Quantization: A Procrustean Approach to Learning Binary Codes", CVPR 2011):

1. centre the descriptors and project them on their top ``N_b`` principal directions
   (the first ``N_b`` columns of the 128-D PCA basis), ``V = (X - mean) W[:, :N_b]``;
2. learn an orthogonal ``N_b x N_b`` rotation ``R`` that minimises the quantisation loss
   ``||sign(V R) - V R||_F``, alternating ``B = sign(V R)`` and the orthogonal Procrustes update
   ``R = U_a U_b^T`` from the SVD ``B^T V = U_b S U_a^T`` (``iterations`` rounds, random orthogonal
   start drawn from ``seed``);
3. bit ``k`` of a code is ``1`` where ``(V R)[:, k] > 0``; the ``N_b`` bits are packed into one
   unsigned integer (bit ``k`` is ``1 << k``), so Hamming distances are ``popcount(a ^ b)``.

Everything is deterministic for a given input and seed: PCA axes get a fixed sign (the largest
coordinate of each axis is positive) and the ITQ start comes from ``numpy.random.default_rng(seed)``.
The projection is fitted once (on the first ``Δt`` frames, or on the whole log) and then frozen;
re-fitting is a caller's decision (``Retriever.refit``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lcv_replay.errors import RetrievalError


@dataclass(frozen=True)
class PCAModel:
    """A fitted PCA basis.

    Attributes:
        mean: ``(D,)`` float32 mean of the fitting descriptors.
        components: ``(K, D)`` float32 orthonormal principal axes, by decreasing variance.
        explained_variance: ``(K,)`` float64 variance of the fitting data along each axis.
    """

    mean: np.ndarray
    components: np.ndarray
    explained_variance: np.ndarray

    @property
    def dims(self) -> int:
        return int(self.components.shape[0])

    def transform(self, descriptors: np.ndarray) -> np.ndarray:
        """``(N, D)`` descriptors -> ``(N, K)`` float32 PCA coordinates."""
        x = np.asarray(descriptors, dtype=np.float32)
        return (x - self.mean) @ self.components.T


@dataclass(frozen=True)
class BinaryHasher:
    """PCA to ``pca.dims`` dimensions plus an ITQ rotation of the top ``code_bits`` axes.

    Attributes:
        pca: the PCA model (``K = min(pca_dims, D, N - 1)`` axes).
        rotation: ``(code_bits, code_bits)`` float32 orthogonal ITQ rotation ``R``.
        code_bits: ``N_b``, the number of bits per code.
        quantisation_loss: ``||B - V R||_F^2 / N`` on the fitting data after ITQ.
    """

    pca: PCAModel
    rotation: np.ndarray
    code_bits: int
    quantisation_loss: float

    def project(self, descriptors: np.ndarray) -> np.ndarray:
        """``(N, D)`` descriptors -> ``(N, K)`` float32 PCA vectors."""
        return self.pca.transform(_as_2d(descriptors))

    def encode(self, descriptors: np.ndarray) -> np.ndarray:
        """``(N, D)`` descriptors -> ``(N,)`` packed codes (uint32 for <= 32 bits, else uint64)."""
        return self.encode_projected(self.project(descriptors))

    def encode_projected(self, projected: np.ndarray) -> np.ndarray:
        """``(N, K)`` PCA vectors (from :meth:`project`) -> ``(N,)`` packed codes.

        Codes of more than 64 bits come as an object array of Python ints (bit ``k`` = ``1 << k``).
        """
        rotated = projected[:, : self.code_bits] @ self.rotation
        return pack_bits(rotated > 0.0) if self.code_bits <= 64 else pack_bits_wide(rotated > 0.0)


def code_dtype(code_bits: int) -> np.dtype:
    """The unsigned integer type that holds ``code_bits`` bits (uint32 up to 32 bits, else uint64)."""
    if not 1 <= code_bits <= 64:
        raise RetrievalError(f"code_bits = {code_bits} is out of range", fix="use 1..64 bits")
    return np.dtype(np.uint32) if code_bits <= 32 else np.dtype(np.uint64)


def pack_bits(bits: np.ndarray) -> np.ndarray:
    """``(N, B)`` bool -> ``(N,)`` unsigned codes with bit ``k`` set where ``bits[:, k]``."""
    bits = np.asarray(bits, dtype=bool)
    if bits.ndim != 2:
        raise RetrievalError(f"bits must be (N, B), got shape {bits.shape}")
    dtype = code_dtype(bits.shape[1])
    weights = np.left_shift(np.ones(bits.shape[1], dtype=dtype), np.arange(bits.shape[1], dtype=dtype))
    return np.bitwise_or.reduce(np.where(bits, weights, dtype.type(0)), axis=1).astype(dtype, copy=False)


def pack_bits_wide(bits: np.ndarray) -> np.ndarray:
    """``(N, B)`` bool, any ``B`` -> ``(N,)`` object array of Python ints (bit ``k`` = ``1 << k``)."""
    bits = np.asarray(bits, dtype=bool)
    words = [pack_bits(bits[:, w : w + 64]).astype(np.uint64) for w in range(0, bits.shape[1], 64)]
    out = np.empty(bits.shape[0], dtype=object)
    for i in range(bits.shape[0]):
        out[i] = sum(int(word[i]) << (64 * w) for w, word in enumerate(words))
    return out


def unpack_bits(codes: np.ndarray, code_bits: int) -> np.ndarray:
    """``(N,)`` packed codes -> ``(N, code_bits)`` bool; the inverse of :func:`pack_bits`."""
    codes = np.asarray(codes).astype(np.uint64)
    shifts = np.arange(code_bits, dtype=np.uint64)
    return ((codes[:, None] >> shifts) & np.uint64(1)).astype(bool)


def hamming_distances(codes: np.ndarray, code: int) -> np.ndarray:
    """``(N,)`` packed codes and one code -> ``(N,)`` uint8 Hamming distances (vectorised popcount)."""
    codes = np.asarray(codes)
    return np.bitwise_count(codes ^ codes.dtype.type(code))


def fit_pca(descriptors: np.ndarray, dims: int) -> PCAModel:
    """Fit PCA with at most ``dims`` axes on ``(N, D)`` descriptors.

    The number of axes is ``min(dims, D, N - 1)``: N points span at most N - 1 directions.
    Axes are sign-normalised (largest coordinate positive) so the fit is deterministic.
    """
    x = _as_2d(descriptors).astype(np.float64)
    n, d = x.shape
    if n < 2:
        raise RetrievalError(f"PCA needs at least 2 descriptors, got {n}", fix="fit on more frames")
    k = min(dims, d, n - 1)
    mean = x.mean(axis=0)
    xc = x - mean
    if n >= d:  # eigen-decomposition of the D x D covariance: cheap for long logs
        variance, vectors = np.linalg.eigh(xc.T @ xc / (n - 1))
        order = np.argsort(variance)[::-1][:k]
        components, variance = vectors[:, order].T, variance[order]
    else:  # thin SVD of the N x D data: cheap for short warm-ups
        _, singular, vt = np.linalg.svd(xc, full_matrices=False)
        components, variance = vt[:k], singular[:k] ** 2 / (n - 1)
    flip = np.sign(components[np.arange(k), np.argmax(np.abs(components), axis=1)])
    flip[flip == 0] = 1.0
    components = components * flip[:, None]
    return PCAModel(
        mean=mean.astype(np.float32),
        components=np.ascontiguousarray(components, dtype=np.float32),
        explained_variance=np.maximum(variance, 0.0),
    )


def fit_itq(projected: np.ndarray, *, iterations: int, seed: int) -> tuple[np.ndarray, float]:
    """ITQ rotation for ``(N, B)`` centred PCA coordinates.

    Returns:
        ``(R, loss)``: the ``(B, B)`` float32 orthogonal rotation and the final mean quantisation
        loss ``||sign(V R) - V R||_F^2 / N``.
    """
    v = np.asarray(projected, dtype=np.float64)
    n, b = v.shape
    rng = np.random.default_rng(seed)
    rotation, _ = np.linalg.qr(rng.standard_normal((b, b)))
    for _ in range(iterations):
        codes = np.where(v @ rotation > 0.0, 1.0, -1.0)
        u_b, _, u_a_t = np.linalg.svd(codes.T @ v)
        rotation = u_a_t.T @ u_b.T
    z = v @ rotation
    loss = float(np.sum((np.where(z > 0.0, 1.0, -1.0) - z) ** 2) / max(n, 1))
    return rotation.astype(np.float32), loss


def fit_hasher(
    descriptors: np.ndarray, *, pca_dims: int, code_bits: int, iterations: int, seed: int
) -> BinaryHasher:
    """Fit PCA (``pca_dims`` axes) and an ITQ rotation (``code_bits`` bits) on ``(N, D)`` descriptors.

    Raises:
        RetrievalError: fewer than ``code_bits + 1`` descriptors (they would span fewer than
            ``code_bits`` directions), or descriptors with fewer than ``code_bits`` dimensions.
    """
    x = _as_2d(descriptors)
    n, d = x.shape
    if d < code_bits:
        raise RetrievalError(
            f"descriptors have {d} dimensions, fewer than the {code_bits} code bits",
            fix="use fewer retrieval.code_bits or a larger descriptor",
        )
    if n < code_bits + 1:
        raise RetrievalError(
            f"fitting {code_bits}-bit codes needs at least {code_bits + 1} descriptors, got {n}",
            fix="use a longer log, fewer code bits, or a larger warm-up (retrieval.exclusion_frames)",
        )
    pca = fit_pca(x, pca_dims)
    rotation, loss = fit_itq(pca.transform(x)[:, :code_bits], iterations=iterations, seed=seed)
    return BinaryHasher(pca=pca, rotation=rotation, code_bits=code_bits, quantisation_loss=loss)


def _as_2d(descriptors: np.ndarray) -> np.ndarray:
    x = np.asarray(descriptors, dtype=np.float32)
    if x.ndim != 2:
        raise RetrievalError(f"descriptors must be an (N, D) array, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise RetrievalError("descriptors contain NaN or infinity", fix="check the descriptor backend's input")
    return x
