"""Kernel values and analytic gradients vs the definition and finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from hipmdp.kernels import se_kernel, se_kernel_grad


def test_kernel_matches_definition():
    rng = np.random.default_rng(0)
    X1, X2 = rng.normal(size=(5, 3)), rng.normal(size=(4, 3))
    ell, sf2 = np.array([0.5, 1.0, 2.0]), 1.7
    K = se_kernel(X1, X2, ell, sf2)
    for i in range(5):
        for j in range(4):
            r2 = np.sum((X1[i] - X2[j]) ** 2 / ell**2)
            assert K[i, j] == pytest.approx(sf2 * np.exp(-0.5 * r2), rel=1e-12)


def test_kernel_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(6, 3))
    log_params = np.array([np.log(0.7), np.log(1.3), np.log(2.1), np.log(0.9)])

    def kern(p):
        return se_kernel(X, X, np.exp(p[:3]), np.exp(p[3]))

    dK = se_kernel_grad(X, np.exp(log_params[:3]), np.exp(log_params[3])).dK
    eps = 1e-6
    for i in range(4):
        e = np.zeros(4)
        e[i] = eps
        fd = (kern(log_params + e) - kern(log_params - e)) / (2 * eps)
        # central differences: error O(eps²) ~ 1e-12 plus round-off ~ 1e-16/eps
        np.testing.assert_allclose(dK[i], fd, atol=1e-8)


def test_bad_parameters_raise():
    X = np.zeros((2, 2))
    with pytest.raises(ValueError, match="lengthscales"):
        se_kernel(X, X, np.array([1.0]), 1.0)
    with pytest.raises(ValueError, match="lengthscales"):
        se_kernel(X, X, np.array([1.0, -1.0]), 1.0)
    with pytest.raises(ValueError, match="signal_var"):
        se_kernel(X, X, np.array([1.0, 1.0]), 0.0)
    with pytest.raises(ValueError, match="dimension"):
        se_kernel(X, np.zeros((2, 3)), np.array([1.0, 1.0]), 1.0)
