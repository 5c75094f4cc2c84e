"""Smoke test: the cartpole prediction experiment's main runs in-process on a tiny
config and writes every artefact with the documented schema."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

import hipmdp
from hipmdp.planning import LearnedModel
from tasks.cartpole import CartpoleParams
from tasks.cartpole_prediction import (
    DIM_NAMES,
    N_BOOTSTRAP,
    PredictionConfig,
    main,
    parse_args,
    ratio_intervals,
)
from tasks.prediction import PREDICTION_METHODS, best_baseline, entity, mse_table
from tasks.recording import rrd_contents
from tests._prediction import assert_coverage_schema, assert_names_fit_choices
from tests._rrd import rrd_components, rrd_scalars, rrd_times
from tests._seed_spread import assert_reads_the_run

TINY = PredictionConfig(
    train_settings=((0.1, 0.4), (0.3, 0.6), (0.2, 0.5)),
    test_settings=((0.15, 0.45), (0.25, 0.55)),
    batch_repetitions=1,
    batch_episodes=3,
    batch_max_steps=100,
    n_runs=2,
    fit=hipmdp.FitConfig(
        n_support=40,
        n_sweeps=3,
        n_chains=1,
        n_candidates=200,
        n_hyper=100,
        n_smooth=150,
        n_w=50,
        progress=False,
    ),  # fmt: skip
    average_n_max=150,
    n_train=10,
    n_test=10,
    gather_episodes=3,
    workers=1,
    progress=False,
)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    # as a user calling main after `import numpy`: OpenBLAS at two threads
    with threadpool_limits(limits=2):
        return main(TINY, out=tmp_path_factory.mktemp("cartpole"))


def test_artefacts_and_schema(run):
    names = {p.name for p in run.out.iterdir()}
    expected = {"config.json", "metrics.json", "report.md", "weights.png"}
    expected |= {"cartpole.rrd", "hipmdp_run0.npz", "hipmdp_run1.npz", "batch.npz"}
    assert expected <= names
    m = json.loads((run.out / "metrics.json").read_text())
    for method in PREDICTION_METHODS:
        assert set(m["mse"][method]) == set(DIM_NAMES)
        per_setting = np.array(m["per_setting_mse"][method])
        assert per_setting.shape == (2, 4) and np.all(per_setting >= 0)
        # the table's mean is the mean over settings
        np.testing.assert_allclose(
            [m["mse"][method][d]["mean"] for d in DIM_NAMES], per_setting.mean(0)
        )
    # the log-likelihood differences are the per-setting ones' mean
    hip_ll = np.array(m["per_setting_loglik"]["hipmdp"])
    assert hip_ll.shape == (2,)
    for method, lead in m["loglik_difference"].items():
        base_ll = np.array(m["per_setting_loglik"][method])
        assert lead["mean"] == pytest.approx(np.mean(hip_ll - base_ll))
    assert len(m["n_latent_features"]) == 2 and len(m["z"]) == 2
    # no test setting of TINY is a training one
    assert m["test_settings_seen"] == [False, False]
    assert m["unseen"]["n_instances"] == 2
    assert m["unseen"]["mse_ratio_to_best_baseline"] == m["mse_ratio_to_best_baseline"]
    assert set(m["mse_ratio_to_best_baseline"]) == set(DIM_NAMES)
    for d, ci in m["mse_ratio_to_best_baseline_interval"].items():
        assert ci["n_settings"] == 2 and ci["low"] <= ci["high"], d
    assert m["environment"]["packages"]["numpy"] == np.__version__
    assert "Machine: " in (run.out / "report.md").read_text()
    assert_coverage_schema(m, DIM_NAMES, (run.out / "report.md").read_text())


def test_same_seed_same_metrics_whatever_the_callers_blas_threads(run, tmp_path):
    with threadpool_limits(limits=1):
        again = main(TINY, out=tmp_path)
    a = json.loads((run.out / "metrics.json").read_text())
    b = json.loads((again.out / "metrics.json").read_text())
    a.pop("seconds"), b.pop("seconds")
    assert a == b


def test_recording(run):
    rows = rrd_contents(run.out / "cartpole.rrd")
    assert rows["/mse/3/hipmdp"] == len(TINY.test_settings)
    # the panels' values: each setting's MSE of Δẋ (2) and Δθ̇ (3), per method
    per_setting = json.loads((run.out / "metrics.json").read_text())["per_setting_mse"]
    for m, mse in per_setting.items():
        for d in (2, 3):
            got = rrd_scalars(run.out / "cartpole.rrd", f"/mse/{d}/{entity(m)}")
            np.testing.assert_array_equal(got[:, 0], np.asarray(mse)[:, d])
    assert rows["/belief/true/pole_mass"] == len(TINY.test_settings) * (
        TINY.n_train + 1
    )


def test_recording_timelines_play_the_settings_in_turn(run):
    """The belief on ``transition`` and the rollout on ``step``, each counted on
    across the test settings (both on one restarting ``step`` showed unrelated
    quantities at the same instants, every setting on the same ones); the
    rollout ends on the episode's last real pose; the cart drawn as a box."""
    file = run.out / "cartpole.rrd"
    n_set, per = len(TINY.test_settings), TINY.n_train + 1
    belief = rrd_times(file, "/belief/true/pole_mass")
    assert set(belief) == {"episode", "transition"}
    np.testing.assert_array_equal(belief["transition"], np.arange(n_set * per))
    np.testing.assert_array_equal(belief["episode"], np.repeat(np.arange(n_set), per))
    real = rrd_times(file, "/rollout/real")
    assert set(real) == {"episode", "step"}
    np.testing.assert_array_equal(real["step"], np.arange(len(real["step"])))
    episodes, firsts = np.unique(real["episode"], return_index=True)
    np.testing.assert_array_equal(episodes, np.arange(n_set))
    assert np.all(np.diff(real["episode"]) >= 0)
    predicted = rrd_times(file, "/rollout/predicted")
    np.testing.assert_array_equal(predicted["step"], np.delete(real["step"], firsts))
    cart = rrd_times(file, "/rollout/cart")
    np.testing.assert_array_equal(cart["step"], real["step"])
    assert "Boxes3D:centers" in rrd_components(file, "/rollout/cart")
    assert "Capsules3D:translations" in rrd_components(file, "/rollout/real")


def test_cli_bad_option(capsys):
    with pytest.raises(SystemExit):
        parse_args(["--runs", "0"])
    assert "--runs (n_runs): expected >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_args(["--seed", "-5"])
    assert "--seed" in capsys.readouterr().err


def test_cli_refuses_an_out_folder_of_other_files(tmp_path, capsys):
    """A folder holding a report.md but no config.json of a cartpole_prediction
    run is not this experiment's: a usage error before any work, not a
    traceback from main (which would refuse it too)."""
    (tmp_path / "report.md").write_text("mine")
    with pytest.raises(SystemExit) as stopped:
        parse_args(["--out", str(tmp_path), "--no-record"])
    assert stopped.value.code == 2
    assert "choose a new or empty folder" in capsys.readouterr().err
    assert (tmp_path / "report.md").read_text() == "mine"


