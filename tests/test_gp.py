"""GP marginal likelihood, its gradient, hyperparameter recovery and prediction."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from hipmdp import gp
from hipmdp.gp import (
    GPHyper,
    HyperSet,
    condition,
    fit_hyperparameters,
    neg_log_marginal_likelihood,
)
from hipmdp.kernels import se_kernel


def _sample_gp(X, hyper, rng):
    K = se_kernel(X, X, hyper.lengthscales, hyper.signal_var)
    K += hyper.noise_var * np.eye(len(X))
    return np.linalg.cholesky(K) @ rng.normal(size=len(X))


def test_nlml_matches_dense_gaussian_density():
    rng = np.random.default_rng(0)
    X, y = rng.normal(size=(7, 2)), rng.normal(size=7)
    h = GPHyper(np.array([0.8, 1.5]), 1.2, 0.1)
    C = se_kernel(X, X, h.lengthscales, h.signal_var) + h.noise_var * np.eye(7)
    dense = 0.5 * y @ np.linalg.solve(C, y) + 0.5 * np.linalg.slogdet(C)[1]
    dense += 3.5 * np.log(2 * np.pi)
    assert neg_log_marginal_likelihood(h.to_theta(), [(X, y)]).value == pytest.approx(
        dense, rel=1e-12
    )


def test_nlml_of_instances_is_the_sum_of_their_dense_densities():
    """Instances are independent GPs sharing θ: over groups of different sizes
    the value is the sum of each group's -log N(y_b; 0, C_b) (scipy's density),
    and the gradient the sum of each group's."""
    from scipy import stats

    rng = np.random.default_rng(5)
    groups = [(rng.normal(size=(n, 2)), rng.normal(size=n)) for n in (4, 7, 5)]
    h = GPHyper(np.array([0.8, 1.5]), 1.2, 0.1)
    dense = 0.0
    for X, y in groups:
        C = se_kernel(X, X, h.lengthscales, h.signal_var) + h.noise_var * np.eye(len(y))
        dense -= stats.multivariate_normal(np.zeros(len(y)), C).logpdf(y)
    nlml = neg_log_marginal_likelihood(h.to_theta(), groups)
    assert nlml.value == pytest.approx(dense, rel=1e-10)
    each = [neg_log_marginal_likelihood(h.to_theta(), [g]).grad for g in groups]
    np.testing.assert_allclose(nlml.grad, np.sum(each, axis=0), rtol=1e-12)


def test_nlml_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    groups = [(rng.normal(size=(8, 3)), rng.normal(size=8)) for _ in range(2)]
    theta = np.array([0.1, -0.3, 0.4, 0.2, -1.5])
    grad = neg_log_marginal_likelihood(theta, groups).grad
    eps = 1e-6
    for i in range(len(theta)):
        e = np.zeros_like(theta)
        e[i] = eps
        fd = (
            neg_log_marginal_likelihood(theta + e, groups).value
            - neg_log_marginal_likelihood(theta - e, groups).value
        ) / (2 * eps)
        # central differences on an O(10) function: truncation O(eps²), round-off
        # ~1e-15 * 10 / eps ~ 1e-8
        assert grad[i] == pytest.approx(fd, abs=1e-6)


def test_fit_recovers_known_length_scales():
    # 3 instances x 150 points of a GP with ℓ = (0.5, 2.0), σ_f² = 1, σ_n² = 0.01.
    # The ML estimate's standard errors (in θ = log parameters) come from the
    # observed information, the Hessian of the NLML at the optimum (central
    # differences of its analytic gradient); each estimate must be within 4 of
    # them. Swapping the two length scales (a factor 4) or ignoring the data
    # (start ℓ = std(X) ≈ 1.15) is many standard errors off.
    rng = np.random.default_rng(2)
    true = GPHyper(np.array([0.5, 2.0]), 1.0, 0.01)
    groups = []
    for _ in range(3):
        X = rng.uniform(-2, 2, size=(150, 2))
        groups.append((X, _sample_gp(X, true, rng)))
    fit = fit_hyperparameters(groups)
    theta = fit.to_theta()
    eps = 1e-4
    hessian = np.array(
        [
            (
                neg_log_marginal_likelihood(theta + eps * e, groups).grad
                - neg_log_marginal_likelihood(theta - eps * e, groups).grad
            )
            / (2 * eps)
            for e in np.eye(len(theta))
        ]
    )
    se = np.sqrt(np.diag(np.linalg.inv(0.5 * (hessian + hessian.T))))
    assert np.all(np.abs(theta - true.to_theta()) < 4 * se)
    # the standard errors are small next to the alternatives above
    assert np.all(np.abs(np.log(4.0)) > 4 * se[:2])


