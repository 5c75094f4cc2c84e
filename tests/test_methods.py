"""Your own method in the prediction benchmark (tasks/methods.py): the example
method against its dense formulas, the spec and output checks, and a method added
to a run leaving every other number as it was."""

from __future__ import annotations

import dataclasses
import json
import re
import warnings

import numpy as np
import pytest

import hipmdp
from tasks import methods
from tasks.cartpole_prediction import _params, main, parse_args
from tasks.methods import Added, BayesianLinear, MethodSpec, method_seed
from tasks.prediction import PREDICTION_METHODS, score_instance
from tasks.recording import rrd_contents
from tests.test_cartpole_prediction import TINY

LINEAR = "linear=tasks.methods:BayesianLinear"


def features(states: np.ndarray) -> np.ndarray:
    """(1, s0, s1, sin s0, cos s0): BayesianLinear's features of a 2-d state whose
    dimension 0 is an angle, written out."""
    s0, s1 = states[:, 0], states[:, 1]
    return np.column_stack([np.ones(len(s0)), s0, s1, np.sin(s0), np.cos(s0)])


def transitions(w: np.ndarray, n: int, rng, noise: float = 0.0, instances: int = 1):
    """n transitions of 2 actions whose Δs is linear in the features: Δs = x w[a]
    + noise; instance ids 0..instances-1 in turn, every other transition."""
    states = rng.uniform(-1.0, 1.0, size=(n, 2))
    actions = np.arange(n) % 2
    x = features(states)
    deltas = np.einsum("np,npd->nd", x, w[actions]) + noise * rng.normal(size=(n, 2))
    return hipmdp.Transitions(
        states, actions, states + deltas, np.arange(n) // 2 % instances, angle_dims=(0,)
    )


def weights(rng) -> np.ndarray:
    """(A, p, D) = (2, 5, 2), small so that no angle change wraps."""
    return rng.uniform(-0.1, 0.1, size=(2, 5, 2))


def test_bayesian_linear_equals_its_function_space_form():
    """Dense reference: the same Bayesian linear regression as a GP. With the prior
    W ~ N(W_a, σ²/λ), f(x) = x W has mean x W_a and covariance k(x, x') = σ² x x'ᵀ
    / λ; the predictive of Δ at x is

        mean = x W_a + k(x, X) (K + σ² I)⁻¹ (Y - X W_a),
        var = σ² + k(x, x) - k(x, X) (K + σ² I)⁻¹ k(X, x),

    with W_a and σ² from least squares on the action's batch transitions."""
    rng = np.random.default_rng(0)
    batch = transitions(weights(rng), 300, rng, noise=0.05)
    train = transitions(weights(rng), 40, rng, noise=0.05)
    test = transitions(weights(rng), 30, rng)
    lam = 3.0
    method = BayesianLinear(prior_strength=lam)
    method.fit(batch, rng=rng)
    # the documented x = (1, s, sin θ, cos θ), column for column (a user reading
    # the weights W_a needs the order; the predictions alone do not show it)
    np.testing.assert_array_equal(method.features(test.states), features(test.states))
    mean, var = method.adapt(train, rng=rng).predict(test.states, test.actions)

    for a in (0, 1):
        b, t, q = batch.actions == a, train.actions == a, test.actions == a
        xb = features(batch.states[b])
        w_a, *_ = np.linalg.lstsq(xb, batch.deltas[b], rcond=None)
        sigma2 = np.mean((batch.deltas[b] - xb @ w_a) ** 2, axis=0)
        X, Y, x = features(train.states[t]), train.deltas[t], features(test.states[q])
        for d in range(2):
            scale = sigma2[d] / lam  # k(u, v) = scale · u vᵀ
            gain = (
                scale
                * x
                @ X.T
                @ np.linalg.inv(scale * X @ X.T + sigma2[d] * np.eye(len(X)))
            )
            expected_mean = x @ w_a[:, d] + gain @ (Y[:, d] - X @ w_a[:, d])
            expected_var = sigma2[d] + np.diag(
                scale * x @ x.T - gain @ (scale * X @ x.T)
            )
            np.testing.assert_allclose(mean[q, d], expected_mean, rtol=1e-8, atol=1e-12)
            # the fit adds 1e-12 to σ² (documented), far below the tolerance
            np.testing.assert_allclose(var[q, d], expected_var, rtol=1e-7)


def test_bayesian_linear_falls_back_for_actions_with_too_few_batch_transitions():
    """An action with no more batch transitions than features (5) has the prior
    W_a = 0 and the variance of Δs over the whole batch; the other keeps its fit."""
    rng = np.random.default_rng(7)
    batch = transitions(weights(rng), 200, rng, noise=0.01)
    keep = np.flatnonzero(batch.actions == 0).tolist() + [1, 3, 5, 7, 9]
    batch = batch.take(np.array(sorted(keep)))
    assert np.sum(batch.actions == 1) == 5
    method = BayesianLinear()
    method.fit(batch, rng=rng)
    test = transitions(weights(rng), 20, rng)
    empty = batch.take(np.arange(0))
    mean, var = method.adapt(empty, rng=rng).predict(test.states, test.actions)
    one = test.actions == 1
    np.testing.assert_array_equal(mean[one], 0.0)
    # σ² (1 + x (λI)⁻¹ xᵀ) with no train transitions, λ = 10
    lever = np.sum(features(test.states[one]) ** 2, axis=1, keepdims=True) / 10
    np.testing.assert_allclose(
        var[one], (np.var(batch.deltas, axis=0) + 1e-12) * (1 + lever)
    )
    assert np.all(mean[~one] != 0.0)
    with pytest.raises(ValueError, match="actions: expected 0..1 .*, got 2..2"):
        method.adapt(empty, rng=rng).predict(test.states, np.full(20, 2))
    # a negative index would silently pick the last action's weights
    with pytest.raises(ValueError, match="actions: expected 0..1 .*, got -1..0"):
        method.adapt(empty, rng=rng).predict(test.states, test.actions - 1)
    with pytest.raises(ValueError, match="call fit before adapt"):
        BayesianLinear().adapt(empty, rng=rng)
    for bad in (0.0, np.inf, np.nan):
        with pytest.raises(ValueError, match="prior_strength: expected a finite"):
            BayesianLinear(prior_strength=bad)


