"""Gibbs steps the dense-against-structured comparisons cannot see, since both
sides run the same sweep (found by a mutation review): the z step leaves
singletons to the new-feature step, born features take f from the residual
without the old singletons, the weight draw's fallback for a singular
covariance, the eigenvalue floor, the w block with a single latent feature and
σ_w ≠ σ_w0, f = 0 wherever z is off, the removal of an unused feature, the
residual the z step hands on, the importance choice of a born feature's weights,
the skipped proposal of k' = k, and a sweep's purity; and (another review) what
`prepare` takes as round-off and floors per row, the weight fallback's
tolerance relative to its covariance, and `MeanDraws` leaving the stream where
a draw leaves it."""

from __future__ import annotations

import numpy as np
import pytest

from hipmdp import gibbs_dense as dense
from hipmdp import gibbs_eigen as fast
from hipmdp.gibbs import (
    GibbsData,
    GibbsPriors,
    GibbsState,
    gibbs_sweep,
    init_state,
    log_joint,
    prepare,
)
from hipmdp.gibbs_sweep import f_block, new_feature_step, sweep, z_step_row
from tests.test_gibbs_sampler import assert_whitened, small_problem


def test_z_step_leaves_singletons_to_the_new_feature_step():  # G11
    data, rng = small_problem(3)
    alg = fast.EigenAlgebra(prepare(data))
    z = np.array([[1, 1, 1], [1, 0, 0]], dtype=bool)
    w = np.vstack([np.ones(4), rng.normal(size=4)])
    f = rng.normal(size=(2, 3, 5)) * z[:, :, None]
    z2, f2 = z.copy(), f.copy()
    z_step_row(alg, 0, z2, w, f2, rng=rng)
    assert z2[1, 0] and np.array_equal(f2[1, 0], f[1, 0])


def test_born_features_take_f_from_the_residual_without_the_old_singletons():  # G06
    data, rng = small_problem(5)
    alg = dense.MeanDraws(fast.EigenAlgebra(prepare(data)))
    priors = GibbsPriors(alpha=6.0, sigma_w=1.0, sigma_w0=1.0, n_w=20)
    z = np.array([[1, 1, 1], [1, 0, 0]], dtype=bool)
    w = np.vstack([np.ones(4), 3 * rng.normal(size=4)])
    f = np.zeros((2, 3, 5))
    f[1, 0] = 3 * rng.normal(size=5)
    E = alg.Yc[0] - f[0, 0] - np.outer(w[1], f[1, 0])
    E0 = E + np.outer(w[1], f[1, 0])
    for seed in range(200):
        z2, w2, f2, _ = new_feature_step(
            alg, 0, E, (z, w, f, np.zeros(2)), priors, rng=np.random.default_rng(seed)
        )
        if z2.shape[0] > 2:  # the singleton was replaced by >= 2 new features
            want = fast.f_posterior(E0, w2[1:].T, alg.cache.lam[0], alg.noise[0]).mean
            np.testing.assert_allclose(f2[1:, 0], want, atol=1e-10)
            return
    pytest.fail("no birth accepted")


def test_weight_draw_fallback_with_a_non_symmetric_eigenbasis(monkeypatch):  # E09
    mean = np.array([[0.5], [-0.25], [1.0]])
    Bm = np.array([[1.0, 0.0], [1.0, 1.0], [0.0, 2.0]])
    cov = Bm @ Bm.T  # rank 2: w · n is fixed, n = b1 x b2
    n = np.cross(Bm[:, 0], Bm[:, 1])
    monkeypatch.setattr(fast, "w_posterior", lambda *a: (mean, cov))
    alg = fast.EigenAlgebra(prepare(small_problem(3)[0]))
    rng = np.random.default_rng(4)
    with pytest.raises(np.linalg.LinAlgError):  # singular: the fallback's case
        np.linalg.cholesky(cov)
    d = np.array([alg.w_draw(None, None, None, 1.0, rng=rng)[:, 0] for _ in range(500)])
    np.testing.assert_allclose(d @ n, (mean[:, 0] @ n), atol=1e-6)
    # in the rank-2 range, d - mean = Bm x with x ~ N(0, I): its coordinates
    # x = Bm⁺(d - mean) must be standard normal (pairs included), to the
    # Monte Carlo bounds of `assert_whitened`
    x = (d - mean[:, 0]) @ np.linalg.pinv(Bm).T
    assert_whitened(x, np.zeros(2), np.eye(2))


