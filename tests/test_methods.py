"""Your own method in the prediction benchmark (tasks/methods.py): the example
method against its dense formulas, the spec and output checks, and a method added
to a run leaving every other number as it was."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

import hipmdp
from tasks import methods
from tasks.cartpole_prediction import main, parse_args
from tasks.methods import Added, BayesianLinear, MethodSpec, method_seed
from tasks.prediction import PREDICTION_METHODS, score_instance
from tasks.recording import rrd_contents
from tests.test_cartpole_prediction import TINY

LINEAR = "linear=tasks.methods:BayesianLinear"


def transitions(w: np.ndarray, n: int, rng, noise: float = 0.0, instances: int = 1):
    """n transitions of 2 actions whose Δs is linear in BayesianLinear's features
    of a 2-d state (dimension 0 an angle): Δs = x w[a] + noise; instance ids
    0..instances-1 in turn, every other transition."""
    states = rng.uniform(-1.0, 1.0, size=(n, 2))
    actions = np.arange(n) % 2
    x = np.column_stack(
        [np.ones(n), states, np.sin(states[:, 0]), np.cos(states[:, 0])]
    )
    deltas = np.einsum("np,npd->nd", x, w[actions]) + noise * rng.normal(size=(n, 2))
    return hipmdp.Transitions(
        states, actions, states + deltas, np.arange(n) // 2 % instances, angle_dims=(0,)
    )


def weights(rng) -> np.ndarray:
    """(A, p, D) = (2, 5, 2), small so that no angle change wraps."""
    return rng.uniform(-0.1, 0.1, size=(2, 5, 2))


def test_bayesian_linear_equals_the_augmented_least_squares_solution():
    """Dense reference: the posterior mean minimises |XW - Y|² + λ|W - W_a|², the
    least-squares solution of the stacked system [X; √λ I] W = [Y; √λ W_a]; the
    variance is σ² (1 + x (XᵀX + λI)⁻¹ xᵀ) with an explicit inverse."""
    rng = np.random.default_rng(0)
    batch = transitions(weights(rng), 300, rng, noise=0.05)
    train = transitions(weights(rng), 40, rng, noise=0.05)
    test = transitions(weights(rng), 30, rng)
    lam = 3.0
    method = BayesianLinear(prior_strength=lam)
    method.fit(batch, rng=rng)
    mean, var = method.predict(train, test.states, test.actions, rng=rng)

    feats = method.features
    for a in (0, 1):
        b, t, q = batch.actions == a, train.actions == a, test.actions == a
        w_a, *_ = np.linalg.lstsq(feats(batch.states[b]), batch.deltas[b], rcond=None)
        sigma2 = np.mean((batch.deltas[b] - feats(batch.states[b]) @ w_a) ** 2, 0)
        X, Y, p = feats(train.states[t]), train.deltas[t], 5
        stacked_x = np.vstack([X, np.sqrt(lam) * np.eye(p)])
        stacked_y = np.vstack([Y, np.sqrt(lam) * w_a])
        w, *_ = np.linalg.lstsq(stacked_x, stacked_y, rcond=None)
        x = feats(test.states[q])
        np.testing.assert_allclose(mean[q], x @ w, rtol=1e-9, atol=1e-12)
        inverse = np.linalg.inv(X.T @ X + lam * np.eye(p))
        lever = np.array([xi @ inverse @ xi for xi in x])
        np.testing.assert_allclose(
            var[q], (sigma2 + 1e-12) * (1 + lever[:, None]), rtol=1e-9
        )


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
    mean, var = method.predict(none, test.states, test.actions, rng=rng)
    x = method.features(test.states)
    batch_model = np.einsum("np,npd->nd", x, w_batch[test.actions])
    np.testing.assert_allclose(mean, batch_model, atol=1e-10)
    assert np.all(var > 0)
    train = transitions(w_instance, 200, rng)
    mean, _ = method.predict(train, test.states, test.actions, rng=rng)
    np.testing.assert_allclose(mean, test.deltas, atol=1e-6)
    assert np.abs(test.deltas - batch_model).max() > 1e-3  # the two differ


@pytest.mark.parametrize(
    "spec, match",
    [
        ("linear", "expected NAME=module:attribute"),
        ("linear=tasks.methods", "expected NAME=module:attribute"),
        ("=tasks.methods:BayesianLinear", "the name ''"),
        ("my method=tasks.methods:BayesianLinear", "the name 'my method'"),
        ("hipmdp=tasks.methods:BayesianLinear", "'hipmdp' is a built-in method"),
        (3, "expected strings NAME=module:attribute"),
    ],
)
def test_bad_specs_are_named(spec, match):
    with pytest.raises(ValueError, match=match):
        methods.check_specs([spec])


def test_specs_must_be_a_sequence_of_distinct_names():
    with pytest.raises(ValueError, match="expected a sequence"):
        methods.check_specs(LINEAR)
    with pytest.raises(ValueError, match="'linear' is given twice"):
        methods.check_specs([LINEAR, "linear=tests.test_methods:Constant"])
    assert methods.check_specs([LINEAR]) == (
        MethodSpec("linear", "tasks.methods", "BayesianLinear"),
    )


class Constant:
    """Predicts Δs = 0 with variance 1, or what a test sets."""

    def __init__(self, mean=0.0, var=1.0, shape=None):
        self.mean, self.var, self.shape = mean, var, shape

    def fit(self, batch, *, rng):
        self.batch_size = len(batch)

    def predict(self, train, states, actions, *, rng):
        shape = self.shape or states.shape
        return np.full(shape, self.mean), np.full(shape, self.var)


class NoPredict:
    def fit(self, batch, *, rng):
        pass


@pytest.mark.parametrize(
    "spec, match",
    [
        ("x=tasks.no_such_module:A", "cannot import 'tasks.no_such_module'"),
        ("x=tasks.methods:NoSuchClass", "has no class or function 'NoSuchClass'"),
        ("x=tests.test_methods:NoPredict", "NoPredict has no predict"),
        (
            "x=tasks.methods:load",
            "calling load\\(\\) with no arguments raised TypeError",
        ),
    ],
)
def test_methods_that_cannot_be_loaded_are_refused(spec, match):
    with pytest.raises(ValueError, match=match):
        methods.load_all([spec])


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(shape=(3, 4)), "mean has shape \\(3, 4\\), expected \\(5, 4\\)"),
        (dict(mean=np.nan), "mean is not finite"),
        (dict(var=0.0), "var must be > 0"),
        (dict(var=np.inf), "var is not finite"),
    ],
)
def test_bad_predictions_are_refused_naming_the_method(kw, match):
    rng = np.random.default_rng(2)
    s = rng.normal(size=(5, 4))
    test = hipmdp.Transitions(s, np.zeros(5, int), s, np.zeros(5, int))
    added = Added(MethodSpec("mine", "m", "A"), Constant(**kw), 0)
    with pytest.raises(ValueError, match="method mine: predict's " + match):
        added.predict(test, test, (0, 0))


def test_method_streams_depend_on_the_seed_and_the_name_only():
    draw = lambda *a: np.random.default_rng(method_seed(*a)).random()  # noqa: E731
    assert draw(0, "a", 1, 0, 2) == draw(0, "a", 1, 0, 2)
    values = {draw(0, "a", 0), draw(0, "b", 0), draw(1, "a", 0), draw(0, "a", 1, 0, 0)}
    assert len(values) == 4
    # never one of the run's own streams (the seed's first children)
    own = {
        np.random.default_rng(s).random() for s in np.random.SeedSequence(0).spawn(8)
    }
    assert not values & own


def test_an_added_method_is_scored_like_the_others_and_changes_nothing_else():
    """score_instance with an added method: the built-in scores are identical to
    those without it (and the rng stream after), and the method's MSE,
    log-likelihood and coverage are those of its predictions."""
    from tasks.prediction import coverage, gaussian_loglik

    rng = np.random.default_rng(3)
    batch = transitions(weights(rng), 200, rng, noise=0.01, instances=3)
    train = transitions(weights(rng), 20, rng, noise=0.01)
    test = transitions(weights(rng), 20, rng, noise=0.01)
    hip = hipmdp.fit(batch, TINY.fit, rng=np.random.default_rng(4))
    from hipmdp import baselines

    average = baselines.batch_only(batch, rng=np.random.default_rng(5), n_max=100)
    linear = BayesianLinear()
    linear.fit(batch, rng=rng)
    added = Added(MethodSpec("linear", "tasks.methods", "BayesianLinear"), linear, 7)
    streams = [np.random.default_rng(6), np.random.default_rng(6)]
    alone = score_instance([hip], average, batch, train, test, rng=streams[0])
    both = score_instance(
        [hip], average, batch, train, test, rng=streams[1], added=[added], key=(0, 3)
    )
    assert streams[0].random() == streams[1].random()
    for m in PREDICTION_METHODS:
        np.testing.assert_array_equal(alone.mse[m], both.mse[m])
        np.testing.assert_array_equal(alone.coverage[m], both.coverage[m])
        assert alone.loglik[m] == both.loglik[m]
    mean, var = linear.predict(train, test.states, test.actions, rng=rng)
    np.testing.assert_allclose(
        both.mse["linear"], np.mean((test.deltas - mean) ** 2, 0)
    )
    np.testing.assert_allclose(
        both.coverage["linear"], coverage(mean, var, test.deltas)
    )
    assert both.loglik["linear"] == pytest.approx(
        gaussian_loglik(test.deltas, mean, var)
    )


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """TINY without and with two added methods."""
    plain = main(TINY, out=tmp_path_factory.mktemp("plain"))
    config = dataclasses.replace(
        TINY, methods=(LINEAR, "zero=tests.test_methods:Constant")
    )
    return plain, main(config, out=tmp_path_factory.mktemp("added"))


def test_a_run_with_added_methods_reports_them_and_changes_nothing_else(runs):
    plain, added = runs
    a, b = plain.metrics, added.metrics
    for key in ("mse", "loglik_difference", "coverage", "per_setting_mse"):
        assert {m: b[key][m] for m in a[key]} == a[key], key
        assert set(b[key]) - set(a[key]) == {"linear", "zero"}
    assert b["mse_ratio_to_best_baseline"] == a["mse_ratio_to_best_baseline"]
    assert set(b["mse_ratio_per_setting"]) == set(a["mse_ratio_per_setting"]) | {
        "linear",
        "zero",
    }
    # Constant predicts Δs = 0: its MSE is the mean square of the test Δs
    assert b["mse"]["zero"]["dx"]["mean"] > 0
    assert set(b["unseen"]["mse"]) == set(b["mse"])
    config = json.loads((added.out / "config.json").read_text())
    assert config["methods"] == [LINEAR, "zero=tests.test_methods:Constant"]
    report = (added.out / "report.md").read_text()
    assert "linear (`tasks.methods:BayesianLinear`)" in report
    assert "| linear |" in report and "| zero |" in report
    entities = rrd_contents(added.out / "cartpole.rrd")
    assert {"/mse/2/linear", "/mse/3/zero"} <= set(entities)
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
    ]:
        with pytest.raises(SystemExit) as exit_:
            parse_args(["--method", bad, "--out", str(tmp_path / "x")])
        assert exit_.value.code == 2
        assert re.search(match, capsys.readouterr().err)
    assert not (tmp_path / "x").exists()


def test_main_refuses_an_unloadable_method_before_any_work(tmp_path):
    config = dataclasses.replace(TINY, methods=("x=tasks.nothing:A",))
    with pytest.raises(ValueError, match="cannot import"):
        main(config, out=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_readmes_example_method_runs_as_written(tmp_path, monkeypatch):
    """README's `mine.py`, saved where its commands put it, scored in a tiny run;
    its cart-pole command parses as written."""
    import shlex

    from tests.test_docs import ROOT, python_block

    readme = ROOT / "README.md"
    (tmp_path / "mine.py").write_text(
        python_block(readme, "### Scoring your own method")
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    text = readme.read_text()
    command = next(
        line for line in text.splitlines()
        if line.startswith("python -m tasks.cartpole_prediction") and "mine:" in line
    )  # fmt: skip
    argv = shlex.split(command)[3:]
    config, out = parse_args(argv)
    assert config.methods == ("mean=mine:MeanDelta",) and str(out) == "runs/cp_mine"
    config = dataclasses.replace(TINY, methods=config.methods, record=False)
    run = main(config, out=tmp_path / "run")
    mse = run.metrics["mse"]["mean"]
    assert all(v["mean"] > 0 for v in mse.values())


def test_the_acrobot_tables_score_added_methods_and_nothing_else_changes(tmp_path):
    """The swing-up run's test table and approximation floor, with and without
    an added method: the same numbers for every other method and trial."""
    from tasks.acrobot_swingup import main as swingup
    from tests.test_acrobot_swingup import TINY as SWINGUP

    plain = swingup(dataclasses.replace(SWINGUP, record=False), tmp_path / "plain")
    config = dataclasses.replace(SWINGUP, record=False, methods=(LINEAR,))
    added = swingup(config, tmp_path / "added")
    a, b = plain.metrics, added.metrics
    for key in ("mse", "approximation_floor", "loglik_difference", "coverage"):
        assert {m: b[key][m] for m in a[key]} == a[key], key
        assert set(b[key]) - set(a[key]) == {"linear"}, key
    assert b["returns"] == a["returns"]
    report = (added.out / "report.md").read_text()
    assert "linear (`tasks.methods:BayesianLinear`)" in report