def test_bayesian_linear_moves_from_the_batch_fit_to_the_instance():
    """Noise-free linear dynamics: with no train transitions the prediction is the
    batch's model; with many and a weak prior, the instance's."""
    rng = np.random.default_rng(1)
    w_batch, w_instance = weights(rng), weights(rng)
    batch = transitions(w_batch, 200, rng)
    test = transitions(w_instance, 50, rng)
    method = BayesianLinear(prior_strength=1e-8)
    method.fit(batch, rng=rng)
    none = batch.take(np.arange(0))
    mean, var = method.adapt(none, rng=rng).predict(test.states, test.actions)
    x = features(test.states)
    batch_model = np.einsum("np,npd->nd", x, w_batch[test.actions])
    np.testing.assert_allclose(mean, batch_model, atol=1e-10)
    assert np.all(var > 0)
    train = transitions(w_instance, 200, rng)
    mean, _ = method.adapt(train, rng=rng).predict(test.states, test.actions)
    np.testing.assert_allclose(mean, test.deltas, atol=1e-6)
    assert np.abs(test.deltas - batch_model).max() > 1e-3  # the two differ


@pytest.mark.parametrize(
    "spec, match",
    [
        ("linear", "expected NAME=module:attribute"),
        ("linear=tasks.methods", "expected NAME=module:attribute"),
        ("linear=tasks.methods:", "expected NAME=module:attribute"),
        ("linear=:BayesianLinear", "expected NAME=module:attribute"),
        ("=tasks.methods:BayesianLinear", "the name ''"),
        ("my method=tasks.methods:BayesianLinear", "the name 'my method'"),
        ("_mine=tasks.methods:BayesianLinear", "the name '_mine' .* start with"),
        ("-mine=tasks.methods:BayesianLinear", "the name '-mine' .* start with"),
        ("hipmdp=tasks.methods:BayesianLinear", "'hipmdp' is .* a built-in method"),
        # the recording's name of "batch + train"
        ("batch_train=tasks.methods:BayesianLinear", "'batch_train' is .* built-in"),
        # the transfer's models
        ("true=tasks.methods:BayesianLinear", "'true' is .* a built-in method"),
        ("average=tasks.methods:BayesianLinear", "'average' is .* a built-in method"),
        # as the report labels them, and in another case: two "HiP-MDP" rows
        ("HiP-MDP=tasks.methods:BayesianLinear", "'HiP-MDP' is .* reported as"),
        ("HipMDP=tasks.methods:BayesianLinear", "'HipMDP' is .* a built-in method"),
        (3, "expected strings NAME=module:attribute"),
    ],
)
def test_bad_specs_are_named(spec, match):
    with pytest.raises(ValueError, match=match):
        methods.check_specs([spec])


def test_specs_must_be_a_sequence_of_distinct_names():
    with pytest.raises(ValueError, match="expected a sequence"):
        methods.check_specs(LINEAR)
    with pytest.raises(ValueError, match="'linear' is given more than once"):
        methods.check_specs([LINEAR, "linear=tests.test_methods:Constant"])
    # in any case, as the built-in names: a report with rows "linear" and
    # "Linear" would be as ambiguous
    with pytest.raises(ValueError, match="more than once \\('Linear', 'linear'\\)"):
        methods.check_specs([LINEAR, LINEAR, "Linear=tests.test_methods:Constant"])
    # two names with one CRC-32 would share their streams
    with pytest.raises(ValueError, match="'plumless' and 'buckeroo' would share"):
        methods.check_specs(
            ["plumless=tasks.methods:BayesianLinear", "buckeroo=tasks.methods:A"]
        )
    assert methods.check_specs([LINEAR]) == (
        MethodSpec("linear", "tasks.methods", "BayesianLinear"),
    )
    # load_all, which a run calls on its specs, checks them as check_specs does
    with pytest.raises(ValueError, match="more than once \\('Linear', 'linear'\\)"):
        methods.load_all([LINEAR, "Linear=tasks.methods:BayesianLinear"])
    with pytest.raises(ValueError, match="'HiP-MDP' is .* reported as"):
        methods.load_all(["HiP-MDP=tasks.methods:BayesianLinear"])


def test_names_may_hold_letters_digits_and_dots_dashes_underscores():
    """parse_spec's rule: a letter or digit first, then also '_', '.' and '-'."""
    names = ["1st", "gp.v2", "my-method_B"]
    specs = methods.check_specs([f"{n}=tasks.methods:BayesianLinear" for n in names])
    assert [s.name for s in specs] == names