def test_eigenvalues_are_floored_for_a_singular_kernel():  # E04
    X = np.array([[0.0], [0.5], [0.5], [1.0]])  # duplicated support point
    K = np.exp(-0.5 * (X - X.T) ** 2)
    cache = prepare(GibbsData(np.zeros((1, 2, 4)), K[None], np.array([0.1])))
    assert cache.lam.min() >= fast.EIG_FLOOR * cache.lam.max() * (1 - 1e-12)


def test_weight_draw_fallback_refuses_a_covariance_that_is_truly_indefinite(
    monkeypatch,
):
    """Only round-off is clipped: an eigenvalue of -1e-5 of the largest is an
    error in the covariance, not round-off, and must not be drawn from."""
    Q = np.linalg.qr(np.random.default_rng(2).normal(size=(3, 3)))[0]
    cov = Q @ np.diag([1.0, 0.5, -1e-5]) @ Q.T
    monkeypatch.setattr(fast, "w_posterior", lambda *a: (np.zeros((3, 1)), cov))
    alg = fast.EigenAlgebra(prepare(small_problem(3)[0]))
    with pytest.raises(np.linalg.LinAlgError):
        alg.w_draw(None, None, None, 1.0, rng=np.random.default_rng(0))


def test_the_w_block_runs_with_a_single_latent_feature():
    """Kf = 2 (one latent feature, on in every row and kept there by the data):
    the sweep's w[1] is the w-block's conditional mean given the f-block's f
    (dense formula, with means for draws), with the weights' prior sd σ_w, not
    σ_w0. The block was skipped unless there were two latent features."""
    rng = np.random.default_rng(0)
    R, B, m = 3, 4, 5
    data, _ = small_problem(3, R=R, B=B, m=m)
    w_true = np.array([2.0, -1.5, 1.0, 2.5])
    f_true = rng.normal(size=(2, R, m))
    Y = f_true[0][:, None] + w_true[None, :, None] * f_true[1][:, None]
    data = GibbsData(Y + 0.05 * rng.normal(size=Y.shape), data.K, data.noise)
    alg = dense.MeanDraws(dense.DenseAlgebra(data))
    priors = GibbsPriors(alpha=0.1, sigma_w=2.0, sigma_w0=0.5, n_w=20)
    z = np.ones((2, R), dtype=bool)
    w, mu_w = np.vstack([np.ones(B), np.ones(B)]), np.array([0.0, 0.5])
    f = np.zeros((2, R, m))
    # the f-block's means do not depend on the draws the sweep takes
    f1 = f_block(alg, z, w, f, rng=np.random.default_rng(1))
    want = dense.w_posterior(z, f1, data.Y, data.noise, mu_w, priors.sigma_w).mean
    z2, w2, _, _ = sweep(alg, z, w, f, mu_w, priors, rng=np.random.default_rng(2))
    assert z2[1].all()  # feature 1 kept in every row: w2[1] is the w-block's
    np.testing.assert_allclose(w2[1], want[0], rtol=1e-10)


def test_a_sweep_leaves_f_at_0_wherever_z_is_off():
    """The state's f is 0 where z[k,r] is off (`GibbsState`): a feature the z
    step switches off in a row, while another row keeps it, has its f[k,r]
    set to 0 (it kept its last value)."""
    data, _ = small_problem(15, R=4, B=5, m=6)
    priors = GibbsPriors(alpha=2.0, sigma_w=1.0, sigma_w0=1.0, n_w=50)
    cache = prepare(data)
    rng = np.random.default_rng(16)
    state = init_state(data, priors, rng=rng)
    partial = 0  # sweeps that end with a feature on in some rows, off in others
    for _ in range(30):
        state = gibbs_sweep(state, data, priors, cache, rng=rng)
        off = ~state.z
        assert not state.f[off].any()
        partial += bool(off[1:].any())
    assert partial > 0  # the check above saw features off in some rows


