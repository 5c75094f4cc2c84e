"""Single-GP baselines: exact GP formula, subset of data, which data each one uses."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hipmdp.baselines import batch_only, batch_plus_train, fit_gp_baseline, train_only
from hipmdp.data import Transitions
from hipmdp.gp import HyperSet
from hipmdp.kernels import se_kernel

D = 2


def _instance(b, offset, n, rng):
    """Δs = sin(s) + offset, a different constant shift per instance, noise 0.05."""
    S = rng.uniform(-2, 2, size=(n, D))
    acts = rng.integers(0, 2, size=n)
    delta = np.sin(S) * (1 + acts[:, None]) + offset + 0.05 * rng.normal(size=(n, D))
    return Transitions(S, acts, S + delta, np.full(n, b))


def _batch(rng):
    return Transitions.concatenate(
        [_instance(b, off, 60, rng) for b, off in enumerate([-1.0, 0.0, 1.0])]
    )


def test_prediction_is_the_dense_gp_formula():
    rng = np.random.default_rng(0)
    batch = _batch(rng)
    model = batch_only(batch, rng=np.random.default_rng(1))
    Xs = rng.normal(size=(5, D))
    acts = np.array([0, 1, 1, 0, 1])
    mean, var = model.predict(Xs, acts)
    deltas = batch.deltas
    for i in range(5):
        a = acts[i]
        sel = batch.actions == a
        for d in range(D):
            h = model.hyper.get(a, d)
            C = se_kernel(
                batch.states[sel], batch.states[sel], h.lengthscales, h.signal_var
            ) + h.noise_var * np.eye(sel.sum())
            k = se_kernel(
                Xs[i : i + 1], batch.states[sel], h.lengthscales, h.signal_var
            )[0]
            assert mean[i, d] == pytest.approx(
                k @ np.linalg.solve(C, deltas[sel, d]), abs=1e-8
            )
            dense_var = h.signal_var + h.noise_var - k @ np.linalg.solve(C, k)
            assert var[i, d] == pytest.approx(dense_var, abs=1e-8)
    np.testing.assert_allclose(model.predict_mean(Xs, acts), mean, atol=1e-12)
    r = deltas - model.predict(batch.states, batch.actions)[0]
    v = model.predict(batch.states, batch.actions)[1]
    dense_ll = np.sum(-0.5 * r**2 / v - 0.5 * np.log(2 * np.pi * v))
    assert model.log_likelihood(batch) == pytest.approx(dense_ll, rel=1e-12)


def test_mean_predictor_is_predict_mean():
    rng = np.random.default_rng(2)
    batch = _batch(rng)
    Xs = rng.normal(size=(12, D))
    acts = rng.integers(0, 3, size=12)
    # 3 actions, the last with no data: its mean is 0, as in predict_mean
    fitted = batch_only(batch, rng=np.random.default_rng(1), n_max=50).hyper
    hyper = HyperSet(
        *(
            np.concatenate([v, v[:1]])
            for v in (fitted.lengthscales, fitted.signal_var, fitted.noise_var)
        )
    )
    model = batch_only(
        batch, rng=np.random.default_rng(1), n_actions=3, n_max=50, hyper=hyper
    )
    assert model.posteriors[2] == (None, None)
    got = model.mean_predictor()(Xs, acts)
    np.testing.assert_allclose(
        got, model.predict_mean(Xs, acts), rtol=1e-10, atol=1e-12
    )
    assert set(acts) == {0, 1, 2}
    np.testing.assert_array_equal(got[acts == 2], 0.0)
    # each GP's own hyperparameters count, not the set's
    post = model.posteriors[0][1]
    wider = post._replace(hyper=post.hyper._replace(signal_var=4.0))
    other = dataclasses.replace(
        model, posteriors=((model.posteriors[0][0], wider), *model.posteriors[1:])
    )
    np.testing.assert_allclose(
        other.mean_predictor()(Xs, acts), other.predict_mean(Xs, acts), rtol=1e-10
    )
    assert not np.allclose(other.predict_mean(Xs, acts), got)
    # the GPs of one action must share their inputs
    moved = post._replace(X=post.X + 1.0)
    bad = dataclasses.replace(
        model, posteriors=((model.posteriors[0][0], moved), *model.posteriors[1:])
    )
    with pytest.raises(ValueError, match=r"posteriors\[0\]: expected one input set"):
        bad.mean_predictor()


def test_subset_of_data_and_kept_train_points():
    rng = np.random.default_rng(2)
    batch = _batch(rng)
    train = _instance(9, 2.0, 20, rng)
    model = batch_plus_train(batch, train, rng=np.random.default_rng(3), n_max=30)
    for a in range(2):
        X = model.posteriors[a][0].X
        n_train_a = int((train.actions == a).sum())
        assert len(X) == 30
        # every training state of action a is among the conditioning points
        hits = (X[None, :, :] == train.states[train.actions == a][:, None, :]).all(-1)
        assert hits.any(1).sum() == n_train_a
    # the two the other way round: the whole batch kept, beyond n_max, refused
    with pytest.raises(ValueError, match=r"train: expected one new instance's"):
        batch_plus_train(train, batch, rng=np.random.default_rng(3), n_max=30)


def test_train_only_beats_batch_only_on_a_shifted_instance():
    # The new instance is shifted by +2, outside the batch's offsets {-1, 0, 1}: the
    # average model is off by about 2 everywhere, the train-only GP is not.
    rng = np.random.default_rng(4)
    batch = _batch(rng)
    train, test = _instance(9, 2.0, 60, rng), _instance(9, 2.0, 50, rng)
    b = batch_only(batch, rng=np.random.default_rng(5))
    t = train_only(train, rng=np.random.default_rng(5))
    bt = batch_plus_train(batch, train, rng=np.random.default_rng(5))

    def sq_errors(model):
        return (
            (model.predict(test.states, test.actions)[0] - test.deltas) ** 2
        ).ravel()

    def se(x):  # standard error of the mean of the 100 per-value squared errors
        return x.std(ddof=1) / np.sqrt(x.size)

    # The train-only GP is the right model of its instance (hyperparameters by
    # maximum likelihood on it): its squared error is what its own predictive
    # variance (noise included) says, within 4 standard errors. (A bound of
    # 0.25 × the batch model's error, 265× the train-only error here, passed a
    # train-only model off by 1 everywhere.)
    e_t, e_b, e_bt = sq_errors(t), sq_errors(b), sq_errors(bt)
    var_t = t.predict(test.states, test.actions)[1].ravel()
    assert abs(e_t.mean() - var_t.mean()) < 4 * se(e_t - var_t)
    # and it beats batch-only by more than 4 standard errors of the paired
    # differences; batch + train sits between them
    assert (e_b - e_t).mean() > 4 * se(e_b - e_t)
    assert t.log_likelihood(test) > b.log_likelihood(test)
    assert (e_b - e_bt).mean() > 4 * se(e_b - e_bt)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        # n_max = 0 was reported as "action 0 has 0 transitions"
        ({"n_max": 0}, "n_max: expected >= 1, got 0"),
        ({"n_max": 2.5}, "n_max: expected an integer"),
        ({"n_hyper": 1}, "n_hyper: expected >= 2"),
        ({"n_actions": 2.0}, "n_actions: expected an integer"),
        ({"keep": np.ones(3, bool)}, r"keep: expected a bool array of shape \(40,\)"),
        ({"keep": np.ones(40)}, "keep: expected a bool array"),
    ],
)
def test_fit_gp_baseline_checks_its_options(kwargs, match):
    data = _instance(0, 0.0, 40, np.random.default_rng(6))
    with pytest.raises(ValueError, match=match):
        fit_gp_baseline(data, rng=np.random.default_rng(0), **kwargs)


def test_fit_gp_baseline_checks_its_generator_first():
    """None (or a seed) worked on small data and failed on large data inside the
    subsampling, naming no argument."""
    data = _instance(0, 0.0, 40, np.random.default_rng(6))
    for rng in (None, 0):
        with pytest.raises(ValueError, match="rng: expected numpy.random.Generator"):
            fit_gp_baseline(data, rng=rng)


def test_missing_action_needs_hyperparameters():
    rng = np.random.default_rng(6)
    train = _instance(0, 0.0, 20, rng).select(actions=[0])
    with pytest.raises(ValueError, match="action 1"):
        train_only(train, rng=rng, n_actions=2)
    hyper = batch_only(_batch(rng), rng=rng).hyper
    model = fit_gp_baseline(train, rng=rng, n_actions=2, hyper=hyper)
    mean, var = model.predict(np.zeros((1, D)), np.array([1]))
    np.testing.assert_allclose(mean, 0.0)  # the prior where action 1 has no data
    np.testing.assert_allclose(var[0], hyper.signal_var[1] + hyper.noise_var[1])


@pytest.mark.parametrize(
    "states, actions, match",
    [
        (np.zeros((3, D + 1)), np.zeros(3, int), "states: expected shape"),
        (np.zeros((3, D)), np.zeros(2, int), "actions: expected shape"),
        (
            np.full((3, D), np.nan),
            np.zeros(3, int),
            r"states: non-finite value at index \(0, 0\)",
        ),
        ([[0.0] * D, [0.0]], [0, 0], r"states: expected an array of shape \(n, 2\)"),
        (np.zeros((3, D)), np.full(3, 7), r"actions: expected integers in \[0, 2\)"),
        # a continuous action is refused, not truncated to an index
        (np.zeros((2, D)), [0.7, 1.2], "actions: expected integers, got non-integer"),
        (np.zeros((2, D)), [True, False], "actions: expected an integer array"),
        (np.zeros((2, D)), ["0", "1"], "actions: expected an integer array"),
        ([["a"] * D], [0], "states: expected a numeric array"),
    ],
)
def test_bad_queries(states, actions, match):
    model = batch_only(_batch(np.random.default_rng(7)), rng=np.random.default_rng(7))
    with pytest.raises(ValueError, match=match):
        model.predict(states, actions)


def test_log_likelihood_refuses_what_is_not_transitions():
    """Arrays where Transitions belong failed with an AttributeError on .states
    (the HiP-MDP's log_likelihood named the argument)."""
    batch = _batch(np.random.default_rng(7))
    model = batch_only(batch, rng=np.random.default_rng(7))
    with pytest.raises(ValueError, match="data: expected hipmdp.Transitions, got tup"):
        model.log_likelihood((batch.states, batch.actions, batch.next_states))


def test_periodic_baseline_fast_path_and_options():
    # dimension 1 declared an angle: the fitted GPs carry it, mean_predictor agrees
    # with predict_mean and both see a 2π shift of s_1 as the same state
    rng = np.random.default_rng(4)
    batch = _batch(rng)
    model = batch_only(batch, rng=np.random.default_rng(1), n_max=50, periodic=(1,))
    assert model.hyper.periodic == (1,)
    assert model.posteriors[0][0].hyper.periodic == (1,)
    Xs = rng.normal(size=(12, D))
    acts = rng.integers(0, 2, size=12)
    want = model.predict_mean(Xs, acts)
    shifted = Xs + [0.0, -2 * np.pi]
    np.testing.assert_allclose(model.mean_predictor()(Xs, acts), want, rtol=1e-10)
    np.testing.assert_allclose(model.predict(shifted, acts)[0], want, rtol=1e-9)
    np.testing.assert_allclose(model.mean_predictor()(shifted, acts), want, rtol=1e-9)
    plain = batch_only(batch, rng=np.random.default_rng(1), n_max=50)
    assert plain.hyper.periodic == ()
    # the hyperparameters were fitted with the periodic kernel, not only labelled
    assert not np.allclose(model.hyper.lengthscales, plain.hyper.lengthscales)
    assert not np.allclose(plain.predict_mean(Xs, acts), want)
    # given hyperparameters bring their periodic dimensions; a different ask fails
    again = batch_only(batch, rng=np.random.default_rng(1), n_max=50, hyper=model.hyper)
    np.testing.assert_allclose(again.predict_mean(Xs, acts), want, rtol=1e-12)
    with pytest.raises(ValueError, match=r"periodic: expected hyper.periodic = \(1,\)"):
        batch_only(
            batch, rng=np.random.default_rng(1), hyper=model.hyper, periodic=(0,)
        )
    with pytest.raises(ValueError, match="periodic: expected distinct"):
        batch_only(batch, rng=np.random.default_rng(1), periodic=(2,))


def test_named_baselines_refuse_the_arguments_they_set():
    """The docstrings said "kwargs: see fit_gp_baseline", but name= (and keep=
    for batch + train) failed with a duplicate-keyword TypeError."""
    data = _batch(np.random.default_rng(0))
    rng = np.random.default_rng(1)
    with pytest.raises(ValueError, match="name: set by this baseline"):
        train_only(data, rng=rng, name="x")
    with pytest.raises(ValueError, match="name: set by this baseline"):
        batch_only(data, rng=rng, name="x")
    with pytest.raises(ValueError, match="keep, name: set by this baseline"):
        batch_plus_train(data, data, rng=rng, keep=None, name="x")


def test_fit_gp_baseline_checks_n_actions_and_hyper_against_the_data():
    """n_actions below the data's dropped the higher actions' transitions; a
    HyperSet of other (A, D) failed later with an IndexError or used the wrong
    GPs."""
    rng = np.random.default_rng(6)
    data = _instance(0, 0.0, 40, rng)
    with pytest.raises(ValueError, match=r"n_actions: expected >= 2 \(data\), got 1"):
        fit_gp_baseline(data, rng=rng, n_actions=1)
    one = HyperSet(np.ones((1, D, D)), np.ones((1, D)), np.ones((1, D)))
    with pytest.raises(ValueError, match=r"hyper: expected \(A, D\) = \(2, 2\)"):
        fit_gp_baseline(data, rng=rng, hyper=one)


def test_fit_gp_baseline_fits_hyperparameters_on_n_hyper_transitions(monkeypatch):
    from hipmdp import baselines

    sizes = []

    def record(groups, periodic):
        sizes.append([len(y) for _, y in groups])
        return np.ones(D), 1.0, 0.1

    monkeypatch.setattr(baselines, "fit_hyperparameters", record)
    data = _instance(0, 0.0, 80, np.random.default_rng(6))
    fit_gp_baseline(data, rng=np.random.default_rng(0), n_hyper=7)
    assert sizes == [[7]] * (2 * D)  # one pooled group per (a, d)


def test_each_gp_is_fitted_on_its_own_dimensions_changes(monkeypatch):
    """The GP of (a, d) takes its hyperparameters from action a's states and
    the changes of dimension d, and keeps each in its own place: a fit that
    returns (ℓ, σ_f², σ²) = ((a + 1, d + 2), 3 + a + d, 0.1 (1 + a + d))."""
    from hipmdp import baselines

    data = _instance(0, 0.0, 80, np.random.default_rng(6))
    calls = []

    def record(groups, periodic):
        ((X, y),) = groups
        a, d = divmod(len(calls), D)  # fitted in order: action, then dimension
        calls.append((a, d))
        rows = [np.flatnonzero((data.states == x).all(1))[0] for x in X]
        np.testing.assert_array_equal(data.actions[rows], a)
        np.testing.assert_array_equal(y, data.deltas[rows, d])
        return np.array([a + 1.0, d + 2.0]), 3.0 + a + d, 0.1 * (1 + a + d)

    monkeypatch.setattr(baselines, "fit_hyperparameters", record)
    model = fit_gp_baseline(data, rng=np.random.default_rng(0), n_hyper=20)
    assert calls == [(a, d) for a in range(2) for d in range(D)]
    for a in range(2):
        for d in range(D):
            h = model.hyper.get(a, d)
            np.testing.assert_array_equal(h.lengthscales, [a + 1.0, d + 2.0])
            assert (h.signal_var, h.noise_var) == (3.0 + a + d, 0.1 * (1 + a + d))


def test_an_action_with_one_transition_is_conditioned_on_it():
    """With the hyperparameters given one transition is enough: the GP of that
    action is conditioned on it (not left at the prior)."""
    rng = np.random.default_rng(6)
    data = _instance(0, 0.0, 20, rng).select(actions=[0])
    s = np.array([[0.3, -0.2]])
    one = Transitions(s, np.array([1]), s + 1.0, np.zeros(1, int))
    data = Transitions.concatenate([data, one])
    with pytest.raises(ValueError, match="action 1 has 1 transitions"):
        fit_gp_baseline(data, rng=rng)  # one is not enough to fit them
    hyper = HyperSet(np.ones((2, D, D)), np.ones((2, D)), np.full((2, D), 0.01))
    model = fit_gp_baseline(data, rng=rng, hyper=hyper)
    mean, var = model.predict(s, np.array([1]))
    # one point at Δ = 1: mean σ_f²/(σ_f² + σ_n²), variance
    # σ_f² σ_n²/(σ_f² + σ_n²) + σ_n²
    np.testing.assert_allclose(mean, [[1 / 1.01, 1 / 1.01]], rtol=1e-12)
    np.testing.assert_allclose(var, [[0.01 + 0.01 / 1.01] * 2], rtol=1e-12)


def test_each_actions_gp_sees_only_that_actions_transitions():
    """Kept train transitions of every action were given to every action's GP."""
    rng = np.random.default_rng(2)
    batch, train = _batch(rng), _instance(9, 2.0, 20, rng)
    model = batch_plus_train(batch, train, rng=np.random.default_rng(3), n_max=30)
    both = Transitions.concatenate([batch, train])
    for a in range(2):
        own = both.states[both.actions == a]
        for X in (model.posteriors[a][d].X for d in range(D)):
            assert (X[:, None, :] == own[None]).all(-1).any(1).all()


def test_the_baselines_are_named():
    rng = np.random.default_rng(2)
    batch, train = _batch(rng), _instance(9, 2.0, 20, rng)
    hyper = HyperSet(np.ones((2, D, D)), np.ones((2, D)), np.full((2, D), 0.01))
    names = [
        batch_only(batch, rng=rng, hyper=hyper).name,
        train_only(train, rng=rng, hyper=hyper).name,
        batch_plus_train(batch, train, rng=rng, hyper=hyper).name,
        fit_gp_baseline(train, rng=rng, hyper=hyper).name,
    ]
    assert names == ["batch only", "train only", "batch + train", "gp"]