def test_prediction_matches_dense_formula():
    rng = np.random.default_rng(3)
    X, y, Xs = rng.normal(size=(10, 2)), rng.normal(size=10), rng.normal(size=(4, 2))
    h = GPHyper(np.array([0.9, 1.1]), 1.3, 0.05)
    mean, var = condition(X, y, h).predict(Xs, include_noise=True)
    C = se_kernel(X, X, h.lengthscales, h.signal_var) + h.noise_var * np.eye(10)
    Ks = se_kernel(Xs, X, h.lengthscales, h.signal_var)
    np.testing.assert_allclose(mean, Ks @ np.linalg.solve(C, y), atol=1e-10)
    dense_var = h.signal_var + h.noise_var - np.diag(Ks @ np.linalg.solve(C, Ks.T))
    np.testing.assert_allclose(var, dense_var, atol=1e-10)
    # without the noise (the default): the latent function's variance
    mean_f, var_f = condition(X, y, h).predict(Xs)
    np.testing.assert_array_equal(mean_f, mean)
    np.testing.assert_allclose(var_f, dense_var - h.noise_var, atol=1e-10)
    # y as a column gave (4, 1) means, which broadcast silently against (4,)
    with pytest.raises(ValueError, match=r"y: expected shape \(n,\), got \(10, 1\)"):
        condition(X, y[:, None], h)
    # NaN failed inside scipy ("array must not contain infs or NaNs"), σ_n² = -5
    # as a LinAlgError
    for args, match in [
        ((X, y * np.nan, h), "y: expected finite values"),
        ((X * np.inf, y, h), "X: expected finite values"),
        ((X, y, h._replace(noise_var=-5.0)), "hyper.noise_var: expected a finite"),
        ((X, y, h._replace(noise_var=np.nan)), "hyper.noise_var: expected a finite"),
        ((X, y[:9], h), "X and y: expected the same length, got 10 and 9"),
        # n points of one dimension as a 1-D X read as one point of dimension n
        ((X[:, 0], y, h), r"got 1 and 10 \(a 1-D X is one point of dimension 10;"),
    ]:
        with pytest.raises(ValueError, match=match):
            condition(*args)


def test_periodic_nlml_gradient_matches_finite_differences():
    rng = np.random.default_rng(4)
    groups = [(rng.uniform(-4, 4, size=(8, 3)), rng.normal(size=8)) for _ in range(2)]
    theta = np.array([0.1, -0.3, 0.4, 0.2, -1.5])
    grad = neg_log_marginal_likelihood(theta, groups, (0, 2)).grad
    assert not np.allclose(grad, neg_log_marginal_likelihood(theta, groups).grad)
    eps = 1e-6
    for i in range(len(theta)):
        e = np.zeros_like(theta)
        e[i] = eps
        fd = (
            neg_log_marginal_likelihood(theta + e, groups, (0, 2)).value
            - neg_log_marginal_likelihood(theta - e, groups, (0, 2)).value
        ) / (2 * eps)
        assert grad[i] == pytest.approx(fd, abs=1e-6)


