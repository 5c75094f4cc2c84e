"""The structured conditionals (hipmdp.gibbs_eigen) equal the dense reference
(hipmdp.gibbs_dense) to round-off (TOL) on small random problems: f
mean/covariance, w posterior, z log-odds, new-feature likelihood ratios,
log_joint and log_marginal."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hipmdp import gibbs_dense as dense
from hipmdp import gibbs_eigen as fast
from hipmdp.gibbs import GibbsData, GibbsPriors, GibbsState, log_joint, log_marginal
from hipmdp.gibbs_model import ibp_log_prior, normal_logpdf, weight_log_prior

# Round-off, not an approximation: every comparison here factors or inverts a
# matrix σ²I + γK (or its Kronecker form WWᵀ ⊗ K + σ²I) of condition
# κ = 1 + γ_max λ_max/σ², at most ~5e3 in these problems (the near-singular
# kernel's), and a backward-stable solve is accurate to ~κ·ε ≈ 1e-12 relative.
# So TOL = 1e4·ε ≈ 2e-12, relative and absolute (never numpy's default rtol of
# 1e-7). The 1e-8 used before let new_llr's series threshold SMALL be raised
# from 1e-5 to 1e-2 (terms off by x³ ~ 1e-6) without a failure here.
TOL = 1e4 * np.finfo(float).eps


def random_problem(seed: int, R: int = 3, B: int = 3, m: int = 5, Kf: int = 4):
    """Random well-conditioned K, data Y and a state with every feature used."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(R, m, m))
    K = A @ np.swapaxes(A, 1, 2) / m + 0.3 * np.eye(m)
    Y = rng.normal(size=(R, B, m))
    noise = rng.uniform(0.1, 0.5, size=R)
    z = rng.random((Kf, R)) < 0.6
    z[0] = True
    z[np.arange(1, Kf), rng.integers(0, R, Kf - 1)] = True  # every feature used
    w = rng.normal(size=(Kf, B))
    w[0] = 1.0
    f = rng.normal(size=(Kf, R, m)) * z[:, :, None]
    mu_w = np.concatenate([[0.0], rng.normal(size=Kf - 1)])
    return GibbsData(Y, K, noise), GibbsState(z, w, f, mu_w), rng


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("k", [1, 3])
def test_f_posterior_matches_dense(seed, k):
    data, _, rng = random_problem(seed)
    cache = fast.prepare(data)
    W = rng.normal(size=(data.Y.shape[1], k))
    post = fast.f_posterior(cache.Yt[0], W, cache.lam[0], data.noise[0])
    U = cache.U[0]
    VU = np.kron(post.V, U)  # vec(F) = (V ⊗ U) vec(G), row-major
    cov = VU @ np.diag(post.var.ravel()) @ VU.T
    ref = dense.f_posterior(data.Y[0], W, data.K[0], data.noise[0])
    np.testing.assert_allclose((post.mean @ U.T).ravel(), ref.mean, rtol=TOL, atol=TOL)
    np.testing.assert_allclose(cov, ref.cov, rtol=TOL, atol=TOL)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_w_posterior_matches_dense(seed):
    data, st, rng = random_problem(seed)
    cache = fast.prepare(data)
    ft = fast.to_eigen(st.f, cache)
    mean, cov = fast.w_posterior(st.z, ft, cache.Yt, data.noise, st.mu_w, 1.3)
    ref = dense.w_posterior(st.z, st.f, data.Y, data.noise, st.mu_w, 1.3)
    np.testing.assert_allclose(mean, ref.mean, rtol=TOL, atol=TOL)
    np.testing.assert_allclose(cov, ref.cov, rtol=TOL, atol=TOL)
    # f where z is off is not part of the model (`GibbsState`): both ignore it
    junk = np.where(st.z[:, :, None], st.f, rng.normal(size=st.f.shape))
    got = fast.w_posterior(st.z, fast.to_eigen(junk, cache), cache.Yt, data.noise,
                           st.mu_w, 1.3)  # fmt: skip
    np.testing.assert_allclose(got[0], ref.mean, rtol=TOL, atol=TOL)
    np.testing.assert_allclose(got[1], ref.cov, rtol=TOL, atol=TOL)
    ref_junk = dense.w_posterior(st.z, junk, data.Y, data.noise, st.mu_w, 1.3)
    np.testing.assert_allclose(ref_junk.mean, ref.mean, rtol=TOL, atol=TOL)
    np.testing.assert_allclose(ref_junk.cov, ref.cov, rtol=TOL, atol=TOL)