def test_time_split_trains_on_the_first_transitions_and_tests_on_the_last():
    from tasks.agents import CARTPOLE
    from tasks.cartpole import CartpoleParams
    from tasks.prediction import gather_split

    params = CartpoleParams(cart_mass=1.0, pole_mass=0.2, pole_half_length=0.5)
    split = gather_split(
        CARTPOLE, params, 30, 30, rng=np.random.default_rng(0), split="time"
    )
    n = len(split.episodes)
    assert n > 60  # so there is a gap between the two
    np.testing.assert_array_equal(split.train.states, split.episodes.states[:30])
    np.testing.assert_array_equal(split.test.states, split.episodes.states[n - 30 :])
    with pytest.raises(ValueError, match="split: expected one of"):
        gather_split(CARTPOLE, params, 5, 5, rng=np.random.default_rng(0), split="x")
    with pytest.raises(ValueError, match="split: expected one of"):
        PredictionConfig(split="episodes")
    config, _ = parse_args(["--split", "time"])
    assert config.split == "time" and PredictionConfig().split == "random"


def test_gather_split_keeps_learning_until_it_has_enough():
    from tasks.agents import CARTPOLE
    from tasks.cartpole import CartpoleParams
    from tasks.prediction import gather_split

    params = CartpoleParams(cart_mass=1.0, pole_mass=0.2, pole_half_length=0.5)
    rng = np.random.default_rng(0)
    split = gather_split(CARTPOLE, params, 60, 60, rng=rng, n_episodes=1)
    assert len(split.train) == len(split.test) == 60
    # disjoint: no transition is in both
    train = {tuple(r) for r in np.c_[split.train.states, split.train.actions]}
    test = {tuple(r) for r in np.c_[split.test.states, split.test.actions]}
    assert not train & test
    with pytest.raises(ValueError, match="transitions asked, only"):
        gather_split(CARTPOLE, params, 5000, 5000, rng=rng, max_episodes=2)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(train_settings=((0.1, 0.4),)), "train_settings: expected at least two"),
        (dict(test_settings=((0.1,),)), r"test_settings: expected \(mass, half-length"),
        (dict(test_settings=((0.1, 9.0),)), "pole_half_length"),
        (dict(seed=-5), "seed: expected >= 0"),
        (dict(n_runs=2.0), "n_runs: expected an integer"),
        (dict(record="yes"), "record: expected True or False"),
        *(
            (dict.fromkeys([count], 0), f"{count}: expected")
            for count in (
                "batch_repetitions",
                "batch_episodes",
                "batch_max_steps",
                "n_runs",
                "average_n_max",
                "n_train",
                "n_test",
                "gather_episodes",
                "workers",
            )
        ),  # fmt: skip
    ],
)
def test_bad_settings(kw, match):
    with pytest.raises(ValueError, match=match):
        PredictionConfig(**kw)


def test_summarise_separates_the_settings_seen_in_training():
    from tasks.prediction import InstanceScores, summarise

    def scores(x):
        mse = {m: np.full(4, x) for m in PREDICTION_METHODS}
        # levels (0.5, 0.95) x dimensions, offset per method: distinct values,
        # so a swapped level, dimension or method shows
        base = np.array([[0.1, 0.2, 0.3, 0.4], [0.5, 0.6, 0.7, 0.8]])
        cover = {m: base * x / 4 + 0.01 * i
                 for i, m in enumerate(PREDICTION_METHODS)}  # fmt: skip
        # distinct per method: a flipped sign or a swapped method shows
        loglik = {m: x * (i + 1) for i, m in enumerate(PREDICTION_METHODS)}
        return InstanceScores(mse=mse, loglik=loglik, coverage=cover)

    table = summarise([scores(1.0), scores(2.0), scores(4.0)], DIM_NAMES, [1, 0, 0])
    assert table["seen"] == [True, False, False]
    assert table["mse"]["hipmdp"]["dx"]["mean"] == pytest.approx(7 / 3)
    assert table["unseen"]["mse"]["hipmdp"]["dx"]["mean"] == pytest.approx(3.0)
    coverage = table["coverage"]["train only"]  # method 2
    assert list(coverage) == ["0.5", "0.95"]
    assert coverage["0.5"]["dtheta"]["mean"] == pytest.approx(0.2 * 7 / 12 + 0.02)
    assert coverage["0.95"]["dx"]["mean"] == pytest.approx(0.5 * 7 / 12 + 0.02)
    unseen = table["unseen"]["coverage"]["hipmdp"]["0.95"]["dtheta_dot"]
    assert unseen["mean"] == pytest.approx(0.8 * 3 / 4)
    assert table["unseen"]["n_instances"] == 2
    # HiP-MDP minus the method, > 0 favouring the HiP-MDP: here x·1 − x·2 for
    # batch only (method 1), x·1 − x·4 for batch + train (method 3)
    diff = table["loglik_difference"]
    assert "hipmdp" not in diff
    assert diff["batch only"]["mean"] == pytest.approx(-7 / 3)
    assert diff["batch + train"]["mean"] == pytest.approx(-3 * 7 / 3)
    assert table["unseen"]["loglik_difference"]["train only"]["mean"] == -6.0
    assert table["per_instance"]["loglik_difference"]["batch only"] == [-1, -2, -4]
    # each method's own log-likelihood, setting by setting, as metrics.json keeps
    assert table["per_setting_loglik"]["hipmdp"] == [1.0, 2.0, 4.0]
    assert table["per_setting_loglik"]["batch + train"] == [4.0, 8.0, 16.0]
    assert summarise([scores(1.0)], DIM_NAMES, [True])["unseen"] is None
    with pytest.raises(ValueError, match="seen: expected 1 flags"):
        summarise([scores(1.0)], DIM_NAMES, [True, False])


def test_coverage_counts_as_the_dense_interval_check_does():
    from scipy.stats import norm

    from tasks.prediction import coverage

    rng = np.random.default_rng(3)
    mean, var = rng.normal(size=(200, 3)), rng.uniform(0.1, 4.0, size=(200, 3))
    observed = mean + rng.standard_t(3, size=(200, 3)) * np.sqrt(var)
    levels = (0.2, 0.5, 0.95)
    expected = np.zeros((3, 3))
    for k, level in enumerate(levels):
        for i in range(200):
            for d in range(3):
                low, high = norm.interval(level, mean[i, d], np.sqrt(var[i, d]))
                expected[k, d] += (low <= observed[i, d] <= high) / 200
    np.testing.assert_allclose(coverage(mean, var, observed, levels), expected)
    # the interval is closed, as norm.interval's check above: Δ on its edge is in
    edge = norm.ppf(0.75) * np.array([[-1.0], [1.0]])
    assert coverage(np.zeros((2, 1)), np.ones((2, 1)), edge, (0.5,)).item() == 1.0
    with pytest.raises(ValueError, match="levels: expected values in"):
        coverage(mean, var, observed, (0.5, 1.0))


@pytest.mark.parametrize(
    "mean, var, observed, match",
    [
        (np.zeros((3, 2)), np.ones((3, 1)), np.zeros((3, 2)), "expected one shape"),
        (np.zeros(3), np.ones(3), np.zeros(3), "expected one shape"),
        (np.zeros((3, 2)), np.zeros((3, 2)), np.zeros((3, 2)), "var: expected"),
    ],
)
def test_coverage_refuses_mismatched_or_zero_variances(mean, var, observed, match):
    from tasks.prediction import coverage

    with pytest.raises(ValueError, match=match):
        coverage(mean, var, observed)


class _Spy:
    """A fitted model that predicts a constant mean and variance for Δs and
    records the data it is given (its log-likelihood: a distinct constant)."""

    def __init__(self, mean, var=1.0, loglik=0.0):
        self.mean, self.var, self.loglik = mean, var, loglik
        self.n_actions, self.hyper = 2, SimpleNamespace(periodic=(1,))
        self.seen = {}

    def prior(self):
        return "prior"

    def update(self, belief, data):
        self.seen["update"] = (belief, data)
        return "posterior"

    def predict(self, states, actions, belief=None):
        self.seen["predict"] = (states, belief)
        shape = (len(states), 4)
        return np.full(shape, self.mean), np.full(shape, self.var)

    def log_likelihood(self, data, belief=None):
        self.seen["log_likelihood"] = (data, belief)
        return self.loglik