def test_periodic_gp_interpolates_across_the_wrap():
    # A periodic function observed on θ in (-π, 2]: at θ in [2.4, 3.1] the periodic
    # GP has data 0.04-0.9 rad away across θ = ±π, the plain GP only 0.4-1.1 rad
    # behind it. Each with its own fitted hyperparameters. Judged by the periodic
    # GP's own predictive sd: it is right within 4 sd at every test point, and
    # the plain GP's mean lies outside that band at every one.
    rng = np.random.default_rng(7)
    X = rng.uniform(-np.pi, 2.0, size=(60, 1))

    def f(t):
        return np.sin(t[:, 0]) + 0.5 * np.cos(2 * t[:, 0])

    y = f(X) + 0.01 * rng.normal(size=60)
    Xs = np.linspace(2.4, 3.1, 8)[:, None]
    err, sd = {}, {}
    for periodic in ((), (0,)):
        h = fit_hyperparameters([(X, y)], periodic)
        assert h.periodic == periodic
        mean, var = condition(X, y, h).predict(Xs)
        err[periodic], sd[periodic] = np.abs(mean - f(Xs)), np.sqrt(var)
    assert np.all(err[(0,)] < 4 * sd[(0,)])
    assert np.all(err[()] > 4 * sd[(0,)])
    assert np.all(sd[(0,)] < sd[()])  # it knows it has data across the wrap


@pytest.mark.parametrize(("n_subsample", "per_instance"), [(40, 10), (5, 2)])
def test_hyper_set_fits_each_action_on_at_most_n_subsample_transitions(
    monkeypatch, n_subsample, per_instance
):
    """n_subsample is split across the B instances (n_subsample // B each, at
    least 2: 5 // 4 = 1 point per instance has no length scale to fit), each
    action's groups are that action's transitions of one instance, and every
    (a, d) is fitted on them with the periodic dimensions, which the HyperSet
    keeps."""
    rng = np.random.default_rng(0)
    n, D, A, B = 600, 2, 2, 4
    states = rng.normal(size=(n, D))
    actions = rng.integers(A, size=n)
    instances = np.repeat(np.arange(B), n // B)
    deltas = rng.normal(size=(n, D))
    calls = []

    def record(groups, periodic):
        calls.append([(x.copy(), y.copy()) for x, y in groups])
        assert periodic == (1,)
        return np.ones(3)

    monkeypatch.setattr(gp, "fit_hyperparameters", record)
    hyper = gp.fit_hyper_set(states, actions, deltas, instances, A,
                             n_subsample=n_subsample, rng=np.random.default_rng(1),
                             periodic=(1,))  # fmt: skip
    assert hyper.periodic == (1,)
    assert len(calls) == A * D
    for k, groups in enumerate(calls):
        a, d = divmod(k, D)
        assert len(groups) == B and all(len(y) == per_instance for _, y in groups)
        for (x, y), b in zip(groups, range(B), strict=True):
            rows = np.flatnonzero((actions == a) & (instances == b))
            i = [int(np.flatnonzero((states[rows] == s).all(axis=1))[0]) for s in x]
            np.testing.assert_array_equal(y, deltas[rows[i], d])


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"states": np.zeros((0, 2))}, r"states: expected shape \(N >= 1, D\)"),
        ({"n_actions": 0}, "n_actions: expected >= 1"),  # an empty HyperSet
        ({"n_subsample": 0}, "n_subsample: expected >= 1"),  # used 2 silently
        ({"actions": np.zeros(12)}, r"actions: expected integers in \[0, 2\)"),
        ({"actions": np.full(12, 2)}, r"actions: expected integers in \[0, 2\)"),
        ({"actions": np.r_[np.zeros(11, int), 1]},
         "at least 2 transitions of each action, got 1 of action 1"),
        ({"deltas": np.zeros((12, 3))}, r"deltas: expected shape \(12, 2\)"),
        ({"instances": np.zeros(11)}, r"instances: expected shape \(12,\)"),
        ({"states": np.full((12, 2), np.nan)}, "states: expected finite"),
        ({"rng": 0}, "rng: expected a numpy Generator"),
    ],
)  # fmt: skip
def test_hyper_set_refuses_bad_input_before_fitting(change, match):
    """Empty states failed with ZeroDivisionError; an absent action with a
    message about `groups` that did not say which action."""
    args = {
        "states": np.arange(24.0).reshape(12, 2), "actions": np.arange(12) % 2,
        "deltas": np.ones((12, 2)), "instances": np.arange(12) // 6,
        "n_actions": 2, "n_subsample": 8, "rng": np.random.default_rng(0),
    } | change  # fmt: skip
    if len(args["states"]) == 0:
        args |= {"deltas": np.zeros((0, 2)), "actions": np.zeros(0, int),
                 "instances": np.zeros(0, int)}  # fmt: skip
    with pytest.raises(ValueError, match=match):
        gp.fit_hyper_set(
            *(args.pop(k) for k in ("states", "actions", "deltas", "instances")),
            args.pop("n_actions"), **args,
        )  # fmt: skip


