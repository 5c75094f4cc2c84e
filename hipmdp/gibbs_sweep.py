"""One blocked Gibbs sweep, written once over an `Algebra` (fast eigenbasis or dense).

Symbols as in `hipmdp.gibbs_model`: rows `r` (R = A·D), instances `b`, features `k`
(feature 0 = mean dynamics), support points `m`.

A sweep, in order:
  1. f-block: for each row r, f[active,r] | z, w, Y  (Gaussian over stacked features).
  2. w-block: w[1:, b] | z, f, μ_w  for every instance (pools all rows, own σ²[r]).
  3. per row r: z[k,r] for existing features with f[k,r] marginalised, then the
     new-feature Metropolis–Hastings step for the row's singletons.
  4. features used by no row are removed.
  5. μ_w[k] | w[k,:]  (conjugate).

IBP bookkeeping. The IBP's customers are the N = R rows, its dishes the features
k ≥ 1; feature 0 is fixed (`z[0,:] = 1`) and takes no part. For row r and a feature
used by m₋ᵣ,ₖ > 0 *other* rows, the prior is P(z[k,r] = 1 | z[k,-r]) = m₋ᵣ,ₖ / N
(Griffiths & Ghahramani 2011), so the log-odds are

    log P(Y | z=1, f[k,r] marginalised) − log P(Y | z=0) + log m₋ᵣ,ₖ − log(N − m₋ᵣ,ₖ).

Features with m₋ᵣ,ₖ = 0 (the row's *singletons*) have prior probability 0 of being
switched on in this way; under the IBP their number given everything else is
Poisson(α/N). They are resampled jointly by an independence Metropolis–Hastings move:
propose k' ~ Poisson(α/N) features (their μ_w, w drawn from the prior, f marginalised)
in place of the current k singletons and accept with probability

    min(1, L̂(k') / L̂(k)),  L̂(j) = (1/N_w) Σ_{n=1..N_w} P(Y_r | j new features with
                                       weights W_n, f marginalised) / P(Y_r | none),

the paper's N_w-draw estimate of the marginal likelihood with w integrated out
(L̂(0) = 1). An accepted proposal takes one of its N_w weight draws chosen with
probability ∝ its likelihood (importance resampling), and its f from the f-block
conditional. A proposal of k' = k is skipped (it would only redraw the weights, which
the w-block does). With no data every likelihood ratio is 1, every proposal is
accepted, and the step draws the singleton count exactly from Poisson(α/N): the chain
then targets the IBP prior, E[K+] = α H_N. With data the step is exact as N_w → ∞.

`GibbsPriors(multiple_try=True)` makes it exact for every N_w, at the same cost:
L̂(k) of the current singletons is taken over their own weights w and N_w − 1
fresh prior draws, instead of N_w fresh ones. The move is then independent
multiple-try Metropolis (Liu, Liang & Wong 2000; Martino & Read 2013) with the
prior draws of (μ_w, w) as tries and the likelihood ratios (which depend on w
alone) as their importance weights, which leaves p(k, μ_w, w | rest) with f
marginalised unchanged, for N_w = 1 too; f is drawn from its conditional after an
accepted move, as above, and kept after a rejected one. With fresh draws both estimates
are unbiased but their ratio is not, and the chain's law depends on N_w (a test
measures it: `tests/test_gibbs_sampler.py`).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from scipy.special import expit

from hipmdp.gibbs_model import GibbsPriors, draw_new_weights, sample_mu_w

Array = np.ndarray


class Algebra(Protocol):
    """The linear algebra of the conditionals, in its own coordinates for `f` and `Y`.

    Yc: data Y in these coordinates (R, B, m); noise: σ²[r] (R,).
    """

    Yc: Array
    noise: Array

    def f_draw(self, r: int, Yr: Array, W: Array, *, rng: np.random.Generator) -> Array:
        """Draw F (k, m) | Yr (B, m) = W F + ε, W (B, k), F rows ~ N(0, K[r])."""
        ...

    def z_llr(self, r: int, E: Array, w: Array) -> float:
        """log N(E; 0, w wᵀ ⊗ K[r] + σ²I) − log N(E; 0, σ²I); E (B, m), w (B,)."""
        ...

    def new_llr(self, r: int, E: Array, W: Array) -> Array:
        """As z_llr for each draw W[n] (B, k) of k features: W (n, B, k) → (n,)."""
        ...

    def w_draw(self, z: Array, f: Array, mu_w: Array, sigma_w: float, *, rng) -> Array:
        """Draw w[1:] (Kf-1, B) | z, f, μ_w."""
        ...


def residual(Yr: Array, z_r: Array, w: Array, f_r: Array) -> Array:
    """E = Y_r − Σ_k z[k,r] w[k] ⊗ f[k,r].

    Yr (B, m), z_r (Kf,) bool, w (Kf, B), f_r (Kf, m). Returns E (B, m).
    """
    return Yr - np.einsum("kb,km->bm", w[z_r], f_r[z_r])


def f_block(alg: Algebra, z: Array, w: Array, f: Array, *, rng) -> Array:
    """f[active, r] | z, w, Y for every row. z (Kf, R), w (Kf, B), f (Kf, R, m)."""
    f = np.zeros_like(f)
    for r in range(z.shape[1]):
        on = z[:, r]
        f[on, r] = alg.f_draw(r, alg.Yc[r], w[on].T, rng=rng)
    return f


def z_step_row(alg: Algebra, r: int, z: Array, w: Array, f: Array, *, rng) -> Array:
    """z[k,r] | rest for features k ≥ 1 used by another row (f[k,r] marginalised).

    Updates z and f in place (f[k,r] drawn from its conditional when switched or
    left on, set to 0 when off); returns the row's residual E (B, m) afterwards.
    """
    N = z.shape[1]
    E = residual(alg.Yc[r], z[:, r], w, f[:, r])
    for k in range(1, z.shape[0]):
        m_minus = int(z[k].sum() - z[k, r])
        if m_minus == 0:
            continue  # singleton (or unused): handled by new_feature_step
        Ek = E + w[k][:, None] * f[k, r] if z[k, r] else E
        log_odds = alg.z_llr(r, Ek, w[k]) + np.log(m_minus) - np.log(N - m_minus)
        z[k, r] = rng.random() < expit(log_odds)
        if z[k, r]:
            f[k, r] = alg.f_draw(r, Ek, w[k][:, None], rng=rng)[0]
            E = Ek - w[k][:, None] * f[k, r]
        else:
            f[k, r] = 0.0
            E = Ek
    return E


def logsumexp(x: Array) -> float:
    """log Σ exp(x) for a 1-d array x, stably."""
    top = float(np.max(x))
    return top + float(np.log(np.sum(np.exp(x - top))))


def softmax(x: Array) -> Array:
    """exp(x) / Σ exp(x) for a 1-d array x, summing to 1 to round-off whatever
    the scale of x. (``exp(x - logsumexp(x))`` does not: at |x| ~ 1e13, as a
    new feature's log-likelihood ratios reach on noise-free data, the
    subtraction loses ~1e-3 and the weights summed to 1 ± 1e-3, which
    ``rng.choice`` refuses.)"""
    p = np.exp(x - np.max(x))
    return p / p.sum()


def _log_ml(
    alg: Algebra, r: int, E: Array, k: int, priors: GibbsPriors, *, rng, current=None
):
    """log L̂(k), the N_w-draw estimate, with its draws (mu, W) and per-draw llr.
    ``current`` (B, k): weights taken as the first of the N_w draws, beside
    N_w − 1 drawn (the multiple-try step; mu then holds the drawn ones' only)."""
    drawn = priors.n_w - (current is not None)
    mu, W = draw_new_weights(drawn, E.shape[0], k, priors, rng=rng)
    if current is not None:
        W = np.concatenate([current[None], W])
    llr = alg.new_llr(r, E, W) if k else np.zeros(priors.n_w)
    return logsumexp(llr) - float(np.log(priors.n_w)), mu, W, llr


def new_feature_step(
    alg: Algebra, r: int, E: Array, state: tuple, priors: GibbsPriors, *, rng
) -> tuple:
    """Metropolis–Hastings move on row r's singleton features (module docstring).

    E: residual of row r (B, m) with every current feature on; state: (z, w, f, mu_w).
    Returns the new (z, w, f, mu_w) (arrays may change size).
    """
    z, w, f, mu_w = state
    N = z.shape[1]
    single = [k for k in range(1, z.shape[0]) if z[k, r] and z[k].sum() == 1]
    k_new = int(rng.poisson(priors.alpha / N))
    if k_new == len(single):
        return z, w, f, mu_w
    E0 = E + np.einsum("kb,km->bm", w[single], f[single, r])
    current = w[single].T if priors.multiple_try and single else None
    log_old = _log_ml(alg, r, E0, len(single), priors, rng=rng, current=current)[0]
    log_new, mu, W, llr = _log_ml(alg, r, E0, k_new, priors, rng=rng)
    if np.log(rng.random()) >= log_new - log_old:
        return z, w, f, mu_w
    keep = np.setdiff1d(np.arange(z.shape[0]), single)
    z, w, f, mu_w = z[keep], w[keep], f[keep], mu_w[keep]
    if k_new == 0:
        return z, w, f, mu_w
    n = int(rng.choice(priors.n_w, p=softmax(llr)))  # importance resampling
    z_add = np.zeros((k_new, N), dtype=bool)
    z_add[:, r] = True
    f_add = np.zeros((k_new,) + f.shape[1:])
    f_add[:, r] = alg.f_draw(r, E0, W[n], rng=rng)
    return (
        np.concatenate([z, z_add]),
        np.concatenate([w, W[n].T]),
        np.concatenate([f, f_add]),
        np.concatenate([mu_w, mu[n]]),
    )


def remove_unused(z: Array, w: Array, f: Array, mu_w: Array) -> tuple:
    """Drop features k ≥ 1 with z[k,:] all off."""
    keep = z.any(axis=1)
    keep[0] = True
    return z[keep], w[keep], f[keep], mu_w[keep]


def sweep(
    alg: Algebra, z: Array, w: Array, f: Array, mu_w: Array, priors: GibbsPriors, *, rng
) -> tuple:
    """One full sweep (module docstring) in the algebra's coordinates.

    z (Kf, R) bool, w (Kf, B), f (Kf, R, m), mu_w (Kf,); inputs are not modified.
    Returns the new (z, w, f, mu_w).
    """
    z = z.copy()
    w = w.copy()
    mu_w = mu_w.copy()
    f = f_block(alg, z, w, f, rng=rng)
    if z.shape[0] > 1:
        w[1:] = alg.w_draw(z, f, mu_w, priors.sigma_w, rng=rng)
    for r in range(z.shape[1]):
        E = z_step_row(alg, r, z, w, f, rng=rng)
        z, w, f, mu_w = new_feature_step(alg, r, E, (z, w, f, mu_w), priors, rng=rng)
    z, w, f, mu_w = remove_unused(z, w, f, mu_w)
    mu_w = sample_mu_w(w, priors, rng=rng)
    return z, w, f, mu_w