def _transitions(n, rng):
    """``n`` transitions of one instance: standard normal states and Δs, actions
    0 or 1."""
    s = rng.normal(size=(n, 4))
    a = rng.integers(0, 2, n)
    return hipmdp.Transitions(s, a, s + rng.normal(size=(n, 4)), np.zeros(n, int))


def test_score_instance_averages_the_fits_scores(monkeypatch):
    """With several HiP-MDP fits, its MSE and coverage are the means of each fit's
    (stub models: each predicts a constant mean and variance)."""
    from tasks import prediction

    def stub(mean, var):  # a log-likelihood distinct per fit
        return _Spy(mean, var, loglik=10.0 * mean + 1.0)

    for name in ("train_only", "batch_plus_train"):
        monkeypatch.setattr(prediction.baselines, name, lambda *a, **k: stub(0, 1))
    rng = np.random.default_rng(5)
    test = _transitions(400, rng)
    fits = [stub(0.0, 0.25), stub(1.0, 4.0)]
    scores = prediction.score_instance(fits, stub(0, 1), test, test, test, rng=rng)
    d = test.deltas
    np.testing.assert_allclose(
        scores.mse["hipmdp"], np.mean([np.mean((d - f.mean) ** 2, 0) for f in fits], 0)
    )
    each = [prediction.coverage(np.full_like(d, f.mean), np.full_like(d, f.var), d)
            for f in fits]  # fmt: skip
    np.testing.assert_allclose(scores.coverage["hipmdp"], np.mean(each, axis=0))
    assert not np.allclose(each[0], each[1])  # so one fit alone would not pass
    # the HiP-MDP's log-likelihood is the mean of the fits' (1 and 11); each
    # baseline's is its own (Stub(0, 1): 1)
    assert scores.loglik == {
        "hipmdp": 6.0,
        "batch only": 1.0,
        "train only": 1.0,
        "batch + train": 1.0,
    }


@pytest.mark.parametrize("scale, side", [(1.0, 0), (4.0, 1), (0.25, -1)])
def test_coverage_is_nominal_only_for_the_true_variance(scale, side):
    """Gaussian errors of variance 1 under predictive variance ``scale``: nominal
    within 4 binomial sds at scale 1, above it for a wider variance, below for a
    narrower one."""
    from tasks.prediction import COVERAGE_LEVELS, coverage

    n = 20_000
    observed = np.random.default_rng(4).normal(size=(n, 2))
    shares = coverage(np.zeros((n, 2)), np.full((n, 2), scale), observed)
    for level, share in zip(COVERAGE_LEVELS, shares, strict=True):
        sd = np.sqrt(level * (1 - level) / n)
        if side == 0:
            assert np.all(np.abs(share - level) < 4 * sd)
        else:
            assert np.all(side * (share - level) > 4 * sd)


def test_mse_ratios_are_paired_per_setting():
    from tasks.prediction import mse_ratios

    per = {
        "hipmdp": {"dx": [1.0, 2.0, 4.0, 0.0]},
        "batch only": {"dx": [10.0, 10.0, 2.0, 1.0]},
    }
    r = mse_ratios(per)["batch only"]["dx"]
    logs = np.log([0.1, 0.2, 2.0])  # the setting with a zero MSE is left out
    assert r["geometric_mean"] == pytest.approx(np.exp(logs.mean()))
    # counted on the same 3 settings: 1 < 10, 2 < 10, not 4 < 2 (0 < 1 is left out)
    assert r["n"] == 3 and r["hipmdp_lower"] == 2
    # the interval: the t-interval of the 3 log ratios (df 2), exponentiated
    from scipy import stats

    low, high = stats.t.interval(0.95, df=2, loc=logs.mean(), scale=stats.sem(logs))
    assert [r["low"], r["high"]] == pytest.approx(np.exp([low, high]), rel=1e-12)


def test_seed_spread_reads_the_run(run, tmp_path):
    result = assert_reads_the_run(run.out, tmp_path, "cartpole_prediction")
    metrics = json.loads((run.out / "metrics.json").read_text())
    best = best_baseline(metrics["mse"], "dx")  # the first run's, named
    assert (
        result["numbers"][0]["label"] == f"HiP-MDP MSE / {best}'s, dx (ratio of means)"
    )


def test_ratio_to_best_baseline_divides_by_the_lowest_mean_mse():
    from tasks.cartpole_prediction import _ratios

    def ci(x):
        return {"mean": x, "low": x, "high": x}

    mse = {
        "hipmdp": {d: ci(1.0) for d in DIM_NAMES},
        "batch only": {d: ci(4.0) for d in DIM_NAMES},
        "train only": {d: ci(8.0 if d != "dx" else 2.0) for d in DIM_NAMES},
        "batch + train": {d: ci(5.0 if d != "dtheta" else 0.0) for d in DIM_NAMES},
        "mine": {d: ci(0.5) for d in DIM_NAMES},  # added: never the best baseline
    }
    ratios = _ratios(mse)
    assert ratios["dx"] == 0.5  # train only, 2.0
    assert ratios["dtheta"] is None  # the best baseline predicts it exactly
    assert ratios["dx_dot"] == ratios["dtheta_dot"] == 0.25  # batch only, 4.0


def test_ratio_intervals_resample_settings_with_the_methods_paired():
    """Against a loop over resamples drawn as the function draws them; and a
    HiP-MDP at half the baseline on every setting has the interval [0.5, 0.5]
    whatever the settings drawn (the methods stay paired)."""
    rng = np.random.default_rng(5)
    base = rng.lognormal(0.0, 1.5, size=(6, 4))
    hip = base * rng.uniform(0.2, 1.4, size=base.shape)
    per_setting = {"hipmdp": hip, "batch only": base, "train only": 2 * base}
    mse = {m: {d: {"mean": v[:, j].mean()} for j, d in enumerate(DIM_NAMES)}
           for m, v in per_setting.items()}  # fmt: skip
    got = ratio_intervals(per_setting, mse, rng=np.random.default_rng(1))
    draws = np.random.default_rng(1).integers(6, size=(N_BOOTSTRAP, 6))
    for j, d in enumerate(DIM_NAMES):
        ratios = [hip[i, j].mean() / base[i, j].mean() for i in draws]
        want = np.percentile(ratios, [2.5, 97.5])
        assert [got[d]["low"], got[d]["high"]] == pytest.approx(want, rel=1e-12)
        assert got[d]["share_at_least_1"] == np.mean(np.array(ratios) >= 1)
    half = {**per_setting, "hipmdp": 0.5 * base}
    for ci in ratio_intervals(half, mse, rng=np.random.default_rng(2)).values():
        assert ci["low"] == pytest.approx(0.5) and ci["high"] == pytest.approx(0.5)
        assert ci["share_at_least_1"] == 0.0


def test_mse_table_notes_intervals_that_reach_below_zero():
    """An MSE cannot be negative; a t-interval over settings that says so gets a
    note naming it, and a table without one gets none."""
    ok = {"mean": 2.0, "low": 1.0, "high": 3.0, "n": 9}
    mse = {"hipmdp": {"dx": ok, "dtheta": ok}, "train only": {"dx": ok, "dtheta": ok}}
    assert "below 0" not in mse_table(mse)
    mse["hipmdp"]["dtheta"] = {"mean": 4.6e-05, "low": -4.6e-05, "high": 1.4e-4, "n": 9}
    text = mse_table(mse)
    assert text.startswith("| method | dx | dtheta |")
    assert "| hipmdp | 2 [1, 3] | 4.60e-05 [-4.60e-05, 1.40e-04] † |" in text
    assert text.endswith("The per-setting ratios are the better guide there.")


