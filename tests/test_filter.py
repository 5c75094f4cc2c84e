"""Online filter: basis interpolation, batch = sequential, conjugate posterior."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import stats

from hipmdp.data import Transitions
from hipmdp.filter import Belief, predictive, prior_belief, update_belief
from hipmdp.gp import HyperSet
from hipmdp.kernels import se_kernel
from hipmdp.model import HipMDP

A, D, M, K = 3, 2, 15, 3  # A ≠ D: a swapped (action, dimension) index fails


def _model(seed=0):
    rng = np.random.default_rng(seed)
    hyper = HyperSet(
        lengthscales=rng.uniform(0.5, 1.5, size=(A, D, D)),
        signal_var=rng.uniform(0.5, 2.0, size=(A, D)),
        noise_var=rng.uniform(0.01, 0.05, size=(A, D)),
    )
    z = np.ones((K, A, D), dtype=bool)
    z[1, 0, 1] = z[2, 1, 0] = False
    return HipMDP(
        support=rng.uniform(-2, 2, size=(M, D)),
        hyper=hyper,
        z=z,
        f=rng.normal(size=(K, A, D, M)),
        # B = 4 training instances (≠ K), weights spread around their mean, so the
        # filter's mean_b w² differs from μ_w²
        weights=np.concatenate([np.ones((1, 4)), rng.normal(size=(K - 1, 4))]),
        mu_w=np.array([1.0, 0.5, -1.0]),
        sigma_w=2.0,
        instance_ids=np.arange(4),
        info={},
    )


def _dense_basis(model, s, a):
    """F[d, k] = z[k,a,d] k(s, S*) (K + σ² I)⁻¹ f[k,a,d], one state at a time."""
    out = np.zeros((D, model.f.shape[0]))  # the model's features (K, or 1)
    for d in range(D):
        h = model.hyper.get(a, d)
        Kss = se_kernel(model.support, model.support, h.lengthscales, h.signal_var)
        ks = se_kernel(s[None], model.support, h.lengthscales, h.signal_var)[0]
        coef = np.linalg.solve(Kss + h.noise_var * np.eye(M), model.f[:, a, d].T)
        out[d] = (ks @ coef) * model.z[:, a, d]
    return out


def _dense_interpolation_var(model, s, a):
    """v[d] = k(s, s) - k(s, S*) (K + σ² I)⁻¹ k(S*, s), one state at a time."""
    out = np.zeros(D)
    for d in range(D):
        h = model.hyper.get(a, d)
        Kss = se_kernel(model.support, model.support, h.lengthscales, h.signal_var)
        ks = se_kernel(s[None], model.support, h.lengthscales, h.signal_var)[0]
        out[d] = h.signal_var - ks @ np.linalg.inv(Kss + h.noise_var * np.eye(M)) @ ks
    return out


def _dense_filter_noise(model, s, a):
    """τ²[d] = σ² + c v(s) (1 + Σ_{k>1} z[k,a,d] μ_w[k]²) + r0, one state at a time
    (c = 1, r0 = 0 when the model has no error terms; mean_b w[k,b]² for μ_w[k]²
    with filter_weights="training")."""
    c = np.ones(D) if model.interp_var_scale is None else model.interp_var_scale[a]
    r0 = np.zeros(D) if model.residual_var is None else model.residual_var[a]
    v = _dense_interpolation_var(model, s, a)
    out = np.zeros(D)
    for d in range(D):
        m2 = 1.0
        for k in range(1, model.f.shape[0]):
            w = model.weights[k]
            if model.filter_weights == "training":
                m2 += model.z[k, a, d] * sum(wb * wb for wb in w) / len(w)
            else:
                m2 += model.z[k, a, d] * model.mu_w[k] ** 2
        out[d] = model.hyper.noise_var[a, d] + c[d] * v[d] * m2 + r0[d]
    return out


def _data(model, w, n, rng):
    """n transitions of an instance with weights w (K - 1,), drawn from the model the
    filter assumes: Δ ~ N(f_1 + F w, τ²)."""
    S = rng.uniform(-2, 2, size=(n, D))
    acts = rng.integers(0, A, size=n)
    F = model.basis(S, acts)
    noise = model.filter_noise(S, acts)
    delta = F[..., 0] + F[..., 1:] @ w + np.sqrt(noise) * rng.normal(size=(n, D))
    return Transitions(S, acts, S + delta, np.zeros(n, dtype=int))


def test_basis_matches_dense_interpolation():
    model = _model()
    rng = np.random.default_rng(1)
    S, acts = rng.normal(size=(6, D)), rng.integers(0, A, size=6)
    F = model.basis(S, acts)
    for i in range(6):
        np.testing.assert_allclose(F[i], _dense_basis(model, S[i], acts[i]), atol=1e-10)


WITH_ERROR_TERMS = {
    "residual_var": np.array([[1e-3, 4e-3], [2e-3, 0.0], [0.0, 5e-3]]),
    "interp_var_scale": np.array([[1.0, 3.0], [10.0, 2.0], [4.0, 1.0]]),
}


@pytest.mark.parametrize(
    "terms",
    [{}, WITH_ERROR_TERMS, {**WITH_ERROR_TERMS, "filter_weights": "training"}],
    ids=["plain", "terms", "terms-training"],
)
def test_batch_update_equals_single_updates_and_conjugate_posterior(terms):
    model = dataclasses.replace(_model(), **terms)
    rng = np.random.default_rng(2)
    data = _data(model, np.array([0.3, -0.7]), 12, rng)
    batch = model.update(model.prior(), data)
    seq = model.prior()
    for i in range(len(data)):
        one = Transitions(
            data.states[i : i + 1],
            data.actions[i : i + 1],
            data.next_states[i : i + 1],
            data.instances[i : i + 1],
        )
        seq = model.update(seq, one)
    np.testing.assert_allclose(batch.h, seq.h, atol=1e-10)
    np.testing.assert_allclose(batch.P, seq.P, atol=1e-10)
    # Dense conjugate posterior: stack all (transition, dimension) rows.
    X = np.concatenate(
        [
            _dense_basis(model, s, a)[:, 1:]
            for s, a in zip(data.states, data.actions, strict=True)
        ]
    )
    f1 = np.concatenate(
        [
            _dense_basis(model, s, a)[:, 0]
            for s, a in zip(data.states, data.actions, strict=True)
        ]
    )
    y = data.deltas.reshape(-1) - f1
    tau2 = np.concatenate(
        [
            _dense_filter_noise(model, s, a)
            for s, a in zip(data.states, data.actions, strict=True)
        ]
    )
    assert np.all(tau2 > 1.5 * model.hyper.noise_var[data.actions].reshape(-1))
    Sinv = np.diag(1.0 / tau2)
    cov = np.linalg.inv(X.T @ Sinv @ X + np.eye(K - 1) / model.sigma_w**2)
    mean = cov @ (model.mu_w[1:] / model.sigma_w**2 + X.T @ Sinv @ y)
    np.testing.assert_allclose(batch.mean, mean, atol=1e-9)
    np.testing.assert_allclose(batch.cov, cov, atol=1e-9)
    # Predictive: mean f1 + F μ, variance σ² + F Σ Fᵀ.
    pm, pv = model.predict(data.states[:3], data.actions[:3], batch)
    noise = model.hyper.noise_var[data.actions[:3]].reshape(-1)
    np.testing.assert_allclose(pm.reshape(-1), f1[:6] + X[:6] @ mean, atol=1e-9)
    pm_only = model.predict_mean(data.states[:3], data.actions[:3], batch)
    np.testing.assert_allclose(pm_only, pm, atol=1e-12)
    # Variance: σ² + F Σ Fᵀ + c v(s) Σ_k z[k,a,d] E[w_k²] + r0, with w_0 = 1.
    v = np.concatenate(
        [_dense_interpolation_var(model, s, a) for s, a in zip(
            data.states[:3], data.actions[:3], strict=True)]
    )  # fmt: skip
    ew2 = np.concatenate([[1.0], mean**2 + np.diag(cov)])
    zs = np.concatenate([model.z[:, a, :].T for a in data.actions[:3]])  # (6, K)
    c, r0 = np.ones(6), np.zeros(6)
    if terms:
        c = terms["interp_var_scale"][data.actions[:3]].reshape(-1)
        r0 = terms["residual_var"][data.actions[:3]].reshape(-1)
    expected = (
        noise + np.einsum("ik,kj,ij->i", X[:6], cov, X[:6]) + c * v * (zs @ ew2) + r0
    )
    np.testing.assert_allclose(pv.reshape(-1), expected, rtol=1e-9, atol=1e-12)
    assert np.all(v > 0)  # the term is really exercised


def test_a_model_without_latent_features_predicts_its_mean_dynamics():
    """K = 1 (the sampler found no feature): the belief is empty, filtering
    leaves it so, and the prediction is feature 0 with variance
    σ² + c·v + r0 (dense, one state at a time)."""
    full = dataclasses.replace(_model(2), **WITH_ERROR_TERMS)
    model = dataclasses.replace(
        full, z=full.z[:1], f=full.f[:1], weights=full.weights[:1], mu_w=full.mu_w[:1]
    )
    rng = np.random.default_rng(3)
    data = _data(model, np.zeros(0), 12, rng)
    belief = model.update(model.prior(), data)
    assert belief.mean.shape == (0,) and belief.cov.shape == (0, 0)
    mean, var = model.predict(data.states, data.actions, belief)
    for i, (s, a) in enumerate(zip(data.states, data.actions, strict=True)):
        np.testing.assert_allclose(mean[i], _dense_basis(model, s, a)[:, 0], atol=1e-12)
        want = (
            model.hyper.noise_var[a]
            + model.interp_var_scale[a] * _dense_interpolation_var(model, s, a)
            + model.residual_var[a]
        )
        np.testing.assert_allclose(var[i], want, rtol=1e-9)


def test_paper_filter_uses_the_fitted_noise_alone():
    model = dataclasses.replace(_model(), **WITH_ERROR_TERMS)
    data = _data(model, np.array([0.3, -0.7]), 12, np.random.default_rng(2))
    belief = model.update(model.prior(), data, model_error=False)
    X = np.concatenate([_dense_basis(model, s, a) for s, a in zip(
        data.states, data.actions, strict=True)])  # fmt: skip
    y = data.deltas.reshape(-1) - X[:, 0]
    Sinv = np.diag(1.0 / model.hyper.noise_var[data.actions].reshape(-1))
    P = X[:, 1:].T @ Sinv @ X[:, 1:] + np.eye(K - 1) / model.sigma_w**2
    h = model.mu_w[1:] / model.sigma_w**2 + X[:, 1:].T @ Sinv @ y
    np.testing.assert_allclose(belief.P, P, rtol=1e-9)
    np.testing.assert_allclose(belief.h, h, rtol=1e-9)


def _coverage(model, n_trials, n, seed, **update):
    """Fraction of instances w ~ prior whose 95% posterior ellipsoid after n
    transitions (drawn with the filter's τ²) contains w."""
    rng = np.random.default_rng(seed)
    prior, inside = model.prior(), 0
    bound = stats.chi2.ppf(0.95, K - 1)
    for _ in range(n_trials):
        w = prior.mean + model.sigma_w * rng.normal(size=K - 1)
        belief = model.update(prior, _data(model, w, n, rng), **update)
        e = w - belief.mean
        inside += e @ belief.P @ e <= bound
    return inside / n_trials


def test_filter_is_calibrated_on_data_from_its_own_likelihood():
    # Instances drawn from the prior, data from the filter's own likelihood (with
    # the model-error terms): the posterior is exact, so its 95% region holds the
    # truth 95% of the time (400 trials: sd 1.1%; the bounds are ±4 sd). This
    # checks the update end to end (prior, noise and region together), not
    # whether the model-error terms match a real model's errors (README,
    # coverage, measures that). The paper's filter trusts σ² alone, 2-900×
    # (median 36×) too small here, and its regions miss far more often (93.5% and
    # 3.5% here, as README quotes).
    model = dataclasses.replace(_model(5), **WITH_ERROR_TERMS)
    assert 0.906 <= _coverage(model, 400, 30, seed=6) <= 0.994
    assert _coverage(model, 400, 30, seed=6, model_error=False) < 0.8


def test_filter_concentrates_on_true_weights():
    # 1500 transitions from w_true: each posterior mean lies within 4 posterior
    # standard deviations of the truth (a false failure has probability ~1e-4). If the
    # mean-dynamics term were not subtracted the weights would absorb f_1 and miss.
    model = _model(3)
    w_true = np.array([1.2, -0.4])
    data = _data(model, w_true, 1500, np.random.default_rng(4))
    belief = model.update(model.prior(), data)
    sd = np.sqrt(np.diag(belief.cov))
    assert np.all(np.abs(belief.mean - w_true) < 4 * sd)
    assert np.all(sd < 0.05)  # the data really pin the weights down


def test_prior_and_errors():
    model = _model()
    prior = model.prior()
    np.testing.assert_allclose(prior.mean, model.mu_w[1:])
    np.testing.assert_allclose(prior.cov, np.eye(K - 1) * model.sigma_w**2)
    with pytest.raises(ValueError, match="belief"):
        model.predict(
            np.zeros((1, D)), np.zeros(1, int), Belief(np.zeros(1), np.eye(1))
        )
    with pytest.raises(ValueError, match="states"):
        model.predict(np.zeros((1, D + 1)), np.zeros(1, int), prior)
    with pytest.raises(ValueError, match="actions"):
        model.predict(np.zeros((1, D)), np.array([A]), prior)
    with pytest.raises(ValueError, match="Belief"):
        Belief(np.zeros(2), np.eye(3))
    with pytest.raises(ValueError, match="actions: expected integers, got non-int"):
        model.predict(np.zeros((1, D)), np.array([0.5]), prior)
    with pytest.raises(ValueError, match="belief: expected a hipmdp.Belief"):
        model.predict(np.zeros((1, D)), np.zeros(1, int), prior.mean)
    with pytest.raises(ValueError, match="belief: expected a hipmdp.Belief"):
        model.mean_predictor(None)
    with pytest.raises(ValueError, match="model_error: expected True or False"):
        data = _data(model, model.mu_w[1:], 3, np.random.default_rng(0))
        model.update(prior, data, model_error="no")


def test_filter_functions_check_their_inputs():
    """The functions HipMDP calls, for direct users: a negative σ_w was squared
    away, a wrong-shaped or zero noise variance failed inside numpy or as a
    non-finite Belief that did not name it."""
    # True gave σ_w = 1; "1" a TypeError; inf a zero precision blamed on the Belief
    for bad in (-1.0, True, "1", np.inf):
        with pytest.raises(ValueError, match="sigma_w: expected a finite number > 0"):
            prior_belief(np.zeros(2), bad)
    for bad in (np.zeros((2, 1)), np.array([0.0, np.nan])):
        with pytest.raises(ValueError, match="mu_w: expected finite shape"):
            prior_belief(bad, 1.0)
    prior = prior_belief(np.zeros(2), 1.0)
    F, innovation, noise = np.ones((3, 4, 2)), np.zeros((3, 4)), np.ones((3, 4))
    update_belief(prior, F, innovation, noise)
    for args, match in [
        ((F[..., :1], innovation, noise), r"F: expected shape \(n, D, 2\)"),
        ((F, innovation[:, :3], noise), r"innovation: expected shape \(3, 4\)"),
        ((F, innovation, noise[:2]), r"noise_var: expected shape \(3, 4\)"),
        ((F, innovation, 0 * noise), "noise_var: expected finite values > 0"),
        # NaN here was blamed on the Belief ("expected finite h and P")
        ((F * np.nan, innovation, noise), "F: expected finite values"),
        ((F, innovation + np.inf, noise), "innovation: expected finite values"),
    ]:
        with pytest.raises(ValueError, match=match):
            update_belief(prior, *args)


def test_predictive_checks_its_inputs_as_the_update_does():
    """predictive checked nothing: σ² = -1 gave a variance of 1, an f1 of shape
    (D,) or (1, D) broadcast, and with no latent weights the inputs came back
    as they were given."""
    prior = prior_belief(np.zeros(2), 1.0)
    F, f1, noise = np.ones((3, 4, 2)), np.zeros((3, 4)), np.ones((3, 4))
    predictive(prior, F, f1, noise)
    empty = prior_belief(np.zeros(0), 1.0)
    for belief, args, match in [
        (prior, (F, f1, -noise), "noise_var: expected finite values > 0"),
        (prior, (F, f1[0], noise), r"f1: expected shape \(3, 4\)"),
        (prior, (F, f1[:1], noise), r"f1: expected shape \(3, 4\)"),
        (prior, (F, f1 * np.nan, noise), "f1: expected finite values"),
        (prior, (F * np.nan, f1, noise), "F: expected finite values"),
        (empty, (np.ones((1, 2, 0)), [[1, 2, 3]], [[1, 1]]), "f1: expected shape"),
        ("belief", (F, f1, noise), "belief: expected a Belief"),
    ]:
        with pytest.raises(ValueError, match=match):
            predictive(belief, *args)
    mean, var = predictive(empty, np.ones((1, 2, 0)), [[1, 2]], [[1, 1]])
    assert isinstance(mean, np.ndarray) and mean.tolist() == [[1.0, 2.0]]


@pytest.mark.parametrize(
    ("P", "match"),
    [
        (-np.eye(2), "positive-definite"),
        (np.zeros((2, 2)), "positive-definite"),
        (np.triu(np.ones((2, 2))) + np.eye(2), "symmetric"),
    ],
)
def test_belief_precision_must_be_symmetric_positive_definite(P, match):
    with pytest.raises(ValueError, match=f"Belief: expected a {match} precision"):
        Belief(np.zeros(2), P)


def test_belief_rejects_non_finite_information():
    """A NaN information vector with a finite precision passed every other check
    (its Cholesky factor is fine) and gave a NaN mean."""
    for h, P in [([np.nan, 0.0], np.eye(2)), ([0.0, 0.0], np.diag([1.0, np.inf]))]:
        with pytest.raises(ValueError, match="Belief: expected finite h and P"):
            Belief(np.array(h), P)


def test_belief_keeps_read_only_copies():
    """A belief is a value: writing into the arrays it was built from must not
    move it, and its own arrays cannot be written."""
    h, P = np.array([1.0, 2.0]), 2.0 * np.eye(2)
    belief = Belief(h, P)
    h[:] = 0.0
    P[:] = 5.0 * np.eye(2)
    np.testing.assert_array_equal(belief.h, [1.0, 2.0])
    np.testing.assert_array_equal(belief.P, 2.0 * np.eye(2))
    np.testing.assert_allclose(belief.mean, [0.5, 1.0], rtol=1e-12)  # round-off
    for x in (belief.h, belief.P):
        assert isinstance(x, np.ndarray) and x.dtype == float
        with pytest.raises(ValueError, match="read-only"):
            x[0] = 1.0
    from_lists = Belief([1, 2], [[2, 0], [0, 2]])
    assert from_lists.P.dtype == float and not from_lists.P.flags.writeable


def test_predictive_without_latent_weights_returns_new_arrays():
    """With no latent weights the prediction is (f1, σ²) itself: returned as
    copies, so that writing into the prediction leaves the caller's inputs."""
    f1, noise = np.array([[1.0, 2.0]]), np.array([[0.5, 0.5]])
    mean, var = predictive(
        prior_belief(np.zeros(0), 1.0), np.ones((1, 2, 0)), f1, noise
    )
    mean += 1.0
    var += 1.0
    np.testing.assert_array_equal(f1, [[1.0, 2.0]])
    np.testing.assert_array_equal(noise, [[0.5, 0.5]])


def test_interpolation_variance_is_never_negative():
    """At a support point v_ad = σ_f² - ‖L⁻¹k‖² is below σ² = 1e-12; with σ_f² =
    1e4 it is computed as round-off of ~1e4·1e-16 around that value and comes out
    negative at some of these points (as in `hipmdp.gp`'s prediction): it is
    clipped at 0, so that no variance the model adds it to shrinks."""
    rng = np.random.default_rng(0)
    m = 60
    model = dataclasses.replace(
        _model(),
        support=rng.normal(size=(m, D)),
        f=rng.normal(size=(K, A, D, m)),
        hyper=HyperSet(
            np.ones((A, D, D)), np.full((A, D), 1e4), np.full((A, D), 1e-12)
        ),
    )
    states, actions = np.repeat(model.support, A, axis=0), np.tile(np.arange(A), m)
    v = model.interpolation_var(states, actions)
    assert np.all(v >= 0.0)
    assert v.max() < 1e-9  # round-off of 1e4·1e-16 per term, summed over 60 terms


def test_a_saved_belief_loads_as_it_was_and_goes_on_filtering(tmp_path):
    """A belief filtered on some transitions, saved and loaded, is the same
    belief (h, P and the model it is over), the model takes it, and the file's
    bytes depend only on the belief."""
    model = _model()
    rng = np.random.default_rng(3)
    s = rng.uniform(-1, 1, size=(5, D))
    data = Transitions(s, np.arange(5) % A, s + 0.1, np.zeros(5, int))
    belief = model.update(model.prior(), data)
    path = belief.save(tmp_path / "belief.npz")
    loaded = Belief.load(path)
    np.testing.assert_array_equal(loaded.h, belief.h)
    np.testing.assert_array_equal(loaded.P, belief.P)
    assert loaded.model == belief.model == model.basis_key
    more = Transitions(s, (np.arange(5) + 1) % A, s - 0.1, np.zeros(5, int))
    np.testing.assert_array_equal(
        model.update(loaded, more).h, model.update(belief, more).h
    )
    again = loaded.save(tmp_path / "again.npz")
    assert again.read_bytes() == path.read_bytes()
    by_hand = Belief.load(Belief(np.zeros(2), np.eye(2)).save(tmp_path / "h.npz"))
    assert by_hand.model is None


def test_a_belief_file_that_is_not_one_is_refused(tmp_path):
    """Another .npz, a model file, a damaged one, or one whose precision is not
    positive definite: a ValueError naming the file and what is wrong."""
    from hipmdp.data import npz_bytes

    with pytest.raises(ValueError, match=r"path: expected a \.npz file name"):
        Belief(np.zeros(1), np.eye(1)).save(tmp_path / "belief.json")
    model_file = _model().save(tmp_path / "model.npz")
    with pytest.raises(ValueError, match=r"model.npz: not a belief file \(expected"):
        Belief.load(model_file)
    good = Belief(np.ones(2), 2 * np.eye(2)).save(tmp_path / "b.npz").read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(good[: len(good) // 2])
    with pytest.raises(ValueError, match="cut.npz: not an .npz archive"):
        Belief.load(cut)

    def written(name, meta, sign=1.0):
        path = tmp_path / name
        arrays = {"h": np.zeros(2), "P": sign * np.eye(2), "meta_json": meta}
        path.write_bytes(npz_bytes(arrays))
        return path

    kind = '"kind": "hipmdp.Belief"'
    for path, match in [
        (written("k.npz", '{"kind": "x", "format_version": 1}'), "meta_json's kind"),
        (written("j.npz", "{"), "meta_json is not valid JSON"),
        (written("v.npz", "{" + kind + ', "format_version": 2}'),
         "expected format_version 1, got 2"),
        (written("t.npz", "{" + kind + ', "format_version": true}'),
         "expected format_version 1, got True"),
        (written("f.npz", "{" + kind + ', "format_version": 1.0}'),
         "expected format_version 1, got 1.0"),
        (written("c.npz", "{" + kind + ', "format_version": 1}', 1.0 + 0j),
         "c.npz: P: expected real numbers, got dtype complex128"),
        (written("p.npz", "{" + kind + ', "format_version": 1}', -1.0),
         "p.npz: Belief: expected a positive-definite precision P"),
    ]:  # fmt: skip
        with pytest.raises(ValueError, match=match):
            Belief.load(path)
