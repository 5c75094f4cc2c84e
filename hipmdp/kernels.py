"""Anisotropic squared-exponential kernel with analytic gradients.

Symbols: `x, x'` states of dimension `D`; `ℓ` length scales, shape (D,); `σ_f²` signal
variance; `σ_n²` noise variance (added by the GP, not by the kernel).

    k(x, x') = σ_f² exp(-½ Σ_j (x_j - x'_j)² / ℓ_j²)

Hyperparameters are optimised on the log scale, `θ = (log ℓ_1..log ℓ_D, log σ_f²,
log σ_n²)`, so every gradient here is with respect to log-parameters.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

Array = np.ndarray


class KernelGrad(NamedTuple):
    """Kernel matrix and its derivatives with respect to the log-parameters.

    K: k(X, X), shape (n, n).
    dK: ∂K/∂θ_i for θ = (log ℓ_1..log ℓ_D, log σ_f²), shape (D + 1, n, n).
    """

    K: Array
    dK: Array


def _check_params(lengthscales: Array, signal_var: float, dim: int) -> Array:
    ell = np.asarray(lengthscales, dtype=float)
    if ell.shape != (dim,):
        raise ValueError(f"lengthscales: expected shape ({dim},), got {ell.shape}")
    if not np.all(np.isfinite(ell)) or np.any(ell <= 0):
        raise ValueError(f"lengthscales: expected finite positive values, got {ell}")
    if not np.isfinite(signal_var) or signal_var <= 0:
        raise ValueError(f"signal_var: expected finite positive, got {signal_var}")
    return ell


def scaled_sqdist(X1: Array, X2: Array, lengthscales: Array) -> Array:
    """Squared distance after scaling by the length scales.

        r²(x, x') = Σ_j (x_j - x'_j)² / ℓ_j²

    X1: (n1, D); X2: (n2, D); lengthscales: ℓ, (D,). Returns (n1, n2), clipped at 0
    (the expanded form |a|² + |b|² - 2 a·b can go slightly negative by round-off).
    """
    A = X1 / lengthscales
    Bm = X2 / lengthscales
    d2 = (A * A).sum(1)[:, None] + (Bm * Bm).sum(1)[None, :] - 2.0 * (A @ Bm.T)
    return np.maximum(d2, 0.0)


def se_kernel(X1: Array, X2: Array, lengthscales: Array, signal_var: float) -> Array:
    """Cross-covariance `k(X1, X2) = σ_f² exp(-½ r²)`.

    X1: (n1, D); X2: (n2, D); lengthscales: ℓ, (D,); signal_var: σ_f².
    Returns shape (n1, n2).
    """
    X1 = np.atleast_2d(np.asarray(X1, dtype=float))
    X2 = np.atleast_2d(np.asarray(X2, dtype=float))
    if X1.shape[1] != X2.shape[1]:
        raise ValueError(
            f"X1 and X2: expected the same dimension, got {X1.shape[1]} and "
            f"{X2.shape[1]}"
        )
    ell = _check_params(lengthscales, signal_var, X1.shape[1])
    return signal_var * np.exp(-0.5 * scaled_sqdist(X1, X2, ell))


def se_kernel_grad(X: Array, lengthscales: Array, signal_var: float) -> KernelGrad:
    """k(X, X) and its gradient with respect to (log ℓ, log σ_f²).

        ∂K/∂log ℓ_j = K ⊙ (x_j - x'_j)² / ℓ_j²
        ∂K/∂log σ_f² = K

    X: (n, D). Returns KernelGrad with K (n, n) and dK (D + 1, n, n).
    """
    X = np.atleast_2d(np.asarray(X, dtype=float))
    n, D = X.shape
    ell = _check_params(lengthscales, signal_var, D)
    K = signal_var * np.exp(-0.5 * scaled_sqdist(X, X, ell))
    dK = np.empty((D + 1, n, n))
    Xs = X / ell
    for j in range(D):
        diff = Xs[:, j, None] - Xs[None, :, j]
        dK[j] = K * diff * diff
    dK[D] = K
    return KernelGrad(K=K, dK=dK)