def test_marginal_llr_is_the_ratio_of_two_normal_densities():
    """The dense reference itself, against scipy: log N(y; 0, (WWᵀ) ⊗ K + σ²I) −
    log N(y; 0, σ²I), both covariances written out in full."""
    from scipy.stats import multivariate_normal

    data, _, rng = random_problem(4)
    E, W, K, s2 = data.Y[0], rng.normal(size=(3, 2)), data.K[0], data.noise[0]
    y, eye = E.ravel(), np.eye(E.size)
    want = multivariate_normal(cov=np.kron(W @ W.T, K) + s2 * eye).logpdf(y)
    want -= multivariate_normal(cov=s2 * eye).logpdf(y)
    assert abs(dense.marginal_llr(E, W, K, s2) - want) < TOL * max(1.0, abs(want))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_z_log_odds_matches_dense(seed):
    data, st, rng = random_problem(seed)
    cache = fast.prepare(data)
    E = rng.normal(size=data.Y.shape[1:])
    w = 2.0 * rng.normal(size=data.Y.shape[1])
    for r in range(data.Y.shape[0]):
        llr = fast.z_llr(E @ cache.U[r], w, cache.lam[r], data.noise[r])
        got = llr + np.log(2 / (3 - 2))
        want = dense.z_log_odds(E, w, data.K[r], data.noise[r], m_minus=2, N=3)
        assert abs(got - want) < TOL * max(1.0, abs(want))


@pytest.mark.parametrize("k", [1, 2, 3])
def test_new_feature_llr_matches_dense(k):
    data, _, rng = random_problem(10 + k, B=4)
    cache = fast.prepare(data)
    E = rng.normal(size=data.Y.shape[1:])
    W = rng.normal(size=(6, data.Y.shape[1], k)) * 1.5
    got = fast.new_llr(E @ cache.U[1], W, cache.lam[1], data.noise[1])
    want = [dense.marginal_llr(E, Wn, data.K[1], data.noise[1]) for Wn in W]
    np.testing.assert_allclose(got, want, atol=TOL, rtol=TOL)


@pytest.mark.parametrize("k", [1, 2])
def test_new_feature_llr_near_singular_kernel_matches_dense(k):
    """A smooth SE kernel on 40 close points: most eigenvalues fall below SMALL and
    take the closed-form path of new_llr; it still equals the dense value."""
    rng = np.random.default_rng(20 + k)
    X = rng.uniform(-1, 1, size=(40, 2))
    K = np.exp(-0.5 * ((X[:, None] - X[None]) ** 2).sum(-1) / 1.5**2)
    data = GibbsData(rng.normal(size=(1, 3, 40)), K[None], np.array([0.05]))
    cache = fast.prepare(data)
    W = rng.normal(size=(5, 3, k))
    gmax = np.linalg.eigvalsh(np.swapaxes(W, 1, 2) @ W).max()
    n_small = np.sum(cache.lam[0] / 0.05 * gmax <= fast.SMALL)
    assert 10 <= n_small < 40  # both paths are exercised
    E = rng.normal(size=(3, 40))
    got = fast.new_llr(E @ cache.U[0], W, cache.lam[0], 0.05)
    # the dense reference with the same (floored) spectrum
    K_eff = cache.U[0] @ np.diag(cache.lam[0]) @ cache.U[0].T
    want = [dense.marginal_llr(E, Wn, K_eff, 0.05) for Wn in W]
    np.testing.assert_allclose(got, want, atol=TOL, rtol=TOL)


def _llr_without_cancellation(E, W, K, noise):
    """The dense llr of `dense.marginal_llr` written so that no two large terms
    cancel: with M = (W Wᵀ ⊗ K)/σ² = Q diag(μ) Qᵀ (a dense eigh of the full
    (B·m)² matrix) and t = Qᵀ vec(E),

        llr = ½ Σ_i [t_i² μ_i / (σ² (1 + μ_i)) − log1p(μ_i)].

    Returns (llr, Σ_i |each term|): the scale of its round-off."""
    M = np.kron(W @ W.T, K) / noise
    mu, Q = np.linalg.eigh(0.5 * (M + M.T))
    t = Q.T @ E.ravel()
    quad, logdet = t * t * mu / (noise * (1 + mu)), np.log1p(mu)
    return 0.5 * (quad.sum() - logdet.sum()), np.abs(quad).sum() + np.abs(logdet).sum()


def test_the_cancellation_free_reference_is_the_dense_llr():
    """At unit scale (no cancellation to speak of) the reference of the series
    test below is `dense.marginal_llr`, to round-off of the two log densities
    that `marginal_llr` subtracts (~ε·B·m·|log N(y; 0, σ²I)|)."""
    data, _, rng = random_problem(9, B=3)
    E, K, noise = rng.normal(size=(3, 5)), data.K[0], data.noise[0]
    for k in (1, 2):
        W = rng.normal(size=(3, k))
        want = dense.marginal_llr(E, W, K, noise)
        scale = abs(normal_logpdf(E.ravel(), 0.0, noise))
        got, _ = _llr_without_cancellation(E, W, K, noise)
        assert abs(got - want) < E.size * np.finfo(float).eps * scale