def test_a_methods_stream_is_the_documented_descendant_of_the_seed():
    """method_seed's docstring: the seed's descendant with spawn key
    (METHOD_STREAM, crc32(name), *key), which a user can rebuild outside the run.
    Its first key is past the run's own streams (the seed's children 0..4 in
    cartpole_prediction, one per RunStreams field in the swing-up), so no added
    method's stream is one of theirs or below one of them."""
    import zlib

    from tasks.acrobot_swingup import RunStreams

    ss = method_seed(11, "linear", 1, 3, 2)
    assert ss.entropy == 11
    assert ss.spawn_key == (methods.METHOD_STREAM, zlib.crc32(b"linear"), 1, 3, 2)
    assert methods.METHOD_STREAM >= max(5, len(RunStreams._fields))


class Constant:
    """Predicts Δs = 0 with variance 1, or what a test sets; and scribbles over
    every array it is given, as a careless method might."""

    def __init__(self, mean=0.0, var=1.0, shape=None, out=tuple):
        self.mean, self.var, self.shape, self.out = mean, var, shape, out

    def fit(self, batch, *, rng):
        batch.states[:] = 0.0
        batch.next_states[:] = 1.0

    def adapt(self, train, *, rng):
        train.states[:] = 0.0
        return self

    def predict(self, states, actions):
        shape = self.shape or states.shape
        states -= 1.0
        actions[:] = 0
        return self.out((np.full(shape, self.mean), np.full(shape, self.var)))


class NoAdapt:
    def fit(self, batch, *, rng):
        pass


def agent_on_the_object():
    """A policy built as an object whose agent is an instance attribute."""
    method = NoAdapt()
    method.agent = lambda *, rng: None
    return method


class FitWithoutRng(Constant):
    def fit(self, batch):
        pass


class AdaptWithoutRng(Constant):
    def adapt(self, train):
        return self


class TakesKeywords(Constant):
    """Takes rng (and anything else) as **kwargs: fine."""

    def fit(self, batch, **kwargs):
        pass

    def adapt(self, train, **kwargs):
        return self


class AdaptIsNotAMethod(NoAdapt):
    adapt = None  # a placeholder attribute, not something to call


class AdaptsToNothing(NoAdapt):
    def adapt(self, train, *, rng):
        return None


class FailsInPlanning(Constant):
    """Each predictor answers once (as fit_all's trials ask it), then raises: a
    method that breaks only when planned on."""

    def adapt(self, train, *, rng):
        return OneAnswer()


class OneAnswer:
    def __init__(self):
        self.calls = 0

    def predict(self, states, actions):
        self.calls += 1
        if self.calls > 1:
            raise RuntimeError("second call")
        return np.zeros(states.shape), np.ones(states.shape)


class DisagreeingMean(Constant):
    """predict_mean and predict's mean differ."""

    def adapt(self, train, *, rng):
        return self

    def predict_mean(self, states, actions):
        return np.ones(states.shape)


class FlatMean(DisagreeingMean):
    """predict_mean has predict's values but shape (D,) for one state, where
    planning wants (1, D) (hipmdp.planning.LearnedModel refuses it mid-trial)."""

    def predict_mean(self, states, actions):
        return np.full(states.shape, self.mean).ravel()


class Failing:
    """Its fit, adapt or predictor raises, as the user's code might."""

    def __init__(self, where="predict"):
        self.where = where

    def fit(self, batch, *, rng):
        if self.where == "fit":
            raise RuntimeError("fit failed")

    def adapt(self, train, *, rng):
        if self.where == "adapt":
            raise RuntimeError("adapt failed")
        return self

    def predict(self, states, actions):
        raise RuntimeError("predict failed")