def test_a_sweep_drops_a_feature_no_row_uses():
    """A state may hold a feature with z[k,:] all off (`check_state` takes it;
    the IBP prior of `log_joint` does not): the sweep's step 4 removes it."""
    data, rng = small_problem(3)
    priors = GibbsPriors(alpha=1.0, sigma_w=1.0, sigma_w0=1.0, n_w=20)
    z = np.array([[1, 1, 1], [0, 0, 0]], dtype=bool)
    state = GibbsState(
        z, np.vstack([np.ones(4), rng.normal(size=4)]), np.zeros((2, 3, 5)),
        np.array([0.0, 0.3]),
    )  # fmt: skip
    out = gibbs_sweep(state, data, priors, prepare(data), rng=rng)
    assert out.z[1:].any(axis=1).all()
    assert np.isfinite(log_joint(out, data, priors))


def test_a_kernel_is_refused_only_beyond_the_round_off_of_a_psd_matrix():
    """`prepare` floors eigenvalues down to −PSD_TOLERANCE (1e-8) of the largest as
    round-off and refuses a K[r] with one beyond. A 5 × 5 kernel's round-off is
    ~ m ε λ_max ≈ 1e-15 of λ_max: −1e-10 is round-off, −1e-6 an error in K (each
    100× from the tolerance; the existing case of −0.5 passes a far looser check)."""
    Q = np.linalg.qr(np.random.default_rng(3).normal(size=(5, 5)))[0]

    def data(smallest):
        K = Q @ np.diag([1.0, 0.5, 0.2, 0.1, smallest]) @ Q.T
        return GibbsData(np.zeros((1, 2, 5)), (0.5 * (K + K.T))[None], np.ones(1))

    cache = prepare(data(-1e-10))
    assert cache.lam.min() == fast.EIG_FLOOR * cache.lam.max()  # floored
    with pytest.raises(ValueError, match="positive semi-definite"):
        prepare(data(-1e-6))


def test_each_kernel_is_floored_at_its_own_largest_eigenvalue():
    """The floor of K[r] is EIG_FLOOR · λ_max of K[r] itself, so `prepare` is
    equivariant to scaling one row: with K[1] = 1e-8 K[0] (singular: a duplicated
    support point), row 1's eigenvalues are 1e-8 row 0's, the floored one too (a
    floor from the largest eigenvalue of all rows put it 1e4 times higher)."""
    X = np.array([[0.0], [0.5], [0.5], [1.0]])
    K = np.exp(-0.5 * (X - X.T) ** 2)
    data = GibbsData(np.zeros((2, 2, 4)), np.stack([K, 1e-8 * K]), np.ones(2))
    cache = prepare(data)
    assert cache.lam[0].min() == fast.EIG_FLOOR * cache.lam[0].max()  # floored
    np.testing.assert_allclose(cache.lam[1], 1e-8 * cache.lam[0], rtol=1e-10)


@pytest.mark.parametrize("scale", [1e8, 1e-8])
def test_weight_draw_fallback_judges_round_off_relative_to_the_covariance(
    monkeypatch, scale
):
    """What the fallback clips is round-off relative to the covariance's largest
    eigenvalue, at any scale (σ_w up to 1e4 allows covariances of 1e8): an
    eigenvalue of −5e-14 of the largest is drawn from (w₁ − w₂ fixed at the
    mean's), one of −1e-3 of the largest refused. An absolute tolerance of 1e-8
    refuses the first at scale 1e8 and draws from the second at scale 1e-8."""
    mean = np.array([[0.5], [-0.25]])
    cov = scale * np.array([[1.0, 1.0], [1.0, 1.0 - 1e-13]])  # eigenvalue −5e-14·s
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(cov)
    monkeypatch.setattr(fast, "w_posterior", lambda *args: (mean, cov))
    alg = fast.EigenAlgebra(prepare(small_problem(3)[0]))
    rng = np.random.default_rng(4)
    d = np.array([alg.w_draw(None, None, None, 1.0, rng=rng)[:, 0] for _ in range(50)])
    np.testing.assert_allclose(d[:, 0] - d[:, 1], 0.75, atol=1e-6 * np.sqrt(scale))
    assert np.std(d[:, 0]) > 0.5 * np.sqrt(scale)  # drawn, not the mean alone
    indefinite = scale * np.diag([1.0, -1e-3])
    monkeypatch.setattr(fast, "w_posterior", lambda *args: (mean, indefinite))
    with pytest.raises(np.linalg.LinAlgError):
        alg.w_draw(None, None, None, 1.0, rng=rng)