@pytest.mark.parametrize("levels", [(0.0, 0.5), ((0.5, 0.95),)])
def test_coverage_refuses_a_level_of_zero_or_a_table_of_levels(levels):
    """A 0% interval covers nothing and means nothing; levels are one flat list
    (the result's first axis)."""
    from tasks.prediction import coverage

    with pytest.raises(ValueError, match="levels: expected values in"):
        coverage(np.zeros((3, 2)), np.ones((3, 2)), np.zeros((3, 2)), levels)


def test_gather_split_counts_episodes_and_transitions_as_documented():
    """At max_steps = 5 every cart-pole episode lasts 5 steps (the pole, started
    near upright, cannot fall in 5 steps), so the counts follow by hand: at least
    n_episodes = 3 episodes (15 transitions) even when 10 are asked; exactly 15
    asked are enough without a 4th; at most max_episodes episodes are learned
    (1 + 1 more of 5 steps: 10 transitions) before giving up."""
    from tasks.agents import CARTPOLE
    from tasks.cartpole import CartpoleParams
    from tasks.prediction import gather_split

    params = CartpoleParams()

    def gathered(n_train, n_test, **kw):
        rng = np.random.default_rng(0)
        return gather_split(CARTPOLE, params, n_train, n_test, rng=rng, **kw)

    few = gathered(5, 5, max_steps=5)
    assert len(few.episodes) == 15 and len(few.train) == len(few.test) == 5
    exact = gathered(10, 5, max_steps=5)
    assert len(exact.episodes) == 15 and (len(exact.train), len(exact.test)) == (10, 5)
    with pytest.raises(ValueError, match="only 10 gathered in 2 episodes"):
        gathered(50, 50, max_steps=5, n_episodes=1, max_episodes=2)


def test_score_instance_fits_scores_and_filters_on_the_data_the_protocol_says(
    monkeypatch,
):
    """The protocol (module docstring): "train only" on the train transitions,
    measuring angles as the average model does; "batch + train" on both, with the
    average model's hyperparameters; the HiP-MDP's belief filtered from its prior
    on the train transitions; every method predicts and is scored on the test
    transitions, each with its own predictions; an added method is given the
    train and test transitions and its key. Batch, train and test differ in
    size, so a swap shows; each spy predicts its own constant, so a swapped method
    shows in the MSE, which is written out as the plain mean of squares."""
    from tasks import prediction

    fitted = {}
    spies = {
        "train only": _Spy(1.0, loglik=-2.0),
        "batch + train": _Spy(2.0, loglik=-3.0),
    }

    def train_only(train, *, rng, **kw):
        fitted["train only"] = (train, kw)
        return spies["train only"]

    def batch_plus_train(batch, train, *, rng, **kw):
        fitted["batch + train"] = (batch, train, kw)
        return spies["batch + train"]

    monkeypatch.setattr(prediction.baselines, "train_only", train_only)
    monkeypatch.setattr(prediction.baselines, "batch_plus_train", batch_plus_train)

    rng = np.random.default_rng(8)
    batch, train, test = (_transitions(n, rng) for n in (30, 20, 10))
    average, hip = _Spy(0.5, loglik=-1.0), _Spy(-1.0, loglik=-4.0)
    seen = []

    def predict(*args):  # an added method's: a constant Δs = 3
        seen.append(args)
        return np.full((len(test), 4), 3.0), np.ones((len(test), 4))

    mine = SimpleNamespace(name="mine", predict=predict)
    scores = prediction.score_instance(
        [hip], average, batch, train, test, rng=rng, added=[mine], key=(3, 1)
    )
    assert seen == [(train, test, (3, 1))]  # its key: (table, setting)
    assert fitted["train only"][0] is train
    assert fitted["train only"][1]["periodic"] == average.hyper.periodic
    assert fitted["batch + train"][:2] == (batch, train)
    assert fitted["batch + train"][2]["hyper"] is average.hyper
    assert hip.seen["update"] == ("prior", train)
    assert hip.seen["predict"][1] == "posterior"
    assert hip.seen["log_likelihood"] == (test, "posterior")
    for spy in (average, hip, *spies.values()):
        np.testing.assert_array_equal(spy.seen["predict"][0], test.states)
        assert spy.seen["log_likelihood"][0] is test
    means = {
        "hipmdp": -1.0,
        "batch only": 0.5,
        "train only": 1.0,
        "batch + train": 2.0,
        "mine": 3.0,
    }
    for method, mean in means.items():
        want = [np.mean([(d - mean) ** 2 for d in col]) for col in test.deltas.T]
        np.testing.assert_allclose(scores.mse[method], want, err_msg=method)
    assert {m: scores.loglik[m] for m in PREDICTION_METHODS} == {
        "hipmdp": -4.0,
        "batch only": -1.0,
        "train only": -2.0,
        "batch + train": -3.0,
    }


def test_entity_names_have_no_spaces_and_differ():
    """Recording paths and reserved --method names: the docstring's rule, each
    " + " and then each space to "_"."""
    assert [entity(m) for m in PREDICTION_METHODS] == [
        "hipmdp",
        "batch_only",
        "train_only",
        "batch_train",
    ]


def test_summarise_refuses_scores_with_other_methods_or_too_few_flags():
    from tasks.prediction import InstanceScores, summarise

    def scores(methods):
        return InstanceScores(
            mse={m: np.ones(4) for m in methods},
            loglik={m: 0.0 for m in methods},
            coverage={m: np.full((2, 4), 0.5) for m in methods},
        )

    both = [scores(PREDICTION_METHODS), scores(PREDICTION_METHODS)]
    with pytest.raises(ValueError, match="seen: expected 2 flags, got 1"):
        summarise(both, DIM_NAMES, [True])
    # an added method on the first setting only
    mixed = [scores([*PREDICTION_METHODS, "mine"]), scores(PREDICTION_METHODS)]
    with pytest.raises(ValueError, match="expected the methods .* on every instance"):
        summarise(mixed, DIM_NAMES)


def test_mse_ratios_leave_out_zero_baselines_and_count_only_strictly_lower():
    """A setting where either MSE is 0 has no finite log ratio and is left out;
    an equal MSE is not "lower"; a dimension with no usable setting is None."""
    from tasks.prediction import mse_ratios

    per = {
        "hipmdp": {"dx": [1.0, 2.0, 3.0], "dtheta": [0.0, 0.0, 0.0]},
        "batch only": {"dx": [2.0, 2.0, 0.0], "dtheta": [1.0, 1.0, 1.0]},
    }
    r = mse_ratios(per)["batch only"]
    # settings 1 and 2: ratios 1/2 and 1, geometric mean sqrt(1/2); only 1 < 2
    assert r["dx"]["n"] == 2 and r["dx"]["hipmdp_lower"] == 1
    assert r["dx"]["geometric_mean"] == pytest.approx(np.sqrt(0.5))
    assert r["dtheta"] is None