def test_methods_that_cannot_be_loaded_are_refused(tmp_path, monkeypatch):
    (tmp_path / "broken_method.py").write_text("raise RuntimeError('boom')\n")
    (tmp_path / "imports_a_missing_one.py").write_text("import no_such_dep\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for spec, match in [
        # a package found without the module (a mistyped name): no hint either
        ("x=tasks.no_such_module:A", "No module named 'tasks.no_such_module'\\)$"),
        ("x=no_such_module:A", "add that folder to PYTHONPATH"),
        ("x=no_such_package.mine:A", "No module named 'no_such_package'\\); Python"),
        # found, but what it imports is not: no hint about where to run from
        ("x=imports_a_missing_one:A", "No module named 'no_such_dep'\\)$"),
        ("x=broken_method:A", "importing 'broken_method' raised RuntimeError: boom"),
        ("x=tasks.methods:NoSuchClass", "has no class or function 'NoSuchClass'"),
        # there, but an int
        ("x=tasks.methods:TRIAL_SIZE", "TRIAL_SIZE is not callable \\(type int\\)"),
        ("x=tests.test_methods:AdaptIsNotAMethod", "AdaptIsNotAMethod has no adapt"),
        ("x=tests.test_methods:NoAdapt", "NoAdapt has no adapt"),
        ("x=tests.test_methods:agent_on_the_object", "must be a method of its class"),
        ("x=tasks.methods:load", "calling load\\(\\) with no arguments raised"),
        # the run calls fit(batch, rng=rng) and adapt(train, rng=rng)
        (
            "x=tests.test_methods:FitWithoutRng",
            "FitWithoutRng.fit\\(batch\\) cannot take the run's call fit\\(batch, "
            "rng=rng\\); expected fit\\(batch, \\*, rng\\)",
        ),
        (
            "x=tests.test_methods:AdaptWithoutRng",
            "AdaptWithoutRng.adapt\\(train\\) cannot take .* expected adapt\\(tr",
        ),
    ]:
        with pytest.raises(ValueError, match=match):
            methods.load_all([spec])
    ((_, method),) = methods.load_all(["x=tests.test_methods:TakesKeywords"])
    assert type(method).__name__ == "TakesKeywords"


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(shape=(3, 4)), "mean has shape \\(3, 4\\), expected \\(5, 4\\)"),
        # as many numbers, transposed
        (dict(shape=(4, 5)), "mean has shape \\(4, 5\\), expected \\(5, 4\\)"),
        (dict(mean=np.nan), "mean is not finite"),
        (dict(mean=1j), "mean is complex"),
        (dict(mean="a"), "mean is not an array of numbers"),
        (dict(var=0.0), "var must be > 0"),
        (dict(var=np.inf), "var is not finite"),
        (dict(var=1e-320), "log-likelihood of the test transitions is not finite"),
        (dict(mean=1e200), "mean is so far off that its squared error is not"),
        (dict(out=lambda pair: pair[0]), "must return \\(mean, var\\), got ndarray"),
        (dict(out=lambda pair: (*pair, 0)), "must return \\(mean, var\\), got tuple"),
    ],
)
def test_bad_predictions_are_refused_naming_the_method(kw, match):
    rng = np.random.default_rng(2)
    s = rng.normal(size=(5, 4))
    test = hipmdp.Transitions(s, np.zeros(5, int), s + 0.1, np.zeros(5, int))
    added = Added(MethodSpec("mine", "m", "A"), Constant(**kw), 0)
    with pytest.raises(ValueError, match="method mine: predict" + ".*" + match):
        added.predict(test, test, (0, 0))


class Memo(Constant):
    """Keeps what it adapts to, on itself (fine-tuning in place, a context
    buffer), and predicts the number of instances it has seen."""

    def __init__(self):
        super().__init__()
        self.seen = []

    def adapt(self, train, *, rng):
        self.seen.append(len(train))
        return self

    def predict(self, states, actions):
        return np.full(states.shape, float(len(self.seen))), np.ones(states.shape)


def test_each_prediction_adapts_a_fresh_copy_of_the_fitted_method():
    """The prediction tables adapt the method setting after setting: on one
    shared object, a Memo carried each setting's data into the next (its
    prediction 1, 2, 3, ...), as no transfer trial can."""
    s = np.random.default_rng(2).normal(size=(5, 4))
    test = hipmdp.Transitions(s, np.zeros(5, int), s + 0.1, np.zeros(5, int))
    memo = Memo()
    added = Added(MethodSpec("memo", "m", "A"), memo, 0)
    for key in [(0, 0), (0, 1), (1, 0)]:
        mean, _ = added.predict(test, test, key)
        np.testing.assert_array_equal(mean, 1.0)
    assert memo.seen == []  # the fitted object itself is never adapted


def test_an_adapt_without_a_predictor_is_refused():
    s = np.random.default_rng(2).normal(size=(5, 4))
    test = hipmdp.Transitions(s, np.zeros(5, int), s + 0.1, np.zeros(5, int))
    added = Added(MethodSpec("mine", "m", "A"), AdaptsToNothing(), 0)
    with pytest.raises(ValueError, match="mine: adapt must return an object with"):
        added.predict(test, test, (0, 0))


def test_a_list_is_taken_as_mean_and_variance():
    s = np.random.default_rng(2).normal(size=(5, 4))
    test = hipmdp.Transitions(s, np.zeros(5, int), s + 0.1, np.zeros(5, int))
    added = Added(MethodSpec("mine", "m", "A"), Constant(var=2.0, out=list), 0)
    mean, var = added.predict(test, test, (0, 0))
    np.testing.assert_array_equal(mean, 0.0)
    np.testing.assert_array_equal(var, 2.0)


def test_errors_in_the_users_code_keep_their_type_and_name_the_method():
    batch = transitions(weights(np.random.default_rng(0)), 40, np.random.default_rng(1))
    for where in ("fit", "adapt", "predict"):
        loaded = [(MethodSpec("mine", "m", "A"), Failing(where))]
        with pytest.raises(RuntimeError, match=f"{where} failed") as err:
            methods.fit_all(loaded, batch, 0)  # fit, then the trial prediction
        assert f"in method mine: {where}" in "".join(err.value.__notes__)


def test_fit_all_tries_the_transfers_first_planning_too():
    """A predict_mean that disagrees with predict, or gives its values in
    another shape, is refused before any run."""
    batch = transitions(weights(np.random.default_rng(0)), 40, np.random.default_rng(1))
    for wrong, match in [
        (DisagreeingMean(), "mine: predict_mean gives .* must agree"),
        (FlatMean(), "mine: predict_mean gives shape \\(2,\\), expected \\(1, 2\\)"),
    ]:
        loaded = [(MethodSpec("mine", "m", "A"), wrong)]
        with pytest.raises(ValueError, match=match):
            methods.fit_all(loaded, batch, 0, transfer=True)