def test_mean_draws_take_the_normals_a_draw_takes():
    """`MeanDraws` returns the posterior mean of an f or w draw, and leaves the
    stream where the draw leaves it (its docstring): every later random choice
    of a sweep then sees the uniforms it would see. Each algebra, each draw."""
    data, rng = small_problem(6)
    z = np.array([[1, 1, 1], [1, 0, 1], [0, 1, 1]], dtype=bool)
    f = rng.normal(size=(3, 3, 5)) * z[:, :, None]
    mu_w = np.array([0.0, 0.3, -0.2])
    W = rng.normal(size=(4, 2))
    eig, den = fast.EigenAlgebra(prepare(data)), dense.DenseAlgebra(data)
    means = {  # the posterior means, each in its algebra's coordinates
        (eig, "f"): fast.f_posterior(eig.Yc[1], W, eig.cache.lam[1], eig.noise[1]).mean,
        (den, "f"): dense.f_posterior(den.Yc[1], W, den.K[1], den.noise[1]).mean,
        (eig, "w"): fast.w_posterior(z, f, eig.Yc, eig.noise, mu_w, 1.3)[0],
        (den, "w"): dense.w_posterior(z, f, den.Yc, den.noise, mu_w, 1.3).mean,
    }
    draws = {
        "f": lambda a, g: a.f_draw(1, a.Yc[1], W, rng=g),
        "w": lambda a, g: a.w_draw(z, f, mu_w, 1.3, rng=g),
    }
    for (alg, name), want in means.items():
        g_mean, g_draw = np.random.default_rng(7), np.random.default_rng(7)
        got = draws[name](dense.MeanDraws(alg), g_mean)
        draws[name](alg, g_draw)
        assert g_mean.random() == g_draw.random(), (type(alg).__name__, name)
        np.testing.assert_allclose(got.ravel(), want.ravel(), rtol=1e-12, atol=1e-12)


def test_the_z_step_returns_the_residual_of_the_row_it_leaves():
    """z_step_row's E is Y_r − Σ_k z[k,r] w[k] f[k,r] of the z and f it leaves,
    whether it switched the feature on, off or kept it (the new-feature step
    takes that E as it is); and a feature left on has its f[k,r] from the
    residual without its own term: with means for draws, the dense posterior
    mean of f given Y_r − f[0,r] and w[k]. Row 0 of three, feature 1 also on
    in row 1 (m₋ᵣ,ₖ = 1), started on and off, over 60 seeds."""
    data, rng = small_problem(3)
    alg = dense.MeanDraws(dense.DenseAlgebra(data))
    w = np.vstack([np.ones(4), 0.3 * rng.normal(size=4)])
    f = rng.normal(size=(2, 3, 5))
    f_on = dense.f_posterior(data.Y[0] - f[0, 0], w[1][:, None], data.K[0],
                             data.noise[0]).mean  # fmt: skip
    moves = set()
    for seed in range(60):
        z = np.array([[1, 1, 1], [seed % 2, 1, 0]], dtype=bool)
        z2, f2 = z.copy(), f * z[:, :, None]
        E = z_step_row(alg, 0, z2, w, f2, rng=np.random.default_rng(seed))
        want = data.Y[0] - sum(w[k][:, None] * f2[k, 0] for k in (0, 1) if z2[k, 0])
        np.testing.assert_allclose(E, want, atol=1e-12)
        if z2[1, 0]:
            np.testing.assert_allclose(f2[1, 0], f_on, atol=1e-10)
        moves.add((bool(z[1, 0]), bool(z2[1, 0])))
    assert len(moves) == 4  # on → off, off → on and both stays were seen