def test_score_settings_gives_each_setting_its_own_stream_and_key(monkeypatch):
    """Settings with the same parameters still get independent data (a stream
    each, spawned from the seed); the same seed gives the same streams, and a
    setting's stream does not depend on how many follow it; added methods are
    keyed (table, setting); the gathering's episodes and the average GP's cap
    reach each setting, and its splits come back in order."""
    from tasks import prediction

    draws, keys, sizes = [], [], []

    def gather_split(domain, params, n_train, n_test, *, rng, n_episodes, split):
        draws.append(rng.random())
        sizes.append(n_episodes)
        return prediction.Split(len(draws), None, None)

    def score_instance(hips, average, batch, train, test, *, rng, n_max, added, key):
        keys.append(key)
        sizes.append(n_max)
        return key

    monkeypatch.setattr(prediction, "gather_split", gather_split)
    monkeypatch.setattr(prediction, "score_instance", score_instance)

    def run(n):
        draws.clear()
        keys.clear()
        seed = np.random.SeedSequence(11)
        prediction.score_settings(
            None, [], None, None, ["same"] * n, n_train=1, n_test=1, seed=seed, table=2
        )
        return list(draws), list(keys)

    three, keys3 = run(3)
    assert len(set(three)) == 3
    assert keys3 == [(2, 0), (2, 1), (2, 2)]
    again, _ = run(3)
    two, _ = run(2)
    assert again == three and two == three[:2]
    sizes.clear()
    draws.clear()
    splits = []
    prediction.score_settings(
        None, [], None, None, ["a", "b"], n_train=1, n_test=1, n_episodes=7,
        n_max=90, seed=np.random.SeedSequence(1), splits=splits,
    )  # fmt: skip
    assert sizes == [7, 90, 7, 90]
    assert [s.train for s in splits] == [1, 2]


def test_report_sections_say_what_the_metrics_hold():
    """The report's text functions on small hand-made metrics: the coverage table
    shows each level's mean, levels in order; the unseen section counts the
    settings seen in training and says when none is new; the ratio lines name
    "lower on k of n" and skip a dimension without a ratio; the added-methods
    paragraph marks only the policies; runs without coverage or ratios get no
    text."""
    from tasks.prediction import added_text, coverage_text, ratio_text, unseen_section

    def ci(x):
        return {"mean": x, "low": x - 0.1, "high": x + 0.1, "n": 3}

    coverage = {
        "hipmdp": {"0.5": {"dx": ci(0.41)}, "0.95": {"dx": ci(0.93)}},
        "batch only": {"0.5": {"dx": ci(0.62)}, "0.95": {"dx": ci(0.99)}},
    }
    text = coverage_text(coverage)
    assert "central 50% / 95% Gaussian" in text and "gives 0.50 / 0.95" in text
    assert "| hipmdp | 0.41 / 0.93 |" in text
    assert "| batch only | 0.62 / 0.99 |" in text
    assert coverage_text(None) == coverage_text({}) == ""

    none_new = {"test_settings_seen": [True, False, True], "unseen": None}
    assert unseen_section(none_new) == (
        "2 of the 3 test settings are training settings (the HiP-MDP has their "
        "dynamics among its training instances). No test setting is new."
    )
    assert unseen_section({}) == ""
    unseen = {"n_instances": 4, "mse": {}, "loglik_difference": {}}
    all_new = {"test_settings_seen": [False] * 4, "unseen": unseen}
    assert unseen_section(all_new) == (
        "None of the 4 test settings is a training setting: the tables above are "
        "all on settings the HiP-MDP was not trained on."
    )  # the tables were printed again

    mse = {m: {"dx": ci(1.0), "dtheta": ci(1.0)} for m in PREDICTION_METHODS}
    mse["train only"] = {"dx": ci(0.5), "dtheta": ci(0.5)}
    ratios = {"train only": {"dx": {"geometric_mean": 0.25, "low": 0.125,
                                    "high": 0.5, "n": 5, "hipmdp_lower": 4},
                             "dtheta": None}}  # fmt: skip
    lines = ratio_text({"mse": mse, "mse_ratio_per_setting": ratios})
    assert "- dx: 0.25 " in lines
    assert lines.endswith("against train only; lower on 4 of 5 settings")
    assert "dtheta" not in lines
    assert ratio_text({"mse": mse}) == ""

    added = added_text(["mine=my.module:Mine", "greedy=my.module:Greedy"], {"greedy"})
    assert "mine (`my.module:Mine`)," in added
    assert (
        "greedy (`my.module:Greedy`, a policy, so not in the prediction tables)"
        in added
    )
    assert added_text([]) == ""


class _SpyRecording:
    """Stands in for tasks.recording.Recording (called as the class is): keeps
    every call in ``calls``, writes nothing."""

    def __init__(self):
        self.calls = []

    def __call__(self, file, **kw):
        return self

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def __getattr__(self, name):
        return lambda *args, **kw: self.calls.append((name, args, kw))


def _episodes(rng, n, end, instance, dt):
    """``n`` cart-pole transitions (the states near upright, ``dt`` seconds apart)
    with the first episode ending after transition ``end`` and another at the
    last."""
    s = rng.normal(scale=0.05, size=(n, 4))
    dones = np.zeros(n, bool)
    dones[[end, n - 1]] = True
    return hipmdp.Transitions(
        s, rng.integers(0, 2, n), s + rng.normal(scale=0.01, size=(n, 4)),
        np.full(n, instance), dones=dones, angle_dims=(1,), dt=dt,
    )  # fmt: skip


