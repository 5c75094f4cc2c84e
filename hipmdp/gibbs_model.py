"""The IBP-GP model the blocked Gibbs sampler targets: data, priors, state, prior terms.

Symbols: `r` row = one (action, dimension) prediction task, `r = a·D + d`, `R` rows;
`b` instance (`B`); `k` latent feature (`Kf` including feature 0); `m` support points
`S*`; `Y[r,b] = Δ_b(S*)` the smoothed deltas; `K[r] = K(S*,S*)`; `σ²[r]` noise.

    Y[r,b,:] = Σ_k z[k,r] · w[k,b] · f[k,r,:] + ε,   ε ~ N(0, σ²[r] I_m)
    f[k,r,:] ~ N(0, K[r]),  w[k,b] ~ N(μ_w[k], σ_w²),  μ_w[k] ~ N(0, σ_w0²)
    z[1:, :]ᵀ ~ IBP(α) with N = R customers (the rows) and dishes k = 1, 2, ...

Feature 0 is the mean dynamics: `z[0,:] = 1`, `w[0,:] = 1` always; it is not part of
the IBP (it has no μ_w; `mu_w[0]` is stored as 0 and never used).

Conventions of the state: `f[k,r]` is only defined where `z[k,r]` is on; where
`z[k,r] = 0` the value is stored as 0 (its prior integrates to one and it enters
neither the likelihood nor `log_joint`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.special import gammaln

from hipmdp.data import check_integer, is_real_number

Array = np.ndarray

_LOG_2PI = float(np.log(2.0 * np.pi))


class GibbsData(NamedTuple):
    """What the sampler fits.

    Y: smoothed deltas Δ_b(S*) per row, shape (R, B, m);
    K: GP prior covariance K(S*,S*) of f[k,r], per row, shape (R, m, m);
    noise: noise variance σ²[r], shape (R,).
    """

    Y: Array
    K: Array
    noise: Array


class GibbsPriors(NamedTuple):
    """Prior parameters.

    alpha: IBP concentration α; sigma_w: w[k,b] ~ N(μ_w[k], σ_w²);
    sigma_w0: μ_w[k] ~ N(0, σ_w0²); n_w: importance draws N_w of a new feature's
    weights; multiple_try: the new-feature step takes the current singletons'
    own weights as one of their N_w draws, which makes it exact for every N_w
    (`hipmdp.gibbs_sweep`); False: the paper's step, exact as N_w → ∞ only.
    """

    alpha: float
    sigma_w: float
    sigma_w0: float
    n_w: int
    multiple_try: bool = False


@dataclass(frozen=True)
class GibbsState:
    """One sample of the latent variables.

    z: bool (Kf, R), z[0] all True (feature 0 = mean dynamics);
    w: (Kf, B), w[0] = 1;
    f: (Kf, R, m), basis values f[k,r](S*), 0 where z[k,r] is off;
    mu_w: (Kf,), μ_w[k]; mu_w[0] = 0 is unused.
    """

    z: Array
    w: Array
    f: Array
    mu_w: Array

    @property
    def n_features(self) -> int:
        """K+: the number of IBP features, feature 0 excluded."""
        return int(self.z.shape[0] - 1)


def check_data(data: GibbsData) -> GibbsData:
    """Validate shapes and values; return float arrays. Raises ValueError."""
    Y = np.asarray(data.Y, dtype=float)
    K = np.asarray(data.K, dtype=float)
    noise = np.asarray(data.noise, dtype=float)
    if Y.ndim != 3:
        raise ValueError(f"GibbsData.Y: expected shape (R, B, m), got {Y.shape}")
    R, _, m = Y.shape
    if R < 1 or m < 1:
        raise ValueError(f"GibbsData.Y: need R >= 1 rows and m >= 1, got {Y.shape}")
    if K.shape != (R, m, m):
        raise ValueError(f"GibbsData.K: expected shape {(R, m, m)}, got {K.shape}")
    if noise.shape != (R,):
        raise ValueError(f"GibbsData.noise: expected shape {(R,)}, got {noise.shape}")
    for name, x in (("Y", Y), ("K", K), ("noise", noise)):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"GibbsData.{name}: contains non-finite values")
    if np.any(noise <= 0):
        raise ValueError("GibbsData.noise: every σ²[r] must be > 0")
    if not np.allclose(K, np.swapaxes(K, 1, 2), rtol=1e-10, atol=1e-12):
        raise ValueError("GibbsData.K: every K[r] must be symmetric")
    return GibbsData(Y, K, noise)


def check_priors(priors: GibbsPriors) -> GibbsPriors:
    """Validate prior parameters. Raises ValueError."""
    for name in ("alpha", "sigma_w", "sigma_w0"):
        v = getattr(priors, name)
        if not (is_real_number(v) and np.isfinite(v) and v > 0):  # True passed as 1
            raise ValueError(
                f"GibbsPriors.{name}: expected a finite number > 0, got {v!r}"
            )
    check_integer("GibbsPriors.n_w", priors.n_w, 1)  # 5.0 passed, then crashed
    if not isinstance(priors.multiple_try, bool | np.bool_):
        raise ValueError(
            f"GibbsPriors.multiple_try: expected a bool, got {priors.multiple_try!r}"
        )
    return priors


def check_state(state: GibbsState, R: int, B: int, m: int) -> None:
    """Validate a state against data sizes. Raises ValueError."""
    Kf = state.z.shape[0] if state.z.ndim == 2 else -1
    shapes = {
        "z": (state.z.shape, (Kf, R)),
        "w": (state.w.shape, (Kf, B)),
        "f": (state.f.shape, (Kf, R, m)),
        "mu_w": (state.mu_w.shape, (Kf,)),
    }
    for name, (got, want) in shapes.items():
        if got != want or Kf < 1:
            raise ValueError(f"GibbsState.{name}: expected shape {want}, got {got}")
    if state.z.dtype != bool or not state.z[0].all():
        raise ValueError("GibbsState.z: must be bool with z[0] all True")
    if not np.all(state.w[0] == 1.0):
        raise ValueError("GibbsState.w: w[0] must be all ones (mean dynamics)")
    for name in ("w", "f", "mu_w"):
        if not np.all(np.isfinite(getattr(state, name))):
            raise ValueError(f"GibbsState.{name}: expected finite values")


def harmonic(n: int) -> float:
    """H_n = Σ_{i=1..n} 1/i."""
    return float(np.sum(1.0 / np.arange(1, n + 1)))


def ibp_log_prior(z: Array, alpha: float) -> float:
    """log P([Z]) of the IBP, for the left-ordered-form class of Z = z[1:]ᵀ (R × K+).

        log P = K+ log α − α H_N + Σ_k [log (N−m_k)! + log (m_k−1)! − log N!]
                − Σ_h log K_h!

    (Griffiths & Ghahramani 2011, eq. 14) with N = R customers, m_k = Σ_r z[k,r],
    and K_h the number of features sharing the column history h. Feature 0 is not
    part of the IBP. z: bool (Kf, R).
    """
    Z = np.asarray(z[1:], dtype=bool)
    N = z.shape[1]
    mk = Z.sum(axis=1)
    if np.any(mk == 0):
        raise ValueError("ibp_log_prior: z has a feature used by no row")
    logp = Z.shape[0] * np.log(alpha) - alpha * harmonic(N)
    logp += float(np.sum(gammaln(N - mk + 1) + gammaln(mk) - gammaln(N + 1)))
    if Z.shape[0]:
        _, counts = np.unique(Z, axis=0, return_counts=True)
        logp -= float(np.sum(gammaln(counts + 1)))
    return float(logp)


def normal_logpdf(x: Array, mean: Array | float, var: float) -> float:
    """Σ log N(x; mean, var) over all elements."""
    d = np.asarray(x) - mean
    return float(-0.5 * (d.size * (_LOG_2PI + np.log(var)) + np.sum(d * d) / var))


def weight_log_prior(w: Array, mu_w: Array, priors: GibbsPriors) -> float:
    """Σ_{k≥1} [Σ_b log N(w[k,b]; μ_w[k], σ_w²) + log N(μ_w[k]; 0, σ_w0²)].

    w: (Kf, B); mu_w: (Kf,).
    """
    lp = normal_logpdf(w[1:], mu_w[1:, None], priors.sigma_w**2)
    return lp + normal_logpdf(mu_w[1:], 0.0, priors.sigma_w0**2)


def sample_mu_w(w: Array, priors: GibbsPriors, *, rng: np.random.Generator) -> Array:
    """Conjugate draw of μ_w[k] | w[k,:] for k ≥ 1 (DESIGN erratum, not the print).

        var = (1/σ_w0² + B/σ_w²)⁻¹,   mean = var · Σ_b w[k,b] / σ_w²

    w: (Kf, B). Returns mu_w (Kf,) with mu_w[0] = 0.
    """
    B = w.shape[1]
    var = 1.0 / (1.0 / priors.sigma_w0**2 + B / priors.sigma_w**2)
    mean = var * w[1:].sum(axis=1) / priors.sigma_w**2
    mu = np.zeros(w.shape[0])
    mu[1:] = mean + np.sqrt(var) * rng.standard_normal(w.shape[0] - 1)
    return mu


def draw_new_weights(
    n_draws: int, B: int, k_new: int, priors: GibbsPriors, *, rng: np.random.Generator
) -> tuple[Array, Array]:
    """N_w prior draws of k_new new features' (μ_w, w): μ ~ N(0, σ_w0²), w ~ N(μ, σ_w²).

    Returns (mu (n_draws, k_new), W (n_draws, B, k_new)).
    """
    mu = priors.sigma_w0 * rng.standard_normal((n_draws, k_new))
    W = mu[:, None, :] + priors.sigma_w * rng.standard_normal((n_draws, B, k_new))
    return mu, W