def test_a_born_feature_takes_a_weight_draw_by_its_importance_weight(monkeypatch):
    """An accepted new feature takes draw n of its N_w weight draws (its μ_w and
    w together) with probability ∝ its likelihood ratio: softmax over n of
    log N(E; 0, W_n W_nᵀ ⊗ K + σ²I) − log N(E; 0, σ²I) (the dense formula).
    Three fixed draws stand in for the prior's, each w = s_n · w_true on data
    of one feature: every ratio is > 1, so a proposal of one feature against
    none is always accepted. Frequencies within 4 standard errors; the uniform
    choice (1/3 each) errs by 20 standard errors on draw 0, the best draw
    alone by 32 on draw 2 (~1100 births)."""
    from hipmdp import gibbs_sweep

    rng = np.random.default_rng(0)
    B, m, noise = 3, 3, 0.5
    A = rng.normal(size=(m, m))
    K = A @ A.T / m + 0.3 * np.eye(m)
    w_true = np.array([1.2, -0.8, 0.4])
    f_true = np.linalg.cholesky(K) @ rng.normal(size=m)
    Y = np.outer(w_true, f_true) + np.sqrt(noise) * rng.normal(size=(B, m))
    W = np.array([0.2, 0.6, 1.0])[:, None, None] * w_true[None, :, None]
    mu = np.array([[-0.5], [0.25], [0.75]])
    llr = np.array([dense.marginal_llr(Y, Wn, K, noise) for Wn in W])
    p = np.exp(llr) / np.exp(llr).sum()
    assert np.all(llr > 0) and 0.1 < p.min() and p.max() < 0.6  # informative

    def fixed_draws(n_draws, B_, k, priors, *, rng):
        assert (n_draws, B_) == (3, B)
        return np.tile(mu, (1, k)), np.tile(W, (1, 1, k))

    monkeypatch.setattr(gibbs_sweep, "draw_new_weights", fixed_draws)
    alg = fast.EigenAlgebra(prepare(GibbsData(Y[None], K[None], np.array([noise]))))
    priors = GibbsPriors(alpha=1.0, sigma_w=1.0, sigma_w0=1.0, n_w=3)
    empty = (np.ones((1, 1), bool), np.ones((1, B)), np.zeros((1, 1, m)), np.zeros(1))
    rng = np.random.default_rng(1)
    chosen = []
    for _ in range(3000):
        z, w, _, mu_w = new_feature_step(alg, 0, alg.Yc[0], empty, priors, rng=rng)
        if z.shape[0] == 2:  # one feature born
            n = int(np.flatnonzero(np.all(np.isclose(W[:, :, 0], w[1]), axis=1))[0])
            assert mu_w[1] == mu[n, 0]  # its μ_w is the same draw's
            chosen.append(n)
    freq = np.bincount(chosen, minlength=3) / len(chosen)
    assert np.all(np.abs(freq - p) < 4 * np.sqrt(p * (1 - p) / len(chosen)))


def test_a_proposal_of_as_many_features_as_the_row_has_singletons_is_skipped():
    """k' = k leaves the row's singleton as it is (its w, f and μ_w: redrawing
    the weights is the w-block's job); so does a rejected k' ≠ k. So whenever
    the step ends with the row's one singleton count unchanged, the state is
    the one it was given. α/N = 1: k' = 1 in ~37% of the steps."""
    data, rng = small_problem(3)
    alg = fast.EigenAlgebra(prepare(data))
    priors = GibbsPriors(alpha=3.0, sigma_w=1.0, sigma_w0=1.0, n_w=20)
    z = np.array([[1, 1, 1], [1, 0, 0]], dtype=bool)
    w = np.vstack([np.ones(4), rng.normal(size=4)])
    f = rng.normal(size=(2, 3, 5)) * z[:, :, None]
    mu_w = np.array([0.0, 0.4])
    E = alg.Yc[0] - f[0, 0] - np.outer(w[1], f[1, 0])
    same = 0
    for seed in range(100):
        out = new_feature_step(
            alg, 0, E, (z, w, f, mu_w), priors, rng=np.random.default_rng(seed)
        )
        if out[0].shape[0] == 2:
            same += 1
            for got, was in zip(out, (z, w, f, mu_w), strict=True):
                np.testing.assert_array_equal(got, was)
    assert same > 20


def test_a_sweep_leaves_the_state_it_is_given_unchanged():
    """`gibbs_sweep` is pure: the arrays of the state it is given are as they were
    after it returns (the z step works on the row's z in place: on the caller's
    z, a kept reference to an earlier sample changed under it), over sweeps
    whose z changes (checked)."""
    data, _ = small_problem(15, R=4, B=5, m=6)
    priors = GibbsPriors(alpha=2.0, sigma_w=1.0, sigma_w0=1.0, n_w=50)
    cache = prepare(data)
    rng = np.random.default_rng(16)
    state = init_state(data, priors, rng=rng)
    moved = 0
    for _ in range(10):
        before = {k: getattr(state, k).copy() for k in ("z", "w", "f", "mu_w")}
        new = gibbs_sweep(state, data, priors, cache, rng=rng)
        for name, was in before.items():
            np.testing.assert_array_equal(getattr(state, name), was)
        moved += new.z.shape != state.z.shape or not np.array_equal(new.z, state.z)
        state = new
    assert moved > 0