def test_inputs_far_from_0_fit_as_centred_ones():
    """Inputs 100 spreads from 0 lost the kernel distances' precision at the
    search's short length scales: it stopped at its starting point (it warned).
    The kernels now centre such inputs, so they fit as the centred data do."""
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 1, size=(200, 1))
    y = np.sin(6 * X[:, 0]) + 1e-3 * rng.normal(size=200)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        centred = fit_hyperparameters([(X - 0.5, y)])
        shifted = fit_hyperparameters([(X + 100.0, y)])
    start = gp._bounds([(X + 100.0, y)])[0]
    assert np.abs(centred.to_theta() - start).max() > 0.1  # it moved
    np.testing.assert_allclose(shifted.to_theta(), centred.to_theta(), atol=1e-4)


def test_a_search_stuck_at_its_start_warns(monkeypatch):
    """Kernel matrices that are not positive definite at every θ the search
    tries: it returns its start, and says so."""
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 1, size=(50, 1))
    y = np.sin(6 * X[:, 0])

    def fails(*args, **kwargs):
        raise np.linalg.LinAlgError("not positive definite")

    monkeypatch.setattr(gp, "neg_log_marginal_likelihood", fails)
    with pytest.warns(RuntimeWarning, match="the start, not an optimum"):
        stuck = fit_hyperparameters([(X, y)])
    start = gp._bounds([(X, y)])[0]
    np.testing.assert_allclose(stuck.to_theta(), start, rtol=1e-12)
    # the documented start: ℓ = std(X), σ_f² = mean(y²), σ_n² = mean(y²) / 100
    np.testing.assert_allclose(stuck.lengthscales, X.std(0), rtol=1e-12)
    scale = np.mean(y * y)
    np.testing.assert_allclose(
        [stuck.signal_var, stuck.noise_var], [scale, scale / 100], rtol=1e-12
    )


def _hyper_set_args():
    return {
        "lengthscales": np.ones((2, 3, 3)),
        "signal_var": np.full((2, 3), 2.0),
        "noise_var": np.full((2, 3), 0.1),
    }


@pytest.mark.parametrize(
    ("name", "value", "match"),
    [
        ("lengthscales", np.ones((2, 3, 2)), r"scales: expected shape \(A, D, D\)"),
        ("signal_var", np.ones((2, 2)), r"signal_var: expected shape \(2, 3\)"),
        ("noise_var", np.ones(3), r"noise_var: expected shape \(2, 3\)"),
        ("signal_var", np.full((2, 3), np.inf), "signal_var: expected finite values"),
        ("noise_var", np.zeros((2, 3)), "noise_var: expected finite values > 0"),
        ("lengthscales", -np.ones((2, 3, 3)), "lengthscales: expected finite values"),
        ("periodic", (3,), "periodic"),
    ],
)  # fmt: skip
def test_hyper_set_refuses_bad_arrays(name, value, match):
    with pytest.raises(ValueError, match=match):
        HyperSet(**(_hyper_set_args() | {name: value}))


def test_hyper_set_get_is_one_gps_hyperparameters():
    rng = np.random.default_rng(0)
    ell, sf2, sn2 = (
        rng.uniform(0.5, 2, (2, 3, 3)),
        rng.uniform(1, 2, (2, 3)),
        rng.uniform(0.1, 0.2, (2, 3)),
    )
    hyper = HyperSet(ell, sf2, sn2, periodic=[np.int64(1)])
    assert hyper.periodic == (1,)
    h = hyper.get(1, 2)
    np.testing.assert_array_equal(h.lengthscales, ell[1, 2])
    assert (h.signal_var, h.noise_var, h.periodic) == (sf2[1, 2], sn2[1, 2], (1,))