class TrainMean:
    """A method with nothing to say before it has seen the instance: it predicts
    the mean Δs of the train transitions it was adapted to, NaN on none."""

    def fit(self, batch, *, rng):
        pass

    def adapt(self, train, *, rng):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # the mean of no rows
            return TrainMean.Predictor(train.deltas.mean(0))

    @dataclasses.dataclass
    class Predictor:
        mean: np.ndarray

        def predict(self, states, actions):
            return np.tile(self.mean, (len(states), 1)), np.ones(states.shape)


def test_fit_all_adapts_to_no_transitions_only_for_transfer_trials():
    """Only the swing-up's transfer trials adapt a method to no transitions
    (their first planning): without them TrainMean passes its try; with them it
    is refused, the error saying what it was adapted to."""
    batch = transitions(weights(np.random.default_rng(0)), 40, np.random.default_rng(1))
    loaded = [(MethodSpec("naive", "m", "A"), TrainMean())]
    (fitted,) = methods.fit_all(loaded, batch, 0)
    assert isinstance(fitted.method, TrainMean)
    with pytest.raises(ValueError, match="naive: predict's mean is not fin") as err:
        methods.fit_all(loaded, batch, 0, transfer=True)
    note = "".join(err.value.__notes__)
    assert "the try of method naive after adapt on 0 transitions" in note
    # an error in the user's code says it too, beside its own note
    with pytest.raises(RuntimeError, match="predict failed") as err:
        methods.fit_all([(MethodSpec("bad", "m", "A"), Failing())], batch, 0)
    note = "".join(err.value.__notes__)
    assert "in method bad: predict" in note
    assert f"the try of method bad after adapt on {methods.TRIAL_SIZE} trans" in note


@pytest.mark.parametrize("experiment", ["cartpole", "swingup"])
def test_each_experiment_tries_a_method_as_it_will_adapt_it(
    experiment, tmp_path, monkeypatch
):
    """The cart-pole, which never adapts to no transitions, takes TrainMean
    past its try (on to the HiP-MDP fit, stopped here); the swing-up, whose
    transfer trials plan on it adapted to none, refuses it."""
    import tasks.acrobot_swingup as swingup
    import tasks.cartpole_prediction as cp
    from tests.test_acrobot_swingup import TINY as SWINGUP

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):
        raise Stop

    monkeypatch.setattr(hipmdp, "fit", stop)
    method = ("naive=tests.test_methods:TrainMean",)
    if experiment == "cartpole":
        with pytest.raises(Stop):
            cp.main(dataclasses.replace(TINY, methods=method, record=False), tmp_path)
    else:
        config = dataclasses.replace(SWINGUP, methods=method, record=False)
        with pytest.raises(ValueError, match="naive: predict's mean is not") as err:
            swingup.main(config, tmp_path)
        assert "after adapt on 0 transitions" in "".join(err.value.__notes__)


def test_errors_while_planning_on_an_added_method_name_it(tmp_path):
    from tasks.acrobot_swingup import main as swingup
    from tests.test_acrobot_swingup import TINY as SWINGUP

    config = dataclasses.replace(
        SWINGUP, record=False, methods=("late=tests.test_methods:FailsInPlanning",)
    )
    with pytest.raises(RuntimeError, match="second call") as err:
        swingup(config, tmp_path)
    note = "".join(err.value.__notes__)
    assert "planning on method late, added with --method; setting 0, trial 0" in note


def test_each_call_gets_its_own_stream_from_the_seed_and_the_name():
    """The rng a method's adapt is given: the same for the same (seed, name,
    key), different for another setting, table, name or seed."""

    class Draws(Constant):
        def adapt(self, train, *, rng):  # on a copy: the draw is kept on the class
            type(self).drawn = rng.random()
            return super().adapt(train, rng=rng)

    s = np.random.default_rng(2).normal(size=(5, 4))
    test = hipmdp.Transitions(s, np.zeros(5, int), s + 0.1, np.zeros(5, int))

    def draw(name, seed, key):
        Added(MethodSpec(name, "m", "A"), Draws(), seed).predict(test, test, key)
        return Draws.drawn

    first = draw("a", 0, (0, 0))
    assert first == draw("a", 0, (0, 0))
    others = [draw("a", 0, (0, 1)), draw("a", 0, (1, 0)), draw("b", 0, (0, 0))]
    others.append(draw("a", 1, (0, 0)))
    assert len({first, *others}) == 5
    expected = np.random.default_rng(method_seed(0, "a", 1, 0, 0)).random()
    assert first == expected


