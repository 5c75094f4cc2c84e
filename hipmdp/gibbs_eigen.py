"""Structured algebra of the Gibbs conditionals in K's eigenbasis (DESIGN §3).

Symbols as in `hipmdp.gibbs_model` (rows r = a·D + d, instances b, features k with
feature 0 = mean dynamics, m support points); the sweep itself is in
`hipmdp.gibbs_sweep`, the public API in `hipmdp.gibbs`, the dense reference in
`hipmdp.gibbs_dense`.

Structure. K[r] = U Λ Uᵀ is eigendecomposed once per row (`prepare`). Rotating the
data and the basis values, Ỹ[r,b] = Uᵀ Y[r,b] and f̃[k,r] = Uᵀ f[k,r], leaves the
Gaussian likelihood unchanged (U is orthogonal) and makes the GP prior diagonal,
f̃[k,r,j] ~ N(0, λ_j). In these coordinates every conditional factorises over the
eigen-index j, so:

- f-block: the precision (WᵀW ⊗ I)/σ² + I ⊗ K⁻¹ is diagonal in V ⊗ U with
  WᵀW = V diag(γ) Vᵀ (k × k): variance λσ²/(γλ + σ²), O(k B m) per row;
- z-decision: (w wᵀ) ⊗ K + σ²I has eigenvalues ‖w‖²λ_j + σ² along w/‖w‖ ⊗ u_j and
  σ² elsewhere: only the projection p = wᵀẼ (m,) of the residual is needed, O(B m);
- new features: the same for each of N_w weight draws, reusing Ẽ: O(N_w B m), or
  O(N_w B m_big) when eigen-directions with tiny λ are series-summed (`new_llr`);
- w-block: inner products Σ_j f̃f̃ are rotation invariant; the precision is shared by
  all instances.

Small eigenvalues are only used as λσ²/(γλ + σ²) and λ/(γλ + σ²), never as 1/λ, except
in the f prior density of `log_joint`. Eigenvalues are floored at `EIG_FLOOR · λ_max`
(K is close to singular for dense support sets); the model sampled is then
K = U diag(max(λ, floor)) Uᵀ.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from hipmdp.gibbs_model import (
    GibbsData,
    GibbsPriors,
    check_data,
    ibp_log_prior,
    normal_logpdf,
    weight_log_prior,
)

Array = np.ndarray
EIG_FLOOR = 1e-12
#: Eigenvalues of K[r] below −PSD_TOLERANCE · its largest are not round-off: K[r]
#: is not positive semi-definite (round-off of an m × m kernel is ~ m ε λ_max).
PSD_TOLERANCE = 1e-8
_LOG_2PI = float(np.log(2.0 * np.pi))


class GibbsCache(NamedTuple):
    """Per-row eigendecomposition K[r] = U[r] diag(lam[r]) U[r]ᵀ and rotated data.

    U: (R, m, m); lam: (R, m), floored; Yt: Ỹ[r,b] = U[r]ᵀ Y[r,b], (R, B, m);
    noise: σ²[r] (R,).
    """

    U: Array
    lam: Array
    Yt: Array
    noise: Array


def prepare(data: GibbsData) -> GibbsCache:
    """Eigendecompose every K[r] once (O(R m³)) and rotate the data."""
    data = check_data(data)
    lam, U = np.linalg.eigh(data.K)
    floor = EIG_FLOOR * np.maximum(lam.max(axis=1, keepdims=True), 1e-300)
    if np.any(lam[:, -1] <= 0) or np.any(lam[:, 0] < -PSD_TOLERANCE * lam[:, -1]):
        r = int(
            np.argmax((lam[:, -1] <= 0) | (lam[:, 0] < -PSD_TOLERANCE * lam[:, -1]))
        )
        raise ValueError(
            f"GibbsData.K: every K[r] must be positive semi-definite and not zero "
            f"(a positive largest eigenvalue); K[{r}] has "
            f"eigenvalues from {lam[r, 0]:.3g} to {lam[r, -1]:.3g}"
        )
    lam = np.maximum(lam, floor)  # round-off below the floor, as in the docstring
    return GibbsCache(U, lam, data.Y @ U, data.noise)


def to_eigen(f: Array, cache: GibbsCache) -> Array:
    """f̃[k,r] = U[r]ᵀ f[k,r]; f (Kf, R, m) → (Kf, R, m)."""
    return (f.transpose(1, 0, 2) @ cache.U).transpose(1, 0, 2)


def from_eigen(ft: Array, cache: GibbsCache) -> Array:
    """f[k,r] = U[r] f̃[k,r]; inverse of `to_eigen`."""
    return (ft.transpose(1, 0, 2) @ np.swapaxes(cache.U, 1, 2)).transpose(1, 0, 2)


class FPosterior(NamedTuple):
    """f-block posterior in eigen-coordinates, for F̃ (k, m) of one row.

    mean: E[F̃] (k, m); V: eigenvectors of WᵀW (k, k); var: variances (k, m) of the
    independent coordinates G = Vᵀ F̃, i.e. cov(vec F) = (V⊗U) diag(var) (V⊗U)ᵀ.
    """

    mean: Array
    V: Array
    var: Array


def f_posterior(Yt_r: Array, W: Array, lam: Array, noise: float) -> FPosterior:
    """Posterior of F (k, m) given Ỹ_r = W F̃ + ε, F̃[i,j] ~ N(0, λ_j) a priori.

    With WᵀW = V diag(γ) Vᵀ and G = Vᵀ F̃ (DESIGN erratum E[f] = cov Wᵀ Δ / σ²):

        var[i,j] = λ_j σ² / (γ_i λ_j + σ²),
        E[G[i,j]] = var[i,j] (Vᵀ Wᵀ Ỹ_r)[i,j] / σ² = λ_j (VᵀWᵀỸ_r)[i,j] / (γ_i λ_j + σ²)

    Yt_r: (B, m); W: (B, k); lam: (m,); noise: σ². O(k B m + k³).
    """
    if W.shape[1] == 1:  # one feature: γ = ‖w‖², V = [[1]]
        gamma, V = np.array([[float(W[:, 0] @ W[:, 0])]]), np.ones((1, 1))
    else:
        gamma, V = np.linalg.eigh(W.T @ W)
        gamma = np.maximum(gamma, 0.0)[:, None]
    denom = gamma * lam + noise
    mean_g = lam / denom * (V.T @ (W.T @ Yt_r))
    return FPosterior(V @ mean_g, V, lam * noise / denom)


def w_posterior(
    z: Array, ft: Array, Yt: Array, noise: Array, mu_w: Array, sigma_w: float
) -> tuple[Array, Array]:
    """Posterior of w[1:, b], all b at once (DESIGN erratum, per-row noise).

        P = I/σ_w² + Σ_r Φ_r Φ_rᵀ / σ²[r],   Φ_r = z[1:,r] ⊙ f̃[1:,r]  (Kf−1, m)
        h_b = μ_w/σ_w² + Σ_r Φ_r (Ỹ[r,b] − f̃[0,r]) / σ²[r],   E[w_b] = P⁻¹ h_b

    P does not depend on b. z (Kf, R), ft (Kf, R, m), Yt (R, B, m), noise (R,),
    mu_w (Kf,). Returns (mean (Kf−1, B), cov (Kf−1, Kf−1)).
    """
    Phi = z[1:, :, None] * ft[1:]
    s = 1.0 / noise
    Phi_s = Phi * np.sqrt(s)[:, None]
    Kf1 = len(Phi)
    P = np.tensordot(Phi_s, Phi_s, axes=([1, 2], [1, 2])) + np.eye(Kf1) / sigma_w**2
    resid = (Yt - ft[0][:, None, :]) * s[:, None, None]  # (R, B, m)
    h = mu_w[1:, None] / sigma_w**2 + np.einsum(
        "krm,rbm->kb", Phi, resid, optimize=True
    )
    cov = np.linalg.inv(P)
    return cov @ h, 0.5 * (cov + cov.T)


SMALL = 1e-5  # γλ/σ² at most this: the direction's terms are series-summed (new_llr)


def new_llr(Et: Array, W: Array, lam: Array, noise: float) -> Array:
    """log N(Ẽ; 0, W_n W_nᵀ ⊗ Λ + σ²I) − log N(Ẽ; 0, σ²I) for each draw W_n (B, k).

    With W_nᵀW_n = V diag(γ) Vᵀ the covariance has eigenvalues γ_i λ_j + σ² along
    (W_n v_i/√γ_i) ⊗ u_j and σ² elsewhere, so with c = λ/σ², a_i = W_n v_i (B,) and
    A_ij = a_iᵀ Ẽ[:, j]:

        llr = ½ Σ_ij A_ij² c_j / (σ² (1 + γ_i c_j)) − ½ Σ_ij log(1 + γ_i c_j)

    The projection for all draws is one (n·k, B) × (B, m) product. Eigen-directions
    with x = γ_max c_j ≤ SMALL (for a smooth kernel many of them) are summed in
    closed form by the series 1/(1+x) = 1 − x + x² and log(1+x) = x − x²/2 + x³/3,
    relative error ≤ x³ ≤ 1e-15:
    Σ_j A_ij² c_j/(1+γc_j) ≈ a_iᵀ(M₁ − γ_i M₂ + γ_i² M₃)a_i, M_p = Ẽ_s diag(c_sᵖ) Ẽ_sᵀ
    (B, B), and Σ_j log(1+γc_j) ≈ γ_i S₁ − γ_i² S₂/2 + γ_i³ S₃/3, S_p = Σ c_jᵖ.
    That makes a draw O(B² + B m_big) instead of O(B m).

    Et: residual in eigen-coordinates (B, m); W: (n, B, k); lam (m,). Returns (n,).
    """
    n, B, k = W.shape
    if k == 1:
        gamma = np.einsum("nb,nb->n", W[:, :, 0], W[:, :, 0])[:, None]
        a = W  # (n, B, 1)
    else:
        gamma, V = np.linalg.eigh(np.einsum("nbk,nbl->nkl", W, W))
        gamma = np.maximum(gamma, 0.0)
        a = W @ V  # columns a_i = W v_i
    c = lam / noise
    small = c * max(float(gamma.max(initial=0.0)), 1e-300) <= SMALL
    cb = c[~small]
    # large eigenvalues: exact terms, A = aᵀẼ_big (n, k, m_big)
    A = (a.transpose(0, 2, 1).reshape(n * k, B) @ Et[:, ~small]).reshape(n, k, -1)
    Dm = gamma[:, :, None] * cb
    Dm += 1.0
    A *= A
    A *= cb / noise
    A /= Dm
    quad = A.sum(axis=(1, 2))
    np.log(Dm, out=Dm)  # log(1 + γc) vs log1p: absolute error < 1e-16 per term
    logdet = Dm.sum(axis=(1, 2))
    if small.any():  # small eigenvalues: closed-form series sums
        Es, cs = Et[:, small], c[small]
        q = [np.einsum("nbi,bc,nci->ni", a, (Es * cs**p) @ Es.T, a) for p in (1, 2, 3)]
        S = [np.sum(cs**p) for p in (1, 2, 3)]
        quad += np.sum(q[0] - gamma * q[1] + gamma**2 * q[2], axis=1) / noise
        g = gamma
        logdet += np.sum(g * S[0] - g**2 * S[1] / 2 + g**3 * S[2] / 3, axis=1)
    return 0.5 * (quad - logdet)


def z_llr(Et: Array, w: Array, lam: Array, noise: float) -> float:
    """`new_llr` for one feature with weights w (B,): the z[k,r] likelihood ratio.

    llr = ½ Σ_j p_j² λ_j / (σ² (g λ_j + σ²)) − ½ Σ_j log(1 + g λ_j/σ²),
    p = wᵀẼ (m,),  g = ‖w‖²
    """
    p = w @ Et
    g = float(w @ w)
    quad = np.sum(p * p * lam / (noise * (g * lam + noise)))
    return float(0.5 * (quad - np.sum(np.log1p(g * lam / noise))))


class EigenAlgebra:
    """The `Algebra` of `hipmdp.gibbs_sweep` in eigen-coordinates (f̃, Ỹ)."""

    def __init__(self, cache: GibbsCache):
        self.cache, self.Yc, self.noise = cache, cache.Yt, cache.noise

    def f_draw(self, r, Yr, W, *, rng):
        post = f_posterior(Yr, W, self.cache.lam[r], self.noise[r])
        eps = rng.standard_normal(post.mean.shape)
        return post.mean + post.V @ (np.sqrt(post.var) * eps)

    def z_llr(self, r, E, w):
        return z_llr(E, w, self.cache.lam[r], self.noise[r])

    def new_llr(self, r, E, W):
        return new_llr(E, W, self.cache.lam[r], self.noise[r])

    def w_draw(self, z, f, mu_w, sigma_w, *, rng):
        mean, cov = w_posterior(z, f, self.Yc, self.noise, mu_w, sigma_w)
        try:
            L = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            # cov = P⁻¹ of a near-singular P (nearly equal features, tiny noise):
            # round-off left it indefinite. Its eigen-factor, with the negative
            # round-off clipped, draws from the same Gaussian.
            d, Q = np.linalg.eigh(cov)
            if d.min() < -PSD_TOLERANCE * d.max():  # not round-off: a real error
                raise
            L = Q * np.sqrt(np.clip(d, 0.0, None))
        return mean + L @ rng.standard_normal(mean.shape)


def log_joint_eigen(
    z: Array, w: Array, ft: Array, mu_w: Array, priors: GibbsPriors, cache: GibbsCache
) -> float:
    """`log_joint` with f̃ = `to_eigen(f)` given directly (Kf, R, m)."""
    lp = 0.0
    for r in range(z.shape[1]):
        on = z[:, r]
        mean = np.einsum("kb,km->bm", w[on], ft[on, r])
        lp += normal_logpdf(cache.Yt[r], mean, cache.noise[r])
        lam = cache.lam[r]
        quad = np.sum(ft[on, r] ** 2 / lam)
        lp -= 0.5 * (quad + on.sum() * (np.sum(np.log(lam)) + lam.size * _LOG_2PI))
    lp += weight_log_prior(w, mu_w, priors)
    return lp + ibp_log_prior(z, priors.alpha)


def log_marginal_eigen(
    z: Array, w: Array, mu_w: Array, priors: GibbsPriors, cache: GibbsCache
) -> float:
    """log p(Y, z, w, μ_w) with every f marginalised:

        Σ_r log N(vec Y_r; 0, (W_r W_rᵀ) ⊗ K[r] + σ²[r] I) + priors of w, μ_w, z,

    W_r = w[z[:,r]]ᵀ (B, k_r) including feature 0 (`new_llr` with the active set).
    Unlike `log_joint`, it does not grow with the number of active f's through their
    (near-singular) prior densities, so it ranks samples with different z fairly.
    """
    lp = 0.0
    for r in range(z.shape[1]):
        W = w[z[:, r]].T[None]
        Yt = cache.Yt[r]
        lp += float(new_llr(Yt, W, cache.lam[r], cache.noise[r])[0])
        lp += normal_logpdf(Yt, 0.0, cache.noise[r])
    lp += weight_log_prior(w, mu_w, priors)
    return lp + ibp_log_prior(z, priors.alpha)