def test_recording_shows_each_settings_mse_belief_and_first_episode(run, monkeypatch):
    """record() on hand-made settings, through a spy: each method's MSE of Δẋ
    (dimension 2) and Δθ̇ (3) setting by setting; the belief filtered one train
    transition at a time from the prior, ending at the batch posterior (the
    conjugate update's closed form) beside the setting's true mass and length;
    the first episode (up to its first done) posed with the setting's
    parameters (the pole from pivot to tip is 2 half-lengths long), s_0 .. s_T,
    and the HiP-MDP's one-step predictions from the final belief."""
    from tasks import cartpole, prediction_report
    from tasks.prediction import Split, entity

    spy = _SpyRecording()
    monkeypatch.setattr(prediction_report, "Recording", spy)
    hip = hipmdp.load(run.out / "hipmdp_run0.npz")
    rng = np.random.default_rng(6)
    settings = ((0.15, 0.45), (0.25, 0.7))
    ends = (4, 6)  # the first episodes' last transitions

    def gathered(n, end, e):  # timed as the fit's batch was
        return _episodes(rng, n, end, e, hip.info["dt"])

    splits = [
        Split(gathered(5, 2, e), None, gathered(12, ends[e], e)) for e in range(2)
    ]
    config = SimpleNamespace(test_settings=settings)
    per_setting = {m: np.arange(8.0).reshape(2, 4) + 10 * i
                   for i, m in enumerate(PREDICTION_METHODS)}  # fmt: skip
    prediction_report.record("x.rrd", config, {"per_setting_mse": per_setting},
                             hip, splits)  # fmt: skip
    calls = spy.calls
    for m, mse in per_setting.items():
        for d in (2, 3):
            name = f"/mse/{d}/{entity(m)}"
            ((values, kw),) = [
                (a[1], kw) for f, a, kw in calls if f == "scalars" and a[0] == name
            ]
            np.testing.assert_array_equal(values, mse[:, d])
            np.testing.assert_array_equal(kw["episode"], [0, 1])  # setting indices
    beliefs = [a for f, a, _ in calls if f == "belief"]
    for e, (means, sds, truth) in enumerate(beliefs):
        train = splits[e].train
        assert len(means) == len(sds) == len(train) + 1
        np.testing.assert_allclose(means[0], hip.prior().mean)
        posterior = hip.update(hip.prior(), train)
        # one transition at a time or all at once: the same conjugate posterior
        # up to rounding. Measured in the belief's own sds, not relative to the
        # weights (large here, ~1e3, so their rounding is ~1e-7 relative and
        # depends on the fit): a hundredth of an sd is no difference a reader
        # of the panel could see, while one transition fewer moves the mean by
        # tens of sds (the check can see a belief filtered on the wrong data)
        sd = np.sqrt(np.diag(posterior.cov))
        assert np.max(np.abs(means[-1] - posterior.mean) / sd) < 1e-2
        np.testing.assert_allclose(sds[-1], sd, rtol=1e-3)
        fewer = hip.update(hip.prior(), train.head(len(train) - 1))
        assert np.max(np.abs(fewer.mean - posterior.mean) / sd) > 1
        # and moves every sd by 10x that tolerance or more (measured: 3-9%)
        assert np.min(np.abs(np.sqrt(np.diag(fewer.cov)) / sd - 1)) > 1e-2
        assert truth == {
            "pole_mass": settings[e][0],
            "pole_half_length": settings[e][1],
        }
    poses = [a[1] for f, a, _ in calls if f == "capsules"]
    carts = [a[1] for f, a, _ in calls if f == "boxes"]
    predicted = [a[1] for f, a, _ in calls if f == "strips"]
    assert len(beliefs) == len(poses) == len(carts) == len(predicted) == 2
    for e, (mass, half) in enumerate(settings):
        episodes, n = splits[e].episodes, ends[e] + 1
        params = cartpole.CartpoleParams(
            cart_mass=1.0, pole_mass=mass, pole_half_length=half
        )
        states = np.concatenate([episodes.states[:n], episodes.next_states[n - 1 : n]])
        points = cartpole.link_points(states, params)
        np.testing.assert_allclose(poses[e], points[:, 1:])
        np.testing.assert_allclose(carts[e], points[:, 0])
        lengths = np.linalg.norm(poses[e][:, 1] - poses[e][:, 0], axis=-1)
        np.testing.assert_allclose(lengths, 2 * half)
        # the predicted strips: a wiring check (the same predict and link_points
        # that record calls; what is independent is the belief, here updated on
        # the batch at once, there one transition at a time). Positions in
        # metres, to a micrometre: the belief's rounding (above)
        belief = hip.update(hip.prior(), splits[e].train)
        want = LearnedModel(hip, belief, (1,)).predict(
            episodes.states[:n], episodes.actions[:n]
        )
        np.testing.assert_allclose(
            predicted[e], cartpole.link_points(want, params), atol=1e-6
        )


def test_report_puts_the_numbers_in_their_places(run, tmp_path):
    """report.md of the run's metrics under a config with distinct counts: the
    counts in their sentence (TINY: 2 test and 3 training settings; 4 fits), the
    method added with --method named before the MSE table, each ratio with its
    interval low first (a dimension without a ratio as a dash), z of run 0
    (hand-made: run 0 uses every dimension, run 1 none) and the run time."""
    from tasks.prediction_report import write_report

    metrics = json.loads((run.out / "metrics.json").read_text())
    metrics["mse_ratio_to_best_baseline"] = {
        "dx": 0.25,
        "dtheta": None,
        "dx_dot": 0.5,
        "dtheta_dot": 2.0,
    }
    metrics["mse_ratio_to_best_baseline_interval"] = {
        "dx": {"low": 0.15, "high": 0.35}, "dtheta": None,
        "dx_dot": {"low": 0.45, "high": 0.55}, "dtheta_dot": None,
    }  # fmt: skip
    metrics["z"] = [np.ones((1, 2, 4)), np.zeros((1, 2, 4))]  # 2 actions
    metrics["seconds"] = {"fit": 12.0, "prediction": 3.0, "total": 20.0}
    config = dataclasses.replace(
        TINY, n_runs=4, n_train=7, n_test=9, record=False,
        methods=("mine=my.module:Mine",),
    )  # fmt: skip
    write_report(tmp_path, config, metrics)
    text = (tmp_path / "report.md").read_text()
    n_batch = metrics["n_batch_transitions"]
    assert (
        "2 test settings × 7 train / 9\ntest transitions (random split); HiP-MDP "
        f"fitted 4 times on\n{n_batch} batch transitions from 3 training settings."
    ) in text
    assert (
        "## Test log-likelihood (HiP-MDP minus method, over 9 test transitions)" in text
    )
    mse = text.split("## MSE of Δs")[1].split("| method |")[0]
    assert (
        "Added with `--method` (see `tasks/methods.py`): mine (`my.module:Mine`)" in mse
    )
    assert "| 0.25 [0.15, 0.35] | — | 0.5 [0.45, 0.55] | 2 |" in text
    assert f"Latent features per run: {metrics['n_latent_features']}" in text
    assert "| 0 (mean dynamics) | 1111 | 1111 |" in text
    assert "| 0 (mean dynamics) | 0000 | 0000 |" not in text
    assert "Run time: 20 s (fit 12 s, prediction 3 s, the rest 5 s)." in text


def test_weights_figure_plots_each_settings_own_weights(monkeypatch):
    """weights.png is given the training weights without row 0 (the mean
    dynamics, not a latent weight) and, per test setting, that setting's
    filtered belief means: hand-made weights, 3 settings of 2 weights each."""
    from tasks import prediction_report

    given = {}
    monkeypatch.setattr(
        prediction_report, "weights_figure", lambda *args: given.update(args=args)
    )
    config = SimpleNamespace(
        train_settings=((0.1, 0.4), (0.3, 0.6)),
        test_settings=((0.15, 0.45), (0.25, 0.55), (0.2, 0.5)),
    )
    metrics = {
        "training_weights": [[[0.0, 0.0], [1.0, 2.0], [3.0, 4.0]]],
        "test_belief_means": [[10.0, 11.0], [20.0, 21.0], [30.0, 31.0]],
    }
    prediction_report._weights_figure("w.png", config, metrics)
    _, train_p, train_w, test_p, test_w, *_ = given["args"]
    np.testing.assert_array_equal(train_w, [[1.0, 2.0], [3.0, 4.0]])
    np.testing.assert_array_equal(test_w, [[10, 11], [20, 21], [30, 31]])
    np.testing.assert_array_equal(train_p, config.train_settings)
    np.testing.assert_array_equal(test_p, config.test_settings)