def test_fit_takes_a_constant_input_and_zero_targets():
    """A state dimension that never moves (std 0) and a Δ dimension that is
    always 0 (mean(y²) = 0) set the search's scales: log 0 made θ₀ -inf and the
    fit returned NaN or zero hyperparameters. Their scales fall back to 1 and
    1e-12, so the fit is finite and positive, and the constant dimension's
    length scale lies in the box about 1 (a vanishing one would make every
    prediction at another value of that dimension the prior's)."""
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.normal(size=30), np.full(30, 2.0)])
    for y in (np.sin(X[:, 0]), np.zeros(30)):
        h = fit_hyperparameters([(X, y)])
        theta = h.to_theta()
        assert np.all(np.isfinite(theta)), theta
        assert 1e-2 <= h.lengthscales[1] <= 1e2  # std 1 ± the factor 100 box


def test_fit_needs_two_points():
    X, y = np.zeros((1, 2)), np.ones(1)
    for groups in ([], [(X, y)], [(X, y), (X[:0], y[:0])]):
        with pytest.raises(ValueError, match="groups: expected at least 2 data points"):
            fit_hyperparameters(groups)


def test_predicted_variance_is_never_negative():
    """At a training input the latent variance is below σ_n²; with σ_f² = 1e4 the
    difference σ_f² - ‖L⁻¹k‖² is round-off of ~1e4·1e-16 around a true value
    below σ_n² = 1e-12, so it comes out negative at some of these inputs (11 of
    60 when written): it is clipped at 0."""
    rng = np.random.default_rng(0)
    X = rng.normal(size=(60, 2))
    h = GPHyper(np.array([1.0, 1.0]), 1e4, 1e-12)
    _, var = condition(X, rng.normal(size=60), h).predict(X)
    assert np.all(var >= 0.0)


def test_periodic_predict_mean_is_predicts_mean():
    rng = np.random.default_rng(1)
    X, Xs = rng.uniform(-3, 3, size=(20, 2)), rng.uniform(-3, 3, size=(5, 2))
    post = condition(X, np.sin(X[:, 0]), GPHyper(np.array([1.0, 2.0]), 1.0, 0.01, (0,)))
    np.testing.assert_allclose(post.predict_mean(Xs), post.predict(Xs)[0], atol=1e-12)


def test_subsample_draws_sorted_distinct_indices_uniformly():
    """Sorted (as documented: callers keep a subsample in the data's order),
    distinct, and each item equally likely: in 4000 draws of 5 of 20, each is
    drawn Binomial(4000, 1/4) times, mean 1000, sd 27.4; all 20 counts lie
    within 5 sd (probability of failing ~1e-5 for a correct draw)."""
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(gp.subsample(7, 7, rng=rng), np.arange(7))
    np.testing.assert_array_equal(gp.subsample(7, 10, rng=rng), np.arange(7))
    counts = np.zeros(20)
    for _ in range(4000):
        idx = gp.subsample(20, 5, rng=rng)
        assert len(idx) == 5 and np.all(np.diff(idx) > 0)
        counts[idx] += 1
    assert np.all(np.abs(counts - 1000) < 5 * np.sqrt(4000 * 0.25 * 0.75))


def test_condition_takes_one_state_of_shape_d():
    """One state given as (D,) is conditioned on as one point (1, D)."""
    x, y = np.array([0.3, -0.2]), np.array([0.7])
    h = GPHyper(np.array([0.9, 1.1]), 1.3, 0.05)
    Xs = np.random.default_rng(0).normal(size=(4, 2))
    for got, want in zip(
        condition(x, y, h).predict(Xs),
        condition(x[None], y, h).predict(Xs),
        strict=True,
    ):
        np.testing.assert_array_equal(got, want)