def test_an_added_method_is_scored_like_the_others_and_changes_nothing_else():
    """score_instance with an added method: the built-in scores are identical to
    those without it (and the rng stream after), and the method's MSE,
    log-likelihood and coverage are those of its predictions."""
    from hipmdp import baselines
    from hipmdp.data import gaussian_loglik
    from tasks.prediction import coverage

    rng = np.random.default_rng(3)
    batch = transitions(weights(rng), 200, rng, noise=0.01, instances=3)
    train = transitions(weights(rng), 20, rng, noise=0.01)
    test = transitions(weights(rng), 20, rng, noise=0.01)
    hip = hipmdp.fit(batch, TINY.fit, rng=np.random.default_rng(4))
    average = baselines.batch_only(batch, rng=np.random.default_rng(5), n_max=100)
    linear = BayesianLinear()
    linear.fit(batch, rng=rng)
    added = [
        Added(MethodSpec("linear", "tasks.methods", "BayesianLinear"), linear, 7),
        Added(MethodSpec("zero", "tests.test_methods", "Constant"), Constant(), 7),
    ]
    streams = [np.random.default_rng(6), np.random.default_rng(6)]
    alone = score_instance([hip], average, batch, train, test, rng=streams[0])
    both = score_instance(
        [hip], average, batch, train, test, rng=streams[1], added=added, key=(0, 3)
    )
    assert streams[0].random() == streams[1].random()
    for m in PREDICTION_METHODS:
        np.testing.assert_array_equal(alone.mse[m], both.mse[m])
        np.testing.assert_array_equal(alone.coverage[m], both.coverage[m])
        assert alone.loglik[m] == both.loglik[m]
    mean, var = linear.adapt(train, rng=rng).predict(test.states, test.actions)
    np.testing.assert_allclose(
        both.mse["linear"], np.mean((test.deltas - mean) ** 2, 0)
    )
    np.testing.assert_allclose(
        both.coverage["linear"], coverage(mean, var, test.deltas)
    )
    assert both.loglik["linear"] == pytest.approx(
        gaussian_loglik(test.deltas, mean, var)
    )
    # Constant predicts Δs = 0, whatever it did to its copies of the inputs
    np.testing.assert_allclose(both.mse["zero"], np.mean(test.deltas**2, 0))


def without(tree, names):
    """``tree`` with every dict key in ``names`` removed, at any depth."""
    if isinstance(tree, dict):
        return {k: without(v, names) for k, v in tree.items() if k not in names}
    if isinstance(tree, list):
        return [without(v, names) for v in tree]
    return tree


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """TINY without and with two added methods (one scribbling over its inputs)."""
    plain = main(TINY, out=tmp_path_factory.mktemp("plain"))
    config = dataclasses.replace(
        TINY, methods=(LINEAR, "zero=tests.test_methods:Constant")
    )
    return plain, main(config, out=tmp_path_factory.mktemp("added"))


def test_a_run_with_added_methods_reports_them_and_changes_nothing_else(runs):
    plain, added = runs
    a, b = plain.metrics, added.metrics
    for m in (a, b):
        del m["seconds"], m["environment"]
    assert without(b, {"linear", "zero"}) == a
    for key in (
        "mse", "loglik_difference", "coverage", "per_setting_mse",
        "per_setting_loglik",
    ):  # fmt: skip
        assert set(b[key]) - set(a[key]) == {"linear", "zero"}, key
    assert set(b["unseen"]["mse"]) == set(b["mse"])
    assert set(b["mse_ratio_per_setting"]) == set(a["mse_ratio_per_setting"]) | {
        "linear",
        "zero",
    }
    config = json.loads((added.out / "config.json").read_text())
    assert config["methods"] == [LINEAR, "zero=tests.test_methods:Constant"]
    report = (added.out / "report.md").read_text()
    assert "linear (`tasks.methods:BayesianLinear`)" in report
    assert "| linear |" in report and "| zero |" in report
    entities = rrd_contents(added.out / "cartpole.rrd")
    assert {"/mse/2/linear", "/mse/3/zero"} <= set(entities)

    # the report's tables, but for the added rows and the sentence naming them
    # (the non-empty lines; the run times after them differ)
    def tables(run, added=("| linear ", "| zero ", "Added with", "† The intervals")):
        text = (run.out / "report.md").read_text()
        text = text[text.index("## MSE") : text.index("## Latent structure")]
        return [ln for ln in text.splitlines() if ln and not ln.startswith(added)]

    assert tables(added) == tables(plain)
    assert "Added with" not in (plain.out / "report.md").read_text()


def test_same_seed_same_scores_for_an_added_method(runs, tmp_path):
    _, added = runs
    config = dataclasses.replace(TINY, methods=(LINEAR,), record=False)
    again = main(config, out=tmp_path)
    assert again.metrics["mse"]["linear"] == added.metrics["mse"]["linear"]


def test_the_command_line_takes_methods_and_refuses_bad_ones(capsys, tmp_path):
    config, _ = parse_args(
        ["--method", LINEAR, "--method", "z=tasks.methods:BayesianLinear"]
    )
    assert config.methods == (LINEAR, "z=tasks.methods:BayesianLinear")
    assert parse_args([])[0].methods == ()
    for bad, match in [
        ("linear", "--method \\(methods\\): expected NAME=module:attribute"),
        ("x=tasks.nothing:A", "--method \\(methods\\): .*cannot import"),
        # a class that will not build or is not a model: refused as usage too,
        # before the run gathers any data
        ("x=tests.test_methods:NoAdapt", "--method .*: .*NoAdapt has no adapt"),
        ("x=tasks.methods:load", "--method .*: calling load\\(\\) with no arg"),
        ("x=tests.test_policies:BothKinds", "--method .*: .* both adapt and agent"),
        ("x=tasks.methods:SarsaPolicy", "--method .*: .* only tasks.acrobot_swingup"),
        ("x=tests.test_methods:FitWithoutRng", "--method .*: .*fit\\(batch\\) cannot"),
    ]:
        with pytest.raises(SystemExit) as exit_:
            parse_args(["--method", bad, "--out", str(tmp_path / "x")])
        assert exit_.value.code == 2
        assert re.search(match, capsys.readouterr().err)


