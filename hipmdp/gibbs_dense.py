"""Plain dense reference of every Gibbs conditional (for tests and the benchmark).

Symbols as in `hipmdp.gibbs_model`. Everything here is written as printed in DESIGN §2
(with its errata) with dense matrices of size k·m (f-block), B·m (z decisions) and
R·m (w-block): no structure is exploited. Vectors over (instance, support point) are
stacked instance-major, `y = Y_r.ravel()` for Y_r (B, m); stacked features are
feature-major, `f = F.ravel()` for F (k, m).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import linalg

from hipmdp.gibbs_model import (
    GibbsData,
    GibbsPriors,
    GibbsState,
    check_data,
    check_priors,
    ibp_log_prior,
    normal_logpdf,
    weight_log_prior,
)
from hipmdp.gibbs_sweep import sweep

Array = np.ndarray
_LOG_2PI = float(np.log(2.0 * np.pi))


class Gaussian(NamedTuple):
    """A Gaussian posterior: mean (n,) or (n, c) for c right-hand sides, cov (n, n)."""

    mean: Array
    cov: Array


def mvn_logpdf(y: Array, cov: Array) -> float:
    """log N(y; 0, cov) through a Cholesky factor; y (n,), cov (n, n)."""
    L = linalg.cholesky(cov, lower=True)
    a = linalg.solve_triangular(L, y, lower=True)
    return float(-0.5 * (y.size * _LOG_2PI + a @ a) - np.sum(np.log(np.diag(L))))


def f_posterior(Yr: Array, W: Array, K: Array, noise: float) -> Gaussian:
    """Posterior of the stacked f = vec(F) (k·m) given Y_r = W F + ε (erratum form).

        𝐊 = I_k ⊗ K,  𝐖 = W ⊗ I_m,
        cov(f) = σ² (𝐖ᵀ𝐖 + σ² 𝐊⁻¹)⁻¹,   E[f] = cov(f) 𝐖ᵀ y / σ²

    Yr: (B, m); W: (B, k) weights of the active features; K: (m, m); noise: σ².
    """
    k, m = W.shape[1], K.shape[0]
    Wb = np.kron(W, np.eye(m))
    Kinv = np.kron(np.eye(k), linalg.inv(K))
    cov = noise * linalg.inv(Wb.T @ Wb + noise * Kinv)
    cov = 0.5 * (cov + cov.T)
    return Gaussian(cov @ Wb.T @ Yr.ravel() / noise, cov)


def w_posterior(
    z: Array, f: Array, Y: Array, noise: Array, mu_w: Array, sigma_w: float
) -> Gaussian:
    """Posterior of w[1:, b] for every instance b (erratum form, per-row noise).

        cov = (F_bᵀ Σ⁻¹ F_b + I/σ_w²)⁻¹
        E[w_b] = cov (μ_w/σ_w² + F_bᵀ Σ⁻¹ (Δ_b − F_1b))

    F_b: (R·m, Kf−1), column k−1 = z[k,r] f[k,r] stacked over rows; Σ = diag(σ²[r]
    repeated m times); F_1b = f[0] stacked. z (Kf, R), f (Kf, R, m), Y (R, B, m),
    noise (R,), mu_w (Kf,). Returns mean (Kf−1, B) and cov (Kf−1, Kf−1), the same for
    every b since F_b does not depend on b.
    """
    Kf, R, m = f.shape
    F = (z[1:, :, None] * f[1:]).reshape(Kf - 1, R * m).T
    Sinv = np.repeat(1.0 / noise, m)
    cov = np.eye(Kf - 1) * sigma_w**2  # the prior, if there are no instances
    means = []
    for b in range(Y.shape[1]):
        Fb = F  # the basis values do not depend on the instance
        cov = linalg.inv(Fb.T @ (Sinv[:, None] * Fb) + np.eye(Kf - 1) / sigma_w**2)
        delta = (Y[:, b] - f[0]).ravel()
        means.append(cov @ (mu_w[1:] / sigma_w**2 + Fb.T @ (Sinv * delta)))
    mean = np.stack(means, axis=1) if means else np.zeros((Kf - 1, 0))
    return Gaussian(mean, cov)


def marginal_llr(E: Array, W: Array, K: Array, noise: float) -> float:
    """log N(y; 0, (W Wᵀ) ⊗ K + σ²I) − log N(y; 0, σ²I), y = vec(E).

    The likelihood of the residual E (B, m) with k features of weights W (B, k) on and
    their f marginalised, against all of them off. The numerator factors the dense
    (B·m)² covariance; the denominator's σ²I is diagonal, so it is a sum of B·m
    independent normal log densities (no factor needed).
    """
    y = E.ravel()
    cov = np.kron(W @ W.T, K) + noise * np.eye(y.size)
    return mvn_logpdf(y, cov) - normal_logpdf(y, 0.0, noise)


def z_log_odds(
    E: Array, w: Array, K: Array, noise: float, m_minus: int, N: int
) -> float:
    """log P(z[k,r]=1 | rest) − log P(z[k,r]=0 | rest), f[k,r] marginalised.

    E: residual of row r without feature k (B, m); w: w[k,:] (B,); m_minus: m₋ᵣ,ₖ;
    N: number of rows. = marginal_llr(E, w[:,None]) + log m₋ᵣ,ₖ − log(N − m₋ᵣ,ₖ).
    """
    return marginal_llr(E, w[:, None], K, noise) + np.log(m_minus / (N - m_minus))


class DenseAlgebra:
    """`hipmdp.gibbs_sweep.Algebra` with dense matrices in original coordinates."""

    def __init__(self, data: GibbsData):
        self.Yc, self.K, self.noise = data.Y, data.K, data.noise

    def f_draw(self, r, Yr, W, *, rng):
        post = f_posterior(Yr, W, self.K[r], self.noise[r])
        L = linalg.cholesky(post.cov, lower=True)
        draw = post.mean + L @ rng.standard_normal(post.mean.size)
        return draw.reshape(W.shape[1], -1)

    def z_llr(self, r, E, w):
        return marginal_llr(E, w[:, None], self.K[r], self.noise[r])

    def new_llr(self, r, E, W):
        return np.array([marginal_llr(E, Wn, self.K[r], self.noise[r]) for Wn in W])

    def w_draw(self, z, f, mu_w, sigma_w, *, rng):
        post = w_posterior(z, f, self.Yc, self.noise, mu_w, sigma_w)
        L = linalg.cholesky(post.cov, lower=True)
        return post.mean + L @ rng.standard_normal(post.mean.shape)


class MeanDraws:
    """Either `Algebra` with its f and w draws replaced by their posterior means,
    after taking the standard normals a draw takes (a checking device).

    The structured and the dense algebra draw f and w through different square
    roots of the same covariance, so sweeps from one state and seed differ. With
    means for draws every other random choice (z decisions, new-feature proposals
    and their acceptance, μ_w) sees the same uniforms, and whole sweeps must agree:
    z exactly, w, f and μ_w to round-off. A mean costs what a draw costs (the
    dense draw still factors its covariance). Other attributes are the algebra's.
    """

    def __init__(self, algebra) -> None:
        self.algebra = algebra

    def __getattr__(self, name):
        return getattr(self.algebra, name)

    def f_draw(self, r, Yr, W, *, rng):
        return self.algebra.f_draw(r, Yr, W, rng=_ZeroNormals(rng))

    def w_draw(self, z, f, mu_w, sigma_w, *, rng):
        return self.algebra.w_draw(z, f, mu_w, sigma_w, rng=_ZeroNormals(rng))


class _ZeroNormals:
    """In place of the Generator of a draw `mean + L ε`: ε is taken from `rng` (the
    stream advances as for the draw) and zeros of its shape are returned."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def standard_normal(self, size=None) -> Array:
        return np.zeros_like(self.rng.standard_normal(size))


def dense_gibbs_sweep(
    state: GibbsState, data: GibbsData, priors: GibbsPriors, *, rng: np.random.Generator
) -> GibbsState:
    """`hipmdp.gibbs.gibbs_sweep` with every conditional computed densely."""
    data, priors = check_data(data), check_priors(priors)
    out = sweep(
        DenseAlgebra(data), state.z, state.w, state.f, state.mu_w, priors, rng=rng
    )
    return GibbsState(*out)


def dense_log_joint(state: GibbsState, data: GibbsData, priors: GibbsPriors) -> float:
    """log p(Y, z, w, f, μ_w), dense (see `hipmdp.gibbs.log_joint`)."""
    z, w, f = state.z, state.w, state.f
    lp = 0.0
    for r in range(z.shape[1]):
        mean = np.einsum("kb,km->bm", w[z[:, r]], f[z[:, r], r])
        lp += normal_logpdf(data.Y[r], mean, data.noise[r])
        for k in np.flatnonzero(z[:, r]):
            lp += mvn_logpdf(f[k, r], data.K[r])
    lp += weight_log_prior(w, state.mu_w, priors)
    return lp + ibp_log_prior(z, priors.alpha)
