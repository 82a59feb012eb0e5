"""PCA, ITQ and packed codes: determinism, exactness of the bit operations, short inputs."""

from __future__ import annotations

import numpy as np
import pytest

from lcv_replay.errors import RetrievalError
from lcv_replay.retrieval.hashing import (
    code_dtype,
    fit_hasher,
    fit_itq,
    fit_pca,
    hamming_distances,
    pack_bits,
    unpack_bits,
)


def _data(n: int = 300, d: int = 96, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    scales = np.linspace(3.0, 0.1, d)
    return (rng.normal(size=(n, d)) * scales + rng.normal(size=d)).astype(np.float32)


@pytest.mark.parametrize("bits", [1, 7, 20, 32, 33, 64])
def test_pack_unpack_round_trip(bits):
    rng = np.random.default_rng(bits)
    b = rng.random((50, bits)) < 0.5
    codes = pack_bits(b)
    assert codes.dtype == code_dtype(bits)
    assert np.array_equal(unpack_bits(codes, bits), b)
    assert int(codes.max()) < (1 << bits)


def test_hamming_matches_bitwise_brute_force():
    rng = np.random.default_rng(3)
    bits = rng.random((400, 20)) < 0.5
    codes = pack_bits(bits)
    for q in range(5):
        expected = (bits != bits[q]).sum(axis=1)
        assert np.array_equal(hamming_distances(codes, int(codes[q])), expected)


def test_pca_axes_are_orthonormal_sorted_and_span_the_data():
    x = _data()
    pca = fit_pca(x, 16)
    c = pca.components.astype(np.float64)
    assert pca.dims == 16
    assert np.allclose(c @ c.T, np.eye(16), atol=1e-5)
    assert np.all(np.diff(pca.explained_variance) <= 1e-9)
    # the variance along each axis is what the model says it is
    z = pca.transform(x).astype(np.float64)
    assert np.allclose(z.var(axis=0, ddof=1), pca.explained_variance, rtol=1e-3)
    # same subspace as numpy's SVD of the centred data
    _, _, vt = np.linalg.svd(x - x.mean(axis=0), full_matrices=False)
    assert np.allclose(np.abs(c @ vt[:16].T).max(axis=1), 1.0, atol=1e-4)


def test_pca_caps_dims_at_n_minus_1_and_uses_both_paths():
    x = _data(n=40, d=96)
    assert fit_pca(x, 128).dims == 39  # N - 1 when N < D (SVD path)
    assert fit_pca(_data(n=300, d=96), 128).dims == 96  # D when N > D (covariance path)


def test_fit_is_deterministic_for_a_seed_and_depends_on_it():
    x = _data()
    a = fit_hasher(x, pca_dims=64, code_bits=20, iterations=30, seed=5)
    b = fit_hasher(x.copy(), pca_dims=64, code_bits=20, iterations=30, seed=5)
    c = fit_hasher(x, pca_dims=64, code_bits=20, iterations=30, seed=6)
    assert np.array_equal(a.rotation, b.rotation)
    assert np.array_equal(a.encode(x), b.encode(x))
    assert not np.array_equal(a.rotation, c.rotation)


def test_itq_rotation_is_orthogonal_and_lowers_quantisation_loss():
    v = fit_pca(_data(), 20).transform(_data())
    r0, loss0 = fit_itq(v, iterations=0, seed=0)
    r50, loss50 = fit_itq(v, iterations=50, seed=0)
    assert np.allclose(r50.astype(np.float64) @ r50.T, np.eye(20), atol=1e-5)
    assert loss50 < loss0


def test_codes_are_sign_of_rotated_top_components():
    x = _data()
    h = fit_hasher(x, pca_dims=64, code_bits=20, iterations=10, seed=0)
    z = h.project(x)[:, :20] @ h.rotation
    assert np.array_equal(unpack_bits(h.encode(x), 20), z > 0)
    # balanced-ish bits: ITQ on centred data does not produce constant bits
    mean_bits = unpack_bits(h.encode(x), 20).mean(axis=0)
    assert np.all((mean_bits > 0.1) & (mean_bits < 0.9))


@pytest.mark.parametrize("n", [0, 1, 20])
def test_too_few_descriptors_is_a_clear_error(n):
    with pytest.raises(RetrievalError, match="needs at least 21|at least 2"):
        fit_hasher(_data(n=max(n, 1))[:n], pca_dims=128, code_bits=20, iterations=5, seed=0)


def test_bad_descriptors_are_refused():
    x = _data()
    x[3, 4] = np.nan
    with pytest.raises(RetrievalError, match="NaN"):
        fit_hasher(x, pca_dims=16, code_bits=8, iterations=1, seed=0)
    with pytest.raises(RetrievalError, match=r"\(N, D\)"):
        fit_pca(np.zeros(10), 4)
    with pytest.raises(RetrievalError, match="fewer than the 20 code bits"):
        fit_hasher(_data(d=10), pca_dims=16, code_bits=20, iterations=1, seed=0)