def test_main_refuses_an_unloadable_method_before_any_work(tmp_path):
    config = dataclasses.replace(TINY, methods=("x=tasks.nothing:A",))
    with pytest.raises(ValueError, match="cannot import"):
        main(config, out=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_method_that_breaks_does_so_before_the_fits(tmp_path):
    """fit_all's trial prediction runs right after the batch data: the run stops
    before it fits a HiP-MDP (no model file is written)."""
    bad = "bad=tests.test_methods:Failing"
    with pytest.raises(RuntimeError, match="predict failed"):
        main(dataclasses.replace(TINY, methods=(bad,)), out=tmp_path)
    assert (tmp_path / "batch.npz").exists()
    assert not list(tmp_path.glob("hipmdp_run*.npz"))


class FailsOnTheSecondSetting(Constant):
    """Adapts as fit_all's try and the first test setting ask, then raises."""

    adapted = 0

    def adapt(self, train, *, rng):
        FailsOnTheSecondSetting.adapted += 1  # on the class: each call has a copy
        if FailsOnTheSecondSetting.adapted > 2:
            raise KeyError("third adapt")
        return self


def test_an_error_in_a_prediction_table_names_the_setting(tmp_path):
    FailsOnTheSecondSetting.adapted = 0
    late = "late=tests.test_methods:FailsOnTheSecondSetting"
    config = dataclasses.replace(TINY, methods=(late,), record=False)
    with pytest.raises(KeyError, match="third adapt") as err:
        main(config, out=tmp_path)
    note = "".join(err.value.__notes__)
    assert "in method late: adapt" in note
    params = _params(*TINY.test_settings[1])
    assert f"(scoring test settings: setting 1 of 0-1, {params}; " in note
    assert f"{TINY.n_train} train and {TINY.n_test} test transitions)" in note


def test_readmes_example_method_runs_as_written(tmp_path, monkeypatch):
    """README's `mine.py`, saved where its commands put it, scored in a tiny run;
    its cart-pole commands (the quick first try, the paper run) parse as
    written."""
    import shlex

    from tests.test_docs import ROOT, python_block

    readme = ROOT / "README.md"
    (tmp_path / "mine.py").write_text(
        python_block(readme, "### Scoring your own method")
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    text = readme.read_text()
    commands = [
        line for line in text.splitlines()
        if line.startswith("python -m tasks.cartpole_prediction") and "mine:" in line
    ]  # fmt: skip
    outs = []
    for command in commands:
        config, out = parse_args(shlex.split(command)[3:])
        assert config.methods == ("mean=mine:MeanDelta",)
        outs.append(str(out))
    assert outs == ["runs/cp_mine_quick", "runs/cp_mine"]
    config = dataclasses.replace(TINY, methods=config.methods, record=False)
    run = main(config, out=tmp_path / "run")
    mse = run.metrics["mse"]["mean"]
    assert all(v["mean"] > 0 for v in mse.values())


def test_the_acrobot_run_takes_added_methods_and_nothing_else_changes(
    tiny_swingup, tmp_path
):
    """The swing-up run without an added method (one process) and with one (two
    worker processes, each trial on a fresh copy of the method): in the
    prediction tables, the approximation floor and the transfer trials, the same
    numbers for every other method, and the added method's own rows beside them.
    The tiny config's episodes all run to the step limit, so the returns alone
    would not show a change: the traced trial's states, one-step predictions
    and belief of every built-in method are compared too."""
    from tests._swingup import traced_main
    from tests.test_acrobot_swingup import TINY as SWINGUP

    assert SWINGUP.workers == 1  # the session's run (conftest.py): one process
    config = dataclasses.replace(SWINGUP, workers=2, methods=(LINEAR,))
    with_linear = traced_main(config, tmp_path / "added")
    plain, added = tiny_swingup.results, with_linear.results
    traced = [{r.method: r for r in x.trials} for x in (tiny_swingup, with_linear)]
    a, b = plain.metrics, added.metrics
    for m in (a, b):
        del m["seconds"], m["environment"]
    pairs = {"hipmdp - linear", "linear - average", "linear - true"}
    assert without(b, {"linear", *pairs}) == a
    for key in ("mse", "approximation_floor", "coverage", "returns", "median_returns"):
        assert set(b[key]) - set(a[key]) == {"linear"}, key
    for key in ("paired_difference", "paired_difference_per_setting"):
        assert set(b[key]) - set(a[key]) == pairs, key
    split = b["step_limit_split"]["pairs"]
    assert set(split) - set(a["step_limit_split"]["pairs"]) == pairs
    for method, result in traced[0].items():
        other = traced[1][method]
        np.testing.assert_array_equal(result.steps, other.steps)
        for x, y in zip(result.traces, other.traces, strict=True):
            for field in ("states", "predicted", "belief_mean", "belief_std"):
                np.testing.assert_array_equal(getattr(x, field), getattr(y, field))
    assert set(traced[0]) == {"true", "average", "hipmdp"}
    assert set(traced[1]) == {"true", "average", "hipmdp", "linear"}
    trials = [np.load(run.out / "trials.npz") for run in (plain, added)]
    assert trials[1]["methods"].tolist() == ["true", "average", "hipmdp", "linear"]
    for field in ("returns", "steps"):
        np.testing.assert_array_equal(trials[1][field][:3], trials[0][field])
    report = (added.out / "report.md").read_text()
    assert "linear (`tasks.methods:BayesianLinear`)" in report
    assert "| linear |" in report and "| hipmdp - linear |" in report
    assert {"/rollout/linear/real", "/returns/linear"} <= set(
        rrd_contents(added.out / "acrobot.rrd")
    )


def test_seed_spread_tabulates_an_added_method_beside_the_others(runs, tmp_path):
    from tests._seed_spread import assert_reads_the_run

    _, added = runs
    result = assert_reads_the_run(added.out, tmp_path, "cartpole_prediction")
    labels = {n["label"] for n in result["numbers"]}
    assert {"log-likelihood, HiP-MDP - linear", "log-likelihood, HiP-MDP - zero"} <= (
        labels
    )


def test_bayesian_linear_keeps_a_variance_on_a_batch_it_fits_exactly():
    """A batch whose Δs the features fit exactly (here nothing moves) still
    gives every prediction a variance > 0 (σ² plus 1e-12): fit_all's tries,
    which refuse a variance of 0, pass."""
    rng = np.random.default_rng(2)
    states = rng.uniform(-1.0, 1.0, size=(40, 2))
    still = hipmdp.Transitions(
        states, np.arange(40) % 2, states.copy(), np.zeros(40, int), angle_dims=(0,)
    )
    spec = MethodSpec("linear", "tasks.methods", "BayesianLinear")
    (fitted,) = methods.fit_all([(spec, BayesianLinear())], still, 0)
    _, var = fitted.method.adapt(still, rng=rng).predict(states, still.actions)
    assert np.all(var >= 1e-12)
    # an action with no more batch transitions than features (p = 5) falls back
    # to the batch's variance of Δs, here 0: that too gets the 1e-12
    few = still.take(np.arange(36))
    few.actions[-3:] = 2
    (fitted,) = methods.fit_all([(spec, BayesianLinear())], few, 0)
    _, var = fitted.method.adapt(few, rng=rng).predict(states[:3], np.full(3, 2))
    assert np.all(var >= 1e-12)


class Spy:
    """Keeps the states every adapt and predict call sees, on the class (the
    tries run on copies of the object)."""

    seen: list = []

    def fit(self, batch, *, rng):
        pass

    def adapt(self, train, *, rng):
        Spy.seen.append(("adapt", train.states.copy()))
        return self

    def predict(self, states, actions):
        Spy.seen.append(("predict", states.copy()))
        return np.zeros(states.shape), np.ones(states.shape)


def test_fit_all_tries_a_prediction_on_transitions_it_did_not_adapt_to():
    """The first try adapts to the first TRIAL_SIZE batch transitions and
    predicts the next TRIAL_SIZE; the second, for transfer trials, adapts to
    none and predicts the first state."""
    rng = np.random.default_rng(3)
    batch = transitions(weights(rng), 25, rng)
    Spy.seen = []
    methods.fit_all([(MethodSpec("spy", "m", "A"), Spy())], batch, 0, transfer=True)
    size = methods.TRIAL_SIZE
    assert [kind for kind, _ in Spy.seen] == ["adapt", "predict"] * 2
    (_, train), (_, test), (_, none), (_, one) = Spy.seen
    np.testing.assert_array_equal(train, batch.states[:size])
    np.testing.assert_array_equal(test, batch.states[size : 2 * size])
    assert none.shape == (0, 2)
    np.testing.assert_array_equal(one, batch.states[:1])


def test_fit_all_tries_a_batch_smaller_than_its_tries():
    """A batch of fewer than TRIAL_SIZE transitions: the first try adapts to all
    of them and predicts none (an empty prediction, which BayesianLinear gives
    as shape (0, D)); with fewer than 2 TRIAL_SIZE, it predicts the rest."""
    rng = np.random.default_rng(4)
    size = methods.TRIAL_SIZE
    spec = MethodSpec("linear", "tasks.methods", "BayesianLinear")
    for n in (size - 2, size + 2):
        batch = transitions(weights(rng), n, rng, noise=0.01)
        (fitted,) = methods.fit_all([(spec, BayesianLinear())], batch, 0)
        assert isinstance(fitted.method, BayesianLinear)
        Spy.seen = []
        methods.fit_all([(MethodSpec("spy", "m", "A"), Spy())], batch, 0)
        (_, train), (_, test) = Spy.seen[:2]
        np.testing.assert_array_equal(train, batch.states[: min(n, size)])
        np.testing.assert_array_equal(test, batch.states[size:])  # none if n < size
        assert len(test) == max(0, n - size)
    mean, var = fitted.method.adapt(batch, rng=rng).predict(
        np.zeros((0, 2)), np.zeros(0, int)
    )  # BayesianLinear's empty prediction, which the first try asks of it
    assert mean.shape == var.shape == (0, 2)


@pytest.mark.parametrize(
    "start, expected",
    [("fork", [False, False]), ("spawn", [False, True]), ("forkserver", [False, True])],
)
def test_methods_are_pickled_for_several_workers_that_are_not_forked(
    monkeypatch, start, expected
):
    monkeypatch.setattr(methods.multiprocessing, "get_start_method", lambda: start)
    assert [methods.must_pickle(w) for w in (1, 2)] == expected