@pytest.mark.parametrize("k", [1, 2])
def test_new_feature_llr_with_every_direction_on_the_series_path_matches_dense(k):
    """K scaled so that x = γ_max λ_j/σ² ≤ 5e-6 < SMALL for every j: new_llr is
    then the series alone. The llr is then tiny (1e-6 to 1e-4) against the two
    log densities (~100) whose difference `dense.marginal_llr` takes: that
    reference's round-off is ~1e-8 of the llr, as large as what a missing
    series term changes (a tolerance of 1e-8 relative passed it by a factor
    0.85 and could not see a dropped x² or x³ term). So the reference here is
    the same dense llr summed without cancellation (`_llr_without_cancellation`,
    checked against `marginal_llr` above), and the tolerance is the round-off of
    a sum of B·m terms, B·m·ε·Σ|terms| (Higham's worst-case bound; the series'
    own truncation, ≤ x³ ~ 1e-16 of a term, is below it). A series missing
    its x² term errs by ~x² ~ 1e-11 of the terms, 1000× this tolerance; a
    first-order one by ~x, 1e8×."""
    rng = np.random.default_rng(30 + k)
    B, m, noise = 3, 6, 0.05
    A = rng.normal(size=(m, m))
    K0 = A @ A.T / m + 0.3 * np.eye(m)
    W = rng.normal(size=(5, B, k))
    gmax = np.linalg.eigvalsh(np.swapaxes(W, 1, 2) @ W).max()
    K = K0 * (0.5 * fast.SMALL * noise / (gmax * np.linalg.eigvalsh(K0).max()))
    cache = fast.prepare(GibbsData(np.zeros((1, B, m)), K[None], np.array([noise])))
    assert np.all(cache.lam[0] / noise * gmax <= fast.SMALL)  # the series path only
    E = rng.normal(size=(B, m))
    got = fast.new_llr(E @ cache.U[0], W, cache.lam[0], noise)
    want, terms = np.array([_llr_without_cancellation(E, Wn, K, noise) for Wn in W]).T
    assert np.all(np.abs(got - want) < B * m * np.finfo(float).eps * terms)


def test_the_dense_and_structured_algebras_agree_row_by_row():
    """The `Algebra` objects a sweep calls (the sweep comparison and the benchmark
    run the dense one): z_llr, and new_llr for 1, 2 and 3 new features, on every
    row, each with its own K[r] and σ²[r]. The conditionals above are checked as
    functions; this checks what the two algebras hand them."""
    data, _, rng = random_problem(7, B=4)
    fa, da = fast.EigenAlgebra(fast.prepare(data)), dense.DenseAlgebra(data)
    for r in range(data.Y.shape[0]):
        E = rng.normal(size=data.Y.shape[1:])
        Et = E @ fa.cache.U[r]
        w = rng.normal(size=data.Y.shape[1])
        want = da.z_llr(r, E, w)
        assert abs(fa.z_llr(r, Et, w) - want) < TOL * max(1.0, abs(want))
        for k in (1, 2, 3):
            W = 1.5 * rng.normal(size=(3, data.Y.shape[1], k))
            got, want = fa.new_llr(r, Et, W), da.new_llr(r, E, W)
            np.testing.assert_allclose(got, want, rtol=TOL, atol=TOL)


@pytest.mark.parametrize("seed", [0, 1])
def test_log_joint_and_marginal_match_dense(seed):
    data, st, rng = random_problem(seed)
    priors = GibbsPriors(alpha=1.7, sigma_w=1.2, sigma_w0=0.8, n_w=5)
    want = dense.dense_log_joint(st, data, priors)
    assert abs(log_joint(st, data, priors) - want) < TOL * abs(want)
    # f where z is off enters neither the likelihood nor log_joint (`GibbsState`)
    junk = np.where(st.z[:, :, None], st.f, rng.normal(size=st.f.shape))
    assert abs(
        log_joint(dataclasses.replace(st, f=junk), data, priors) - want
    ) < TOL * abs(want)
    # f marginalised: N(vec Y_r; 0, (W_r W_rᵀ) ⊗ K + σ²I), W_r incl. feature 0
    lm = sum(
        dense.mvn_logpdf(
            data.Y[r].ravel(),
            np.kron(st.w[st.z[:, r]].T @ st.w[st.z[:, r]], data.K[r])
            + data.noise[r] * np.eye(data.Y[r].size),
        )
        for r in range(data.Y.shape[0])
    )
    lm += weight_log_prior(st.w, st.mu_w, priors) + ibp_log_prior(st.z, 1.7)
    assert abs(log_marginal(st, data, priors) - lm) < TOL * abs(lm)