def test_main_hands_each_step_its_part_of_the_config(tmp_path, monkeypatch):
    """One run whose counts differ from the defaults and from each other, through
    spies that call the real functions: each test setting gathered with the
    config's counts, episodes and split, on a stream of its own (the two settings
    with the same parameters get different data), and scored with its key
    (table 0, setting i) and ``average_n_max``; the average model fitted with
    ``average_n_max``, measuring the angle θ as the HiP-MDP does (periodic
    kernels here); the bootstrap on the seed's 5th child (main's comment),
    which no other step draws from; added methods seeded from the run's seed;
    the fits independent, saved and listed in order; the figures and recording
    given fit 0, whose beliefs are filtered on each setting's train
    transitions; the unseen settings' ratio taken on their own MSEs. The folder
    held an earlier run with 3 fits and a recording: none of its files stay;
    RERUN=off, so this run records nothing and its config.json and report say
    so."""
    import copy

    from tasks import cartpole_prediction as cp
    from tasks import prediction, prediction_report
    from tasks.experiment import write_json

    config = dataclasses.replace(
        TINY, seed=3, test_settings=((0.1, 0.4), (0.25, 0.55), (0.25, 0.55)),
        n_train=7, n_test=9, gather_episodes=2, split="time", average_n_max=120,
        fit=dataclasses.replace(TINY.fit, periodic=True),
    )  # fmt: skip
    monkeypatch.setenv("RERUN", "off")
    write_json(tmp_path / "config.json", TINY)  # the earlier run's files
    for name in ("hipmdp_run2.npz", "cartpole.rrd"):
        (tmp_path / name).write_bytes(b"earlier run")
    calls = {
        k: [] for k in ("gather", "score", "average", "bootstrap", "hip", "methods")
    }

    def state(rng):  # a stream's state before any draw
        return copy.deepcopy(rng.bit_generator.state)

    real = prediction.gather_split, prediction.score_instance, cp.baselines.batch_only
    real += cp.ratio_intervals, prediction_report.write_artefacts, cp.fit_all

    def gather(*args, rng, **kw):
        calls["gather"].append((args, kw, state(rng)))
        return real[0](*args, rng=rng, **kw)

    def score(*args, **kw):
        calls["score"].append(kw)
        return real[1](*args, **kw)

    def average(batch, *, rng, **kw):
        calls["average"].append((kw, state(rng)))
        return real[2](batch, rng=rng, **kw)

    def bootstrap(per_setting, mse, *, rng):
        calls["bootstrap"].append(state(rng))
        return real[3](per_setting, mse, rng=rng)

    def write(path, config, metrics, hip, splits):
        calls["hip"].append((hip, splits))
        return real[4](path, config, metrics, hip, splits)

    def fit_methods(loaded, batch, seed, *args, **kw):
        calls["methods"].append(seed)
        return real[5](loaded, batch, seed, *args, **kw)

    monkeypatch.setattr(prediction, "gather_split", gather)
    monkeypatch.setattr(cp, "fit_all", fit_methods)
    monkeypatch.setattr(prediction, "score_instance", score)
    monkeypatch.setattr(cp.baselines, "batch_only", average)
    monkeypatch.setattr(cp, "ratio_intervals", bootstrap)
    monkeypatch.setattr(prediction_report, "write_artefacts", write)

    run = main(config, out=tmp_path)
    m = json.loads((run.out / "metrics.json").read_text())
    assert not (tmp_path / "hipmdp_run2.npz").exists()
    assert not (tmp_path / "cartpole.rrd").exists()
    assert json.loads((tmp_path / "config.json").read_text())["record"] is False
    assert "No recording" in (tmp_path / "report.md").read_text()

    settings, streams = [], []
    for (_, params, n_train, n_test), kw, stream in calls["gather"]:
        assert (n_train, n_test) == (7, 9)
        assert kw["n_episodes"] == 2 and kw["split"] == "time"
        settings.append((params.pole_mass, params.pole_half_length))
        streams.append(stream)
        # the pole's mass and half-length vary, the rest stays nominal (1 kg cart)
        nominal = dataclasses.replace(
            CartpoleParams(),
            pole_mass=settings[-1][0],
            pole_half_length=settings[-1][1],
        )
        assert params == nominal
    assert settings == list(config.test_settings)
    splits = calls["hip"][0][1]
    assert not np.array_equal(splits[1].train.states, splits[2].train.states)
    assert [kw["key"] for kw in calls["score"]] == [(0, 0), (0, 1), (0, 2)]
    assert all(kw["n_max"] == 120 for kw in calls["score"])
    ((kw, average_stream),) = calls["average"]
    assert kw["n_max"] == 120

    assert calls["methods"] == [3]  # added methods' streams: from the run's seed
    fifth = np.random.default_rng(np.random.SeedSequence(3).spawn(5)[4])
    assert calls["bootstrap"] == [state(fifth)]
    assert calls["bootstrap"][0] not in [average_stream, *streams]

    fits = [hipmdp.load(run.out / f"hipmdp_run{r}.npz") for r in range(2)]
    for fit, weights in zip(fits, m["training_weights"], strict=True):
        np.testing.assert_array_equal(fit.weights, weights)
    # the average model measures θ (dimension 1) as an angle, as the fits do
    assert tuple(kw["periodic"]) == tuple(fits[0].hyper.periodic) == (1,)
    a, b = (fit.weights for fit in fits)
    assert a.shape != b.shape or not np.array_equal(a, b)  # not one fit twice
    # K counts the mean dynamics (z[0], all True); the belief is over the others
    assert m["n_latent_features"] == [len(z) - 1 for z in m["z"]]
    assert len(m["test_belief_means"][0]) == m["n_latent_features"][0]
    hip = calls["hip"][0][0]
    np.testing.assert_array_equal(hip.weights, fits[0].weights)
    for belief, split in zip(m["test_belief_means"], splits, strict=True):
        # the same model saved at full precision: the same belief to rounding
        want = fits[0].update(fits[0].prior(), split.train).mean
        np.testing.assert_allclose(belief, want, rtol=1e-12)
    batch = hipmdp.Transitions.load(run.out / "batch.npz")
    assert m["n_batch_transitions"] == len(batch)

    assert m["test_settings_seen"] == [True, False, False]
    unseen = m["unseen"]
    assert unseen["n_instances"] == 2
    for d in DIM_NAMES:
        mean = {method: mse[d]["mean"] for method, mse in unseen["mse"].items()}
        best = min(mean[method] for method in PREDICTION_METHODS[1:])
        ratio = unseen["mse_ratio_to_best_baseline"][d]
        assert ratio == pytest.approx(mean["hipmdp"] / best)
    assert unseen["mse_ratio_to_best_baseline"] != m["mse_ratio_to_best_baseline"]


def test_ratio_intervals_take_each_dimensions_best_baseline_or_give_none():
    """Each dimension against its own best baseline (train only on dx, batch only
    elsewhere): a HiP-MDP at half of it has the interval [0.5, 0.5]; one equal to
    it has ratio 1 in every resample, which is not lower (share 1); a baseline
    that predicts a dimension exactly (MSE 0) leaves no ratio, as ``_ratios``
    does; nor does a single setting (nothing to resample)."""
    base = np.random.default_rng(7).lognormal(size=(5, 4))
    base[:, 2] = 0.0  # batch only predicts dx_dot exactly
    train = 3.0 * base
    train[:, 0] = 0.25 * base[:, 0]  # the best on dx
    hip = 0.5 * base
    hip[:, 0] = 0.5 * train[:, 0]
    hip[:, 2] = 1.0
    hip[:, 3] = base[:, 3]  # equal to the best on dtheta_dot
    per_setting = {"hipmdp": hip, "batch only": base, "train only": train}
    mse = {m: {d: {"mean": v[:, j].mean()} for j, d in enumerate(DIM_NAMES)}
           for m, v in per_setting.items()}  # fmt: skip
    got = ratio_intervals(per_setting, mse, rng=np.random.default_rng(1))
    for d in ("dx", "dtheta"):
        assert got[d]["low"] == pytest.approx(0.5) == got[d]["high"], d
        assert got[d]["share_at_least_1"] == 0.0
    assert got["dx_dot"] is None
    assert got["dtheta_dot"]["low"] == got["dtheta_dot"]["high"] == 1.0
    assert got["dtheta_dot"]["share_at_least_1"] == 1.0
    one = {m: v[:1] for m, v in per_setting.items()}
    assert ratio_intervals(one, mse, rng=np.random.default_rng(1)) == dict.fromkeys(
        DIM_NAMES
    )