def test_ibp_log_prior_sums_to_one_over_classes():
    """Σ over all left-ordered binary matrices with N=2 rows, up to 3 columns, of
    P([Z]) ≈ 1 (the truncation leaves mass of K+ > 3 ~ Poisson(α H_2) tail)."""
    from itertools import combinations_with_replacement

    from scipy.stats import poisson

    alpha, N = 0.7, 2
    cols = [(1, 0), (0, 1), (1, 1)]
    total = 0.0
    for K in range(4):
        for combo in combinations_with_replacement(cols, K):
            z = np.array([(1, 1)] + list(combo), dtype=bool).reshape(K + 1, N)
            total += np.exp(ibp_log_prior(z, alpha))
    assert abs(total - poisson.cdf(3, alpha * 1.5)) < 1e-12


def test_normal_logpdf_matches_scipy():
    from scipy.stats import norm

    x = np.array([0.3, -1.2, 2.0])
    assert abs(normal_logpdf(x, 0.5, 2.0) - norm.logpdf(x, 0.5, 2**0.5).sum()) < 1e-12


def test_weight_log_prior_is_the_sum_of_normal_log_densities():
    """Σ_{k≥1} [Σ_b log N(w[k,b]; μ_w[k], σ_w²) + log N(μ_w[k]; 0, σ_w0²)], against
    scipy; feature 0 (w = 1, μ_w = 0 unused) is not part of it."""
    from scipy.stats import norm

    rng = np.random.default_rng(5)
    w = np.vstack([np.ones(4), rng.normal(size=(2, 4))])
    mu_w = np.array([0.0, 0.4, -1.1])
    priors = GibbsPriors(alpha=1.0, sigma_w=1.3, sigma_w0=0.6, n_w=5)
    want = norm.logpdf(w[1:], mu_w[1:, None], 1.3).sum()
    want += norm.logpdf(mu_w[1:], 0.0, 0.6).sum()
    assert abs(weight_log_prior(w, mu_w, priors) - want) < 1e-12 * abs(want)
    # feature 0's values do not enter
    w[0], mu_w[0] = 7.0, 3.0
    assert abs(weight_log_prior(w, mu_w, priors) - want) < 1e-12 * abs(want)


def test_ibp_log_prior_refuses_a_feature_no_row_uses():
    """Such a feature has no left-ordered class (log (m_k − 1)! of m_k = 0)."""
    z = np.array([[1, 1], [1, 0], [0, 0]], dtype=bool)
    with pytest.raises(ValueError, match="z has a feature used by no row"):
        ibp_log_prior(z, 1.0)


@pytest.mark.parametrize("k", [1, 2])
def test_new_feature_series_is_exact_to_third_order(monkeypatch, k):
    """The series path at x = γ λ_j/σ² in [4.5e-3, 9e-3] for every j (SMALL
    raised to 1e-2; every draw with γ = 1 on each of its k features): its error is
    ≤ x³ ≈ 7e-7 relative per term (1/(1+x) against 1 − x + x², log(1+x) against
    x − x²/2 + x³/3), and both sums have terms of one sign, so new_llr is within
    1e-6 relative of the dense value. At SMALL = 1e-5 the same check cannot see
    a missing x² or x³ term (~1e-10 relative and below); here such a series errs
    by x² or x²/3 ≥ 7e-6 relative. E = 0 puts the weight on the log-determinant,
    a large E on the quadratic form."""
    monkeypatch.setattr(fast, "SMALL", 1e-2)
    rng = np.random.default_rng(40 + k)
    B, m, noise = 3, 6, 0.05
    Q = np.linalg.qr(rng.normal(size=(m, m)))[0]
    K = Q @ np.diag(np.linspace(0.45, 0.9, m)) @ Q.T * (1e-2 * noise)
    K = 0.5 * (K + K.T)
    W = np.linalg.qr(rng.normal(size=(4, B, k)))[0]  # orthonormal columns: γ = 1
    cache = fast.prepare(GibbsData(np.zeros((1, B, m)), K[None], np.array([noise])))
    x = cache.lam[0] / noise
    assert np.all((4.4e-3 < x) & (x < 9.1e-3))  # the series path only
    for E in (np.zeros((B, m)), 1e3 * rng.normal(size=(B, m))):
        got = fast.new_llr(E @ cache.U[0], W, cache.lam[0], noise)
        want = [dense.marginal_llr(E, Wn, K, noise) for Wn in W]
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)