def test_ratio_intervals_divide_by_a_named_baseline_on_the_same_resamples():
    """``baselines`` names the divisor of one dimension (seed_spread's fixed
    baseline); the resamples are those drawn without it, so that dimension's
    interval is the hand loop's against the named baseline, the other
    dimensions' are unchanged, and naming each dimension's best changes
    nothing."""
    rng = np.random.default_rng(8)
    base = rng.lognormal(0.0, 1.0, size=(7, 4))
    train = base * rng.uniform(0.5, 3.0, size=base.shape)
    hip = base * rng.uniform(0.2, 1.4, size=base.shape)
    per_setting = {"hipmdp": hip, "batch only": base, "train only": train}
    mse = {m: {d: {"mean": v[:, j].mean()} for j, d in enumerate(DIM_NAMES)}
           for m, v in per_setting.items()}  # fmt: skip
    plain = ratio_intervals(per_setting, mse, rng=np.random.default_rng(3))
    best = {d: best_baseline(mse, d) for d in DIM_NAMES}
    assert "train only" not in best.values()  # so naming it changes the divisor
    assert (
        ratio_intervals(per_setting, mse, rng=np.random.default_rng(3), baselines=best)
        == plain
    )
    got = ratio_intervals(
        per_setting, mse, rng=np.random.default_rng(3),
        baselines={"dtheta": "train only"},
    )  # fmt: skip
    draws = np.random.default_rng(3).integers(7, size=(N_BOOTSTRAP, 7))
    ratios = [hip[i, 1].mean() / train[i, 1].mean() for i in draws]
    want = np.percentile(ratios, [2.5, 97.5])
    assert [got["dtheta"]["low"], got["dtheta"]["high"]] == pytest.approx(
        want, rel=1e-12
    )
    assert got["dtheta"]["share_at_least_1"] == np.mean(np.array(ratios) >= 1)
    assert {d: v for d, v in got.items() if d != "dtheta"} == {
        d: v for d, v in plain.items() if d != "dtheta"
    }


def test_ratio_intervals_give_none_where_a_resample_can_divide_by_zero():
    """Two settings, the best baseline exact (MSE 0) on dx_dot of the first
    only: a quarter of the resamples hold that setting alone and have no ratio,
    so dx_dot has no interval (its ratio of means over both settings exists);
    every other dimension has one, the HiP-MDP at half the baseline: [0.5, 0.5]."""
    base = np.ones((2, 4))
    base[0, 2] = 0.0
    per_setting = {"hipmdp": 0.5 * np.ones((2, 4)), "batch only": base,
                   "train only": 2.0 * np.ones((2, 4))}  # fmt: skip
    mse = {m: {d: {"mean": v[:, j].mean()} for j, d in enumerate(DIM_NAMES)}
           for m, v in per_setting.items()}  # fmt: skip
    got = ratio_intervals(per_setting, mse, rng=np.random.default_rng(0))
    assert got["dx_dot"] is None
    for d in ("dx", "dtheta", "dtheta_dot"):
        assert got[d]["low"] == pytest.approx(0.5) == got[d]["high"], d


def test_the_paper_preset_is_the_papers_protocol(tmp_path):
    """The module docstring's protocol (the paper's Table 1): the seven training
    settings as printed, (0.3, 0.4) twice; the 5 × 5 grid of pole masses
    0.1–0.3 kg by half-lengths 0.4–0.6 m (quick: the 3 × 3 grid in steps of
    0.1); 5 Sarsa agents × 30 episodes × ≤ 300 steps per training setting; 5
    fits; 50 train and 50 test transitions."""
    out = ["--out", str(tmp_path / "run"), "--no-record"]
    paper, _ = parse_args(["--preset", "paper", *out])
    grid = [(m, l) for m in np.linspace(0.1, 0.3, 5) for l in np.linspace(0.4, 0.6, 5)]
    np.testing.assert_allclose(paper.test_settings, grid)
    assert len(paper.train_settings) == 7
    assert paper.train_settings.count((0.3, 0.4)) == 2
    assert (paper.batch_repetitions, paper.batch_episodes) == (5, 30)
    assert paper.batch_max_steps == 300 and paper.n_runs == 5
    assert paper.n_train == paper.n_test == 50
    quick, _ = parse_args(out)
    assert quick.train_settings == paper.train_settings
    np.testing.assert_allclose(
        quick.test_settings, [(m, l) for m in (0.1, 0.2, 0.3) for l in (0.4, 0.5, 0.6)]
    )


def test_cli_runs_the_parsed_config_and_prints_the_ratios(
    tmp_path, monkeypatch, capsys
):
    """What the command prints: where it wrote (its recording, cartpole.rrd,
    too), and per dimension the HiP-MDP's
    MSE over the best baseline's, with its bootstrap interval where the run has
    one and that baseline's name, or none where the baseline predicts the
    dimension exactly (main stubbed: the parsed config reaches it)."""
    from tasks import cartpole_prediction as cp

    given = []
    metrics = {
        "mse": {"hipmdp": {"dx": {"mean": 1.0}, "dtheta": {"mean": 1.0}},
                "train only": {"dx": {"mean": 2.0}, "dtheta": {"mean": 3.0}},
                "batch only": {"dx": {"mean": 4.0}, "dtheta": {"mean": 0.0}}},
        "mse_ratio_to_best_baseline": {"dx": 0.5, "dtheta": None},
        "mse_ratio_to_best_baseline_interval": {
            "dx": {"low": 0.25, "high": 1.5}, "dtheta": None},
    }  # fmt: skip

    def fake_main(config, out):
        given.append((config, out))
        (tmp_path / "cartpole.rrd").touch()  # the run recorded
        return cp.Results(tmp_path, metrics)

    monkeypatch.setattr(cp, "main", fake_main)
    assert cp.cli(["--runs", "3", "--out", str(tmp_path)]) == 0
    ((config, out),) = given
    assert config.n_runs == 3 and str(out) == str(tmp_path)
    assert capsys.readouterr().out.splitlines() == [
        f"wrote {tmp_path}/ (report.md, metrics.json, figures, recording)",
        "HiP-MDP MSE / the best baseline's (95% bootstrap interval over the test "
        "settings; below 1: the HiP-MDP is better):",
        "  dx: 0.5 [0.25, 1.5] against train only",
        "  dtheta: none (batch only predicts it exactly)",
        f"tables and plain-language results: {tmp_path / 'report.md'}",
    ]
    # a method added with --method: its MSE over the HiP-MDP's, per dimension
    metrics["mse"]["mine"] = {"dx": {"mean": 240.0}, "dtheta": {"mean": 0.5}}
    (tmp_path / "cartpole.rrd").unlink()  # not a run's folder: run_dir refuses it
    assert cp.cli(["--out", str(tmp_path)]) == 0
    assert capsys.readouterr().out.splitlines()[-2] == (
        "mine (added) MSE / the HiP-MDP's (ratio of means; above 1: the HiP-MDP is "
        "better): dx 2.4e+02, dtheta 0.5"
    )
    # paired by dimension name, not position; none where the HiP-MDP has none
    metrics["mse"]["mine"] = {"dtheta": {"mean": 0.5}, "dx": {"mean": 240.0}}
    metrics["mse"]["hipmdp"]["dtheta"] = {"mean": 0.0}
    (tmp_path / "cartpole.rrd").unlink()
    assert cp.cli(["--out", str(tmp_path)]) == 0
    assert capsys.readouterr().out.splitlines()[-2].endswith(": dtheta n/a, dx 2.4e+02")


def test_the_report_names_the_fit_choices_the_flags_changed(run, tmp_path):
    """A run made with ``--filter-weights training`` or ``--new-features
    multiple_try`` says so in its report.md; a run at the defaults says
    nothing of them."""
    from tasks import prediction_report

    assert_names_fit_choices(run, prediction_report.write_report, TINY, tmp_path, "\n")
