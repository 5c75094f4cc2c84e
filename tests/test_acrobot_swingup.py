"""Smoke test: the swing-up experiment's main runs in-process on a tiny config and
writes every artefact with the documented schema."""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import re
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats
from threadpoolctl import threadpool_limits

import hipmdp
from tasks import acrobot_swingup as swingup
from tasks import compare_runs, prediction, swingup_report
from tasks.acrobot_swingup import (
    PRESETS,
    SwingupConfig,
    main,
    parse_args,
    run_test_instances,
    step_limit_split,
    transfer_metrics,
)
from tasks.experiment import fmt_ci, to_jsonable, trial_seeds
from tasks.prediction import score_settings
from tasks.recording import rrd_contents
from tasks.transfer import (
    METHODS,
    TransferConfig,
    TrialResult,
    run_trial,
    trial_label,
)
from tests._prediction import assert_coverage_schema, assert_names_fit_choices
from tests._rrd import rrd_components, rrd_scalars, rrd_times
from tests._seed_spread import assert_reads_the_run

TINY = SwingupConfig(
    name="tiny",
    train_masses=((0.7, 0.7), (1.3, 1.3), (0.7, 1.3)),
    test_masses=((0.9, 1.1),),
    batch_episodes=2,
    batch_max_steps=150,
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
    n_trials=1,
    transfer=TransferConfig(
        n_episodes=2,
        planning_episodes=1,
        initial_planning_episodes=1,
        n_start_states=2,
        max_steps=60,
        planning_max_steps=60,
    ),  # fmt: skip
    mse_train=15,
    mse_test=15,
    n_floor_settings=1,
    final_window=1,
    workers=1,
    progress=False,
)


@pytest.fixture(scope="module")
def run(tiny_swingup):
    # main(TINY), as a user calling main after `import numpy`: OpenBLAS at two
    # threads (conftest.py)
    return tiny_swingup.results


def test_artefacts_exist(run):
    names = {p.name for p in run.out.iterdir()}
    expected = {
        "config.json", "metrics.json", "report.md", "learning_curves.png",
        "weights.png", "acrobot.rrd", "hipmdp_model.npz", "batch.npz", "trials.npz",
    }  # fmt: skip
    assert expected <= names
    assert not [n for n in names if n.endswith(".tmp")]
    report = (run.out / "report.md").read_text()
    m = json.loads((run.out / "metrics.json").read_text())
    median = m["true_model_final_median_return"]
    assert f"true model's final median\n({median:.1f})" in report
    # one test setting: its per-setting intervals are of one sample, and say so
    # (the MSE ratio line printed "[nan, nan]")
    assert "no interval: one sample" in report
    assert "[nan" not in report and "nan]" not in report
    # and in the singular ("1 test mass settings × 1 trials", "these 1 settings")
    assert "\n1 test mass setting × 1 trial per method;" in report
    assert "so it answers for this setting;" in report


def test_metrics_schema(run):
    m = json.loads((run.out / "metrics.json").read_text())
    split = m["step_limit_split"]
    for method in METHODS:  # every trial has all episodes: the mean of the curve
        want = np.mean(m["returns"][method]["mean"])
        assert split["methods"][method]["mean_return"] == pytest.approx(want)
        rate = np.mean(m["step_limit_rate"][method])
        assert split["methods"][method]["share_at_limit"] == pytest.approx(rate)
    assert "step_limit_split" in (run.out / "report.md").read_text()
    assert set(m["episodes_to_near_optimal"]) == set(METHODS)
    for method in METHODS:
        curve = m["returns"][method]
        assert len(curve["mean"]) == TINY.transfer.n_episodes
        if curve["n_trials"] < 2:  # one trial: no interval (null), not a point
            assert curve["low"] == curve["high"] == [None] * len(curve["mean"])
        else:
            assert np.all(np.array(curve["low"]) <= np.array(curve["mean"]))
        # returns are -steps, bounded by the step limit
        assert all(-TINY.transfer.max_steps <= r <= -1 for r in curve["mean"])
    for method in ("hipmdp", "batch only", "train only", "batch + train"):
        assert set(m["mse"][method]) == {
            "dtheta1", "dtheta2", "dtheta1_dot", "dtheta2_dot"
        }  # fmt: skip
        assert all(v["mean"] >= 0 for v in m["mse"][method].values())
    assert m["n_latent_features"] == len(m["z"]) - 1
    # the one test setting is not a training one: the "unseen" table is the table
    assert m["test_settings_seen"] == [False] and m["unseen"]["n_instances"] == 1
    for method, dims in m["mse"].items():
        for d, v in dims.items():
            assert m["unseen"]["mse"][method][d]["mean"] == pytest.approx(v["mean"])
        assert np.array(m["per_setting_mse"][method]).shape == (1, 4)
        assert len(m["per_setting_loglik"][method]) == 1
    for method, lead in m["loglik_difference"].items():  # HiP-MDP minus method
        ll = m["per_setting_loglik"]
        assert lead["mean"] == pytest.approx(ll["hipmdp"][0] - ll[method][0])
    for d in m["paired_difference"].values():  # one setting: its mean is the mean
        assert d["by_setting"]["mean"] == pytest.approx(d["all_episodes"]["mean"])
        assert d["by_setting"]["n"] == 1
    assert json.loads((run.out / "config.json").read_text())["seed"] == 0
    # the run pinned BLAS to one thread, whatever the caller had (one_blas_thread)
    assert {b["num_threads"] for b in m["environment"]["blas"]} == {1}
    assert "Machine: " in (run.out / "report.md").read_text()
    assert_coverage_schema(
        m, list(m["mse"]["hipmdp"]), (run.out / "report.md").read_text()
    )


def test_paired_differences_and_step_limit_rates_agree_with_the_curves(run):
    m = json.loads((run.out / "metrics.json").read_text())
    curves, limit = m["returns"], m["step_limit_rate"]
    for pair, d in m["paired_difference"].items():
        a, b = pair.split(" - ")
        # the mean of the paired differences is the difference of the means
        gap = np.array(curves[a]["mean"]) - np.array(curves[b]["mean"])
        np.testing.assert_allclose(d["per_episode"]["mean"], gap, atol=1e-9)
        np.testing.assert_allclose(d["all_episodes"]["mean"], gap.mean(), atol=1e-9)
    for pair, rows in m["paired_difference_per_setting"].items():
        # one test setting: the per-setting interval is the overall one
        assert [r["masses"] for r in rows] == [list(x) for x in TINY.test_masses]
        overall = m["paired_difference"][pair]["all_episodes"]
        assert rows[0]["mean"] == pytest.approx(overall["mean"], abs=1e-9)
    cap = TINY.transfer.max_steps
    for method in METHODS:
        assert len(limit[method]) == TINY.transfer.n_episodes
        # a mean return of -cap means every trial hit the limit, and only then
        at_cap = np.isclose(curves[method]["mean"], -cap)
        assert np.array_equal(at_cap, np.isclose(limit[method], 1.0))


def test_trial_file_holds_what_the_curves_summarise(run):
    m = json.loads((run.out / "metrics.json").read_text())
    with np.load(run.out / "trials.npz", allow_pickle=False) as f:
        assert f["methods"].tolist() == list(METHODS)
        np.testing.assert_array_equal(f["test_masses"], TINY.test_masses)
        returns, steps = f["returns"], f["steps"]
    shape = (len(METHODS), len(TINY.test_masses), TINY.n_trials)
    assert returns.shape == steps.shape == (*shape, TINY.transfer.n_episodes)
    np.testing.assert_array_equal(returns, -steps)  # the acrobot's -1 per step
    for i, method in enumerate(METHODS):
        per_trial = returns[i].reshape(-1, returns.shape[-1])
        np.testing.assert_allclose(per_trial.mean(0), m["returns"][method]["mean"])


def test_results_do_not_depend_on_the_callers_blas_threads(run, tmp_path):
    # `run` was made by a caller at two BLAS threads; without the limit inside
    # main, its fitted f differs from a one-thread caller's by ~6e-9 here
    with threadpool_limits(limits=1):
        again = main(TINY, out=tmp_path)
    comparison = compare_runs.main(run.out, again.out)
    assert comparison.arrays["hipmdp_model.npz:f"] == "identical"
    assert comparison.identical, compare_runs.report(comparison)


def test_results_do_not_depend_on_the_workers(run, tmp_path):
    # `run` gathered its batch and ran its trials in one process; here they are
    # spread over two: each job draws from its own seed, so where (and in which
    # order) it runs cannot change it (`workers` is not a difference, as
    # compare_runs counts them)
    again = main(dataclasses.replace(TINY, workers=2), out=tmp_path)
    comparison = compare_runs.main(run.out, again.out)
    assert comparison.identical, compare_runs.report(comparison)


def test_model_file_loads_and_predicts(run):
    model = hipmdp.load(run.out / "hipmdp_model.npz")
    batch = hipmdp.Transitions.load(run.out / "batch.npz")
    mean, var = model.predict(batch.states[:5], batch.actions[:5], model.prior())
    assert mean.shape == (5, 4) and np.all(var > 0)


def test_recording_has_the_panels(run):
    rows = rrd_contents(run.out / "acrobot.rrd")
    metrics = json.loads((run.out / "metrics.json").read_text())
    for m in METHODS:
        assert rows[f"/returns/{m}"] == TINY.transfer.n_episodes
        # the panel's curve is the mean return per episode (one trial: its
        # interval's bounds are NaN, so a panel of a bound shows)
        np.testing.assert_array_equal(
            rrd_scalars(run.out / "acrobot.rrd", f"/returns/{m}")[:, 0],
            metrics["returns"][m]["mean"],
        )
    # every step of the traced trial: T + 1 poses per episode, + 1 static style row
    hip_steps = -np.array(metrics["returns"]["hipmdp"]["mean"])  # one trial: exact
    assert rows["/rollout/hipmdp/real"] == int(hip_steps.sum()) + len(hip_steps) + 1
    has_belief = any(e.startswith("/belief/w") for e in rows)
    assert has_belief == (metrics["n_latent_features"] > 0)
    # the links as bodies (solid capsules), the predictions as thin lines
    file = run.out / "acrobot.rrd"
    assert "Capsules3D:quaternions" in rrd_components(file, "/rollout/hipmdp/real")
    assert "LineStrips3D:strips" in rrd_components(file, "/rollout/hipmdp/predicted")


def test_recording_timelines_play_the_episodes_in_turn(run):
    """Episodes numbered from 1 as in report.md; ``step`` counts on across the
    trial's episodes (a step that restarted each episode put every episode on
    the same instants, where the viewer shows one of them); each episode's
    predictions sit on its real steps but the first."""
    file = run.out / "acrobot.rrd"
    metrics = json.loads((file.parent / "metrics.json").read_text())
    n_ep = TINY.transfer.n_episodes
    lengths = 1 - np.array(metrics["returns"]["hipmdp"]["mean"], dtype=int)
    real = rrd_times(file, "/rollout/hipmdp/real")
    np.testing.assert_array_equal(real["step"], np.arange(lengths.sum()))
    np.testing.assert_array_equal(
        real["episode"], np.repeat(np.arange(n_ep) + 1, lengths)
    )
    predicted = rrd_times(file, "/rollout/hipmdp/predicted")
    firsts = np.cumsum(lengths) - lengths
    np.testing.assert_array_equal(predicted["step"], np.delete(real["step"], firsts))
    returns = rrd_times(file, "/returns/hipmdp")
    np.testing.assert_array_equal(returns["episode"], np.arange(n_ep) + 1)
    assert set(returns) == {"episode"}
    if metrics["n_latent_features"] > 0:
        belief = rrd_times(file, "/belief/w1/mean")
        np.testing.assert_array_equal(belief["step"], real["step"])
        np.testing.assert_array_equal(belief["episode"], real["episode"])


def test_one_episode_under_rerun_off(run, tmp_path, monkeypatch):
    """``--episodes 1`` is accepted, and its report.md used to fail on the
    table's episode-2 column; under RERUN=off the run records nothing and its
    config.json and report.md say so (they said a recording was written); in
    the folder of a run with a recording, that recording goes (it would sit
    beside files it does not show)."""
    shutil.copytree(run.out, tmp_path, dirs_exist_ok=True)  # the last run's files
    assert (tmp_path / "acrobot.rrd").exists()  # else the check below is empty
    monkeypatch.setenv("RERUN", "off")
    one = dataclasses.replace(TINY.transfer, n_episodes=1)
    run = main(dataclasses.replace(TINY, transfer=one), out=tmp_path)
    report = (run.out / "report.md").read_text()
    assert "| method | episode 1 | episodes to near-optimal |" in report
    assert "No recording (`--no-record` or `RERUN=off`)." in report
    assert "rerun acrobot.rrd" not in report
    assert not (run.out / "acrobot.rrd").exists()
    assert json.loads((run.out / "config.json").read_text())["record"] is False


def test_a_failing_figure_keeps_the_metrics(tmp_path, monkeypatch):
    """The artefacts come after the minutes of work; metrics.json used to be
    written after them, so a failing figure (or recording) lost every number."""

    def fail(*args):
        raise RuntimeError("no figure today")

    monkeypatch.setattr(swingup_report, "_weights_figure", fail)
    with pytest.raises(RuntimeError, match="no figure today"):
        main(TINY, out=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert len(metrics["returns"]["hipmdp"]["mean"]) == TINY.transfer.n_episodes


class PredictsOnlyForItsTries:
    """A model whose predict fails once adapted to more transitions than
    fit_all's tries give it (as a prediction table's train split does), and
    whose predict_mean, which planning calls, never fails."""

    def fit(self, batch, *, rng):
        pass

    def adapt(self, train, *, rng):
        self.n = len(train)
        return self

    def predict_mean(self, states, actions):
        return np.zeros(np.shape(states))

    def predict(self, states, actions):
        if self.n > 10:
            raise RuntimeError("predict on a long train split")
        return np.zeros(np.shape(states)), np.ones(np.shape(states))


def test_a_failing_prediction_table_keeps_the_trials(tmp_path):
    """The prediction table comes after the transfer trials, the run's long
    stage: their trials.npz is written before it."""
    late = "late=tests.test_acrobot_swingup:PredictsOnlyForItsTries"
    config = dataclasses.replace(TINY, methods=(late,), record=False)
    assert config.mse_train > 10
    with pytest.raises(RuntimeError, match="predict on a long train split"):
        main(config, out=tmp_path)
    assert not (tmp_path / "metrics.json").exists()
    with np.load(tmp_path / "trials.npz", allow_pickle=False) as f:
        assert list(f["methods"]) == [*METHODS, "late"]
        assert f["returns"].shape[-1] == TINY.transfer.n_episodes


def test_cli_presets_and_bad_options(capsys):
    config, out = parse_args(["--preset", "paper", "--seed", "3", "--workers", "1"])
    assert config.seed == 3 and config.workers == 1 and len(config.test_masses) == 16
    assert PRESETS["quick"].preset == "quick" and out is None
    with pytest.raises(SystemExit):
        parse_args(["--workers", "0"])
    assert "--workers (workers): expected >= 1" in capsys.readouterr().err
    for bad, flag in (("-1", "--seed"), ("x", "--seed"), ("0", "--trials")):
        with pytest.raises(SystemExit):
            parse_args([flag, bad])
        assert flag in capsys.readouterr().err
    # fewer than 3 episodes: the target is the true model's mean over all of them
    config, _ = parse_args(["--episodes", "2"])
    assert config.transfer.n_episodes == 2 and config.final_window == 2
    # more: still the preset's last 3
    config, _ = parse_args(["--episodes", "10"])
    assert config.final_window == PRESETS["quick"].final_window == 3
    with pytest.raises(SystemExit):
        parse_args(["--episodes", "0"])
    assert "--episodes" in capsys.readouterr().err
    assert SwingupConfig(n_floor_settings=0).n_floor_settings == 0  # no floor table
    with pytest.raises(ValueError, match="link_mass_1"):
        SwingupConfig(test_masses=((0.0, 1.0),))
    with pytest.raises(ValueError, match="final_window: expected <= "):
        SwingupConfig(final_window=50)
    # absurd counts: refused here, not after the batch data and the fit (10**12
    # trials hung seeding them, 10**12 episodes failed allocating)
    for args, match in [
        (["--trials", str(10**12)], r"--trials \(n_trials\): expected at most 100,000"),
        (["--trials", "25001"], r"at most 100,000 .* got 100,004"),
        (["--episodes", str(10**12)], r"--episodes \(n_episodes\): expected at most"),
    ]:
        with pytest.raises(SystemExit):
            parse_args(args)
        assert re.search(match, capsys.readouterr().err)
    assert parse_args(["--trials", "25000"])[0].n_trials == 25000
    assert parse_args(["--split", "time"])[0].split == "time"
    assert PRESETS["quick"].split == PRESETS["paper"].split == "random"
    # each flag changes only its field of the fit, and the two together both
    for name in ("quick", "paper"):
        fit = PRESETS[name].fit
        assert (fit.filter_weights, fit.new_features) == ("prior_mean", "paper")
        config, _ = parse_args(["--preset", name, "--filter-weights", "training"])
        assert config.fit == dataclasses.replace(fit, filter_weights="training")
        config, _ = parse_args(["--preset", name, "--new-features", "multiple_try"])
        assert config.fit == dataclasses.replace(fit, new_features="multiple_try")
        config, _ = parse_args(
            ["--preset", name, "--new-features", "multiple_try",
             "--filter-weights", "training"]
        )  # fmt: skip
        assert config.fit == dataclasses.replace(
            fit, new_features="multiple_try", filter_weights="training"
        )
    for flag, bad in [("--filter-weights", "mean"), ("--new-features", "exact")]:
        with pytest.raises(SystemExit):
            parse_args([flag, bad])
        assert f"{flag}: invalid choice: '{bad}'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="split: expected one of"):
        SwingupConfig(split="episodes")


def test_time_split_reaches_the_prediction_table(run, monkeypatch):
    splits, gather = [], prediction.gather_split

    def gather_spy(*args, **kwargs):
        splits.append(gather(*args, **kwargs))
        return splits[-1]

    def score_stub(hips, average, batch, train, test, rng, n_max, added, key):
        return prediction.InstanceScores(
            {m: np.ones(4) for m in prediction.PREDICTION_METHODS},
            {m: 0.0 for m in prediction.PREDICTION_METHODS},
            {
                m: np.ones((len(prediction.COVERAGE_LEVELS), 4))
                for m in prediction.PREDICTION_METHODS
            },
        )

    monkeypatch.setattr(prediction, "gather_split", gather_spy)
    monkeypatch.setattr(prediction, "score_instance", score_stub)
    config = dataclasses.replace(TINY, split="time")
    swingup.prediction_table(config, None, None, None, np.random.SeedSequence(0))
    assert len(splits) == len(config.test_masses) + config.n_floor_settings
    for split in splits:  # the first transitions to train on, the last to test on
        n = len(split.episodes)
        assert n > config.mse_train + config.mse_test
        np.testing.assert_array_equal(
            split.train.states, split.episodes.states[: config.mse_train]
        )
        np.testing.assert_array_equal(
            split.test.states, split.episodes.states[n - config.mse_test :]
        )
    assert "(random split)" in (run.out / "report.md").read_text()


@pytest.mark.parametrize(
    ("field", "bad"),
    [
        ("seed", -1),
        ("seed", "0"),
        ("seed", 1.5),
        ("n_trials", 2.5),
        ("n_trials", True),
        ("fit", {}),
        ("transfer", {}),
        ("record", "no"),
        ("progress", 1),
        ("final_window", 0),  # [-0:] would average every episode
        ("n_floor_settings", -1),  # [:-1] would score all training settings but one
        ("n_floor_settings", len(swingup.TRAIN_MASSES) + 1),
    ],
)
def test_config_fields_of_the_wrong_type_are_refused_on_construction(field, bad):
    """Before any work: a float count or a string seed would otherwise fail (or
    be truncated) minutes into a run, after its folder was written."""
    with pytest.raises(ValueError, match=f"^{field}: expected"):
        SwingupConfig(**{field: bad})


def test_every_method_meets_the_same_initial_states(run):
    # Same instances and seeds for every method: the real episodes of one
    # (setting, trial) start from the same states whatever the method.
    from hipmdp import baselines
    from tasks.acrobot_swingup import run_transfer

    hip = hipmdp.load(run.out / "hipmdp_model.npz")
    batch = hipmdp.Transitions.load(run.out / "batch.npz")
    average = baselines.batch_only(batch, rng=np.random.default_rng(0), n_max=100)
    trials = run_transfer(TINY, hip, average, np.random.SeedSequence(7))
    starts = {
        r.method: [trace.states[0] for trace in r.traces] for r in trials if r.traces
    }
    assert set(starts) == set(METHODS)
    for method in METHODS:
        np.testing.assert_array_equal(starts[method], starts["true"])
    assert not np.array_equal(starts["true"][0], starts["true"][1])  # reset differs


def test_median_view_is_not_decided_by_one_failed_episode():
    """One trial at the step limit drags the HiP-MDP's episode-1 mean out of the
    10% band; its median stays in it, so the two near-optimal counts differ."""
    cap = TINY.transfer.max_steps
    base = np.array([[-20.0, -20.0], [-21.0, -20.0], [-19.0, -20.0]])
    returns = {m: base.copy() for m in METHODS}
    returns["hipmdp"][0, 0] = -cap  # one failure in episode 1
    config = dataclasses.replace(TINY, final_window=1, test_masses=TINY.test_masses[:1])
    m = transfer_metrics(config, _trials(returns))
    for method, r in returns.items():
        np.testing.assert_array_equal(m["median_returns"][method], np.median(r, 0))
    assert m["true_model_final_median_return"] == -20.0
    assert m["episodes_to_near_optimal"]["hipmdp"] == 2
    assert m["episodes_to_near_optimal_median"]["hipmdp"] == 1
    assert m["episodes_to_near_optimal_median"]["true"] == 1


def test_per_setting_differences_group_trials_by_setting():
    """Setting 0: the HiP-MDP gains 10 steps on every trial; setting 1: it loses 4
    on one trial and gains 2 on the other. The overall interval mixes them. The
    HiP-MDP's trials arrive in the other order: pairing by list position would
    pair trial 0 with trial 1 and widen setting 0's zero-width interval."""
    rng = np.random.default_rng(0)
    base = {(s, t): -100.0 + rng.normal(size=2) for s in (0, 1) for t in (0, 1)}
    gain = {(0, 0): 10.0, (0, 1): 10.0, (1, 0): -4.0, (1, 1): 2.0}
    trials = [
        TrialResult(
            m,
            s,
            t,
            r + (gain[s, t] if m == "hipmdp" else 0.0),
            -r,
            np.zeros((3, 1)),
            None,
        )  # fmt: skip
        for (s, t), r in base.items()
        for m in METHODS
    ]
    trials.sort(key=lambda r: -r.trial if r.method == "hipmdp" else r.trial)
    config = dataclasses.replace(TINY, test_masses=((0.7, 0.9), (1.3, 1.1)), n_trials=2)
    rows = transfer_metrics(config, trials)["paired_difference_per_setting"]
    hip_avg = rows["hipmdp - average"]
    assert [r["masses"] for r in hip_avg] == [[0.7, 0.9], [1.3, 1.1]]
    assert hip_avg[0]["mean"] == pytest.approx(10.0)
    assert hip_avg[0]["low"] == pytest.approx(10.0)  # no spread: a zero-width interval
    assert hip_avg[1]["mean"] == pytest.approx(-1.0)
    # setting 1: the t-interval of its 2 trials' gains (the unit is the trial, so
    # 1 degree of freedom; the episodes of a trial are not independent samples)
    half = stats.t.ppf(0.975, 1) * np.std([-4.0, 2.0], ddof=1) / np.sqrt(2)
    low, high = hip_avg[1]["low"], hip_avg[1]["high"]
    assert [low, high] == pytest.approx([-1.0 - half, -1.0 + half], rel=1e-12)
    assert all(r["mean"] == pytest.approx(0.0) for r in rows["average - true"])


def test_transfer_metrics_pair_methods_by_setting_and_trial_in_any_order():
    """3 settings x 4 trials whose (setting, trial) effects are shared by every
    method and dwarf the differences: only a correct pairing gives the narrow
    paired intervals of a hand-paired reference. The trials arrive shuffled,
    each method in its own order."""
    rng = np.random.default_rng(3)
    n_settings, n_trials, n_episodes = 3, 4, 2
    shared = rng.normal(0.0, 30.0, size=(n_settings, n_trials, n_episodes)) - 120
    effect = {m: rng.normal(0.0, 1.0, size=shared.shape) for m in METHODS}
    returns = {m: shared + effect[m] + 3.0 * (m == "hipmdp") for m in METHODS}
    trials = [
        TrialResult(m, s, t, returns[m][s, t], -returns[m][s, t],
                    np.zeros((n_episodes + 1, 1)), None)
        for m in METHODS for s in range(n_settings) for t in range(n_trials)
    ]  # fmt: skip
    trials = [trials[i] for i in rng.permutation(len(trials))]
    config = dataclasses.replace(
        TINY,
        test_masses=((0.7, 0.9), (1.0, 1.0), (1.3, 1.1)),
        n_trials=n_trials,
        final_window=1,
    )
    got = transfer_metrics(config, trials)["paired_difference"]["hipmdp - average"]
    diff = (returns["hipmdp"] - returns["average"]).mean(axis=2)  # (setting, trial)
    t = stats.t.ppf(0.975, diff.size - 1)
    half = t * diff.std(ddof=1) / np.sqrt(diff.size)
    want = {"mean": diff.mean(), "low": diff.mean() - half, "high": diff.mean() + half}
    for k, v in want.items():
        assert got["all_episodes"][k] == pytest.approx(v, rel=1e-12)
    by_setting = diff.mean(axis=1)
    half = stats.t.ppf(0.975, 2) * by_setting.std(ddof=1) / np.sqrt(3)
    assert got["by_setting"]["low"] == pytest.approx(by_setting.mean() - half)
    assert got["by_setting"]["high"] == pytest.approx(by_setting.mean() + half)
    # unpaired, the shared effects would make the interval about 40 times wider
    assert got["all_episodes"]["high"] - got["all_episodes"]["low"] < 3.0


def test_step_limit_split_adds_up_and_counts_only_limit_episodes():
    # 2 methods x 4 episodes: "true" fails once (−50), "average" twice
    returns = np.array([[-10.0, -12.0, -50.0, -8.0], [-50.0, -11.0, -50.0, -9.0]])
    steps = -returns.astype(int)
    split = step_limit_split(returns, steps, 50, methods=("true", "average"))
    t, a = split["methods"]["true"], split["methods"]["average"]
    assert t["share_at_limit"] == 0.25 and a["share_at_limit"] == 0.5
    assert t["mean_return_below_limit"] == pytest.approx(-10.0)
    assert a["mean_return_below_limit"] == pytest.approx(-10.0)
    pair = split["pairs"]["average - true"]
    assert set(split["pairs"]) == {"average - true"}  # pairs of known methods only
    assert pair["gap"] == pytest.approx(-30.0 - -20.0)
    assert pair["below_limit"] == pytest.approx(0.0)
    assert pair["limit"] == pytest.approx(-10.0)
    # the identity mean = (1 - p) μ_< + p · (−cap) holds for each method
    for m in ("true", "average"):
        v = split["methods"][m]
        p = v["share_at_limit"]
        assert v["mean_return"] == pytest.approx(
            (1 - p) * v["mean_return_below_limit"] + p * -50.0
        )
    everything = step_limit_split(returns, np.full((2, 4), 50), 50, ("true", "average"))
    assert everything["methods"]["true"]["mean_return_below_limit"] is None
    assert everything["pairs"]["average - true"]["limit"] is None
    with pytest.raises(ValueError, match="equal shapes"):
        step_limit_split(returns, steps[:, :2], 50, methods=("true", "average"))
    with pytest.raises(ValueError, match="equal shapes"):  # a row per method
        step_limit_split(returns, steps, 50, methods=("true",))


def test_book_inertia_reaches_every_instance(run, tmp_path, monkeypatch):
    config, _ = parse_args(["--book-inertia"])
    assert config.book_inertia and not PRESETS["quick"].book_inertia
    assert config.params(0.7, 1.3).inertias == pytest.approx((1.0, 1.0))
    assert PRESETS["quick"].params(0.7, 1.3).inertias == pytest.approx((0.7, 1.3))
    written = {"test_masses": [[0.7, 1.3]], "book_inertia": True}
    assert run_test_instances(written)[0].inertias == pytest.approx((1.0, 1.0))
    del written["book_inertia"]  # a run from before the option: the default
    assert run_test_instances(written)[0].inertias == pytest.approx((0.7, 1.3))
    with pytest.raises(ValueError, match="book_inertia: expected a bool"):
        SwingupConfig(book_inertia=1)

    trial_params = []

    def spy(job):
        trial_params.append(job.params)
        return run_trial(job)

    monkeypatch.setattr(swingup, "run_trial", spy)
    scored = []

    def score_spy(domain, models, average, batch, instances, *args, **kwargs):
        scored.extend(instances)
        return score_settings(
            domain, models, average, batch, instances, *args, **kwargs
        )

    monkeypatch.setattr(swingup, "score_settings", score_spy)
    book = main(dataclasses.replace(TINY, book_inertia=True, record=False), tmp_path)
    for instances in (trial_params, scored):  # transfer trials, the MSE table
        assert instances
        assert all(p.inertias == pytest.approx((1.0, 1.0)) for p in instances)
    table = hipmdp.data.ParameterTable.load(book.out / "batch.npz")
    shapes = table.values[:, [table.names.index(f"link_shape_{i}") for i in (1, 2)]]
    masses = np.array(TINY.train_masses)
    np.testing.assert_allclose(shapes * masses, 1.0)  # I = k m l² = 1
    assert json.loads((book.out / "config.json").read_text())["book_inertia"]
    assert "stays at the book's 1 kg·m²" in (book.out / "report.md").read_text()
    # the same seed on other dynamics: other batch data and other returns
    ours = hipmdp.Transitions.load(run.out / "batch.npz")
    theirs = hipmdp.Transitions.load(book.out / "batch.npz")
    n = min(len(ours), len(theirs))
    assert not np.allclose(ours.next_states[:n], theirs.next_states[:n])


def test_seed_spread_reads_the_run(run, tmp_path):
    result = assert_reads_the_run(run.out, tmp_path, "acrobot_swingup")
    labels = [n["label"] for n in result["numbers"]]
    assert "HiP-MDP margin to the 10% target, episode 2" in labels


def _trials(returns: dict, setting: int = 0, n_weights: int = 1) -> list:
    """TrialResults of one setting from ``{method: (trials, episodes) returns}``,
    steps = -returns (the acrobot's -1 per step)."""
    return [
        TrialResult(m, setting, i, r[i], (-r[i]).astype(int),
                    np.zeros((r.shape[1] + 1, n_weights)), None)
        for m, r in returns.items() for i in range(len(r))
    ]  # fmt: skip


def test_near_optimal_is_10_percent_of_the_true_models_last_episodes():
    """3 trials x 4 episodes, final_window 2. The true model's mean curve is
    [-40, -30, -32.67, -27.33]: the target is the mean of its last two, -30, and
    within 10% is >= -33; its median curve is [-40, -30, -24, -16], target -20,
    within 10% >= -22. The HiP-MDP's curve [-35, -23, -21, -21] is within 20%
    of either target an episode earlier than within 10%, and within 10% of the
    first episodes' target (-35) from episode 1. Episodes of 50 steps ran to the
    50-step limit."""
    true = np.array(
        [[-40, -30, -24, -16], [-40, -30, -24, -16], [-40, -30, -50, -50]], float
    )
    hip = np.tile([-35.0, -23.0, -21.0, -21.0], (3, 1))
    average = np.full((3, 4), -45.0)
    config = dataclasses.replace(
        TINY,
        n_trials=3,
        final_window=2,
        transfer=dataclasses.replace(TINY.transfer, n_episodes=4, max_steps=50),
    )
    m = transfer_metrics(
        config, _trials({"true": true, "average": average, "hipmdp": hip})
    )
    assert m["near_optimal_target"]["true_model_final_mean_return"] == -30.0
    assert m["near_optimal_target"]["final_window"] == 2
    assert m["true_model_final_median_return"] == -20.0
    assert m["episodes_to_near_optimal"] == {"true": 2, "average": None, "hipmdp": 2}
    assert m["episodes_to_near_optimal_median"]["hipmdp"] == 3
    # per trial, the threshold is 10% below that trial's true mean over the last
    # 2 episodes: -22, -22, -55; episode 1's margins -13, -13, +20
    assert m["margin_to_target"]["hipmdp"]["mean"][0] == pytest.approx(-2.0)
    np.testing.assert_allclose(m["step_limit_rate"]["true"], [0, 0, 1 / 3, 1 / 3])
    np.testing.assert_array_equal(m["step_limit_rate"]["hipmdp"], 0.0)


def test_test_belief_means_average_each_settings_final_beliefs():
    """weights.png places each test setting at the mean, over its trials, of the
    HiP-MDP's belief after the last episode (not the prior it started from)."""
    returns = {m: np.full((2, 2), -30.0) for m in METHODS}
    trials = _trials(returns, 0, 2) + _trials(returns, 1, 2)
    final = {(0, 0): [1, 2], (0, 1): [3, 4], (1, 0): [10, 20], (1, 1): [30, 40]}
    for r in trials:
        if r.method == "hipmdp":
            r.weight_means[-1] = final[r.setting, r.trial]
    config = dataclasses.replace(TINY, n_trials=2, test_masses=((0.7, 0.9), (1.3, 1.1)))
    got = transfer_metrics(config, trials)["test_belief_means"]
    assert got == {"0": [2.0, 3.0], "1": [20.0, 30.0]}


def test_trial_arrays_put_each_trial_at_its_method_setting_and_trial():
    """trials.npz's returns[method, setting, trial] is that trial's; a missing
    trial is refused rather than left as NaN."""
    config = dataclasses.replace(TINY, n_trials=3, test_masses=((0.7, 0.9), (1.3, 1.1)))
    trials = [
        TrialResult(m, s, t, np.array([-(100 * i + 10 * s + t + 1.0)] * 2),
                    np.array([100 * i + 10 * s + t + 1] * 2), None, None)
        for i, m in enumerate(METHODS) for s in range(2) for t in range(3)
    ]  # fmt: skip
    arrays = swingup.trial_arrays(config, trials[::-1])
    assert arrays["returns"].shape == (3, 2, 3, 2)
    assert arrays["returns"][2, 1, 0, 1] == -211.0  # hipmdp, setting 1, trial 0
    np.testing.assert_array_equal(arrays["steps"], -arrays["returns"])
    with pytest.raises(ValueError, match="one result per"):
        swingup.trial_arrays(config, trials[1:])


def _table(report: str, after: str) -> list[list[str]]:
    """The cells of the first Markdown table after the text ``after``, header
    row first."""
    lines = report[report.index(after) :].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return [rows[0], *rows[2:]]  # without the |---| line


def _nan_bounds(x):
    """metrics.json's intervals as main holds them: NaN bounds where JSON has
    null (one sample)."""
    if isinstance(x, dict):
        return {
            k: np.nan if k in ("low", "high") and v is None else _nan_bounds(v)
            for k, v in x.items()
        }
    return [_nan_bounds(v) for v in x] if isinstance(x, list) else x


def test_report_tables_show_the_episodes_they_name(run, tmp_path):
    """10 episodes, one setting, 3 trials. The returns table shows episodes 1,
    2, 5 and 10; every cell is that episode's number. By hand, with d = (-3, 0,
    3) per trial: true -20 everywhere (target -20, within 10%: >= -22); average
    -30 + d; HiP-MDP -(40 - 2e) + d at 0-based episode e, except -60 (the
    60-step limit) on trial 0 of episodes 1 and 9, and -21 on trial 1 of
    episode 9. HiP-MDP means: episode 1 -45.67, 2 -38, 5 -32, 9 -34, 10 -22
    (within 10% first at 10); medians: episode 1 -40, 9 -21 (within at 9)."""
    d = np.array([-3.0, 0.0, 3.0])[:, None]
    e = np.arange(10)
    hip = -(40.0 - 2 * e) + d
    hip[0, 0] = hip[0, 8] = -60.0
    hip[1, 8] = -21.0
    returns = {
        "true": np.full((3, 10), -20.0), "average": -30.0 + d + 0 * e, "hipmdp": hip
    }  # fmt: skip
    config = dataclasses.replace(
        TINY,
        n_trials=3,
        final_window=1,
        transfer=dataclasses.replace(
            TINY.transfer, n_episodes=10, planning_max_steps=30
        ),
    )
    metrics = _nan_bounds(json.loads((run.out / "metrics.json").read_text()))
    metrics |= transfer_metrics(config, _trials(returns))
    swingup_report.write_report(tmp_path, config, metrics)
    report = (tmp_path / "report.md").read_text()

    def means(cells):  # "mean [low, high]" cells to their means
        return [float(c.split(" [")[0]) for c in cells]

    header, *rows = _table(report, "## Returns per real episode")
    assert header[1:5] == ["episode 1", "episode 2", "episode 5", "episode 10"]
    row = {r[0]: r for r in rows}
    assert list(row) == ["true model", "average model", "HiP-MDP"]
    assert means(row["HiP-MDP"][1:5]) == [-45.67, -38.0, -32.0, -22.0]
    assert row["HiP-MDP"][5] == "10" and row["average model"][5] == "not within 10"
    # final_window 1: the last episode's mean, and the report says so
    assert (
        "true model's final mean return (-20.0,\nits mean over the last episode)"
        in report
    )
    window = dict(metrics["near_optimal_target"], final_window=3)
    swingup_report.write_report(
        tmp_path, config, metrics | {"near_optimal_target": window}
    )
    assert "its mean over the last 3 episodes)" in (tmp_path / "report.md").read_text()

    # the targets, first: episode 2's margin, -16, has its interval below 0
    # (missed); the lead over the average model, -2.567, one across 0
    targets = report.split("## Against the targets")[1].split("\n## ")[0]
    lead = metrics["paired_difference"]["hipmdp - average"]["all_episodes"]
    margin = {k: v[1] for k, v in metrics["margin_to_target"]["hipmdp"].items()
              if k != "n"}  # fmt: skip
    assert margin["mean"] == pytest.approx(-16.0) and margin["high"] < 0 < lead["high"]
    assert [line for line in targets.splitlines() if line.startswith("- ")] == [
        "- HiP-MDP within 10% of the true model by episode 2, margin per trial: "
        f"{fmt_ci(margin, signed=True)} (missed)",
        "- HiP-MDP - average model, mean return over all episodes: "
        f"{fmt_ci(lead, signed=True)} (not clearly ahead)",
    ]
    assert report.index("## Against the targets") < report.index("## Returns")

    # margin per trial: the return minus -22 (10% below the true model's -20)
    header, *rows = _table(report, "Per trial, each method's return")
    assert header == ["method", "episode 1", "episode 2"]
    assert means({r[0]: r for r in rows}["HiP-MDP"][1:]) == [-23.67, -16.0]

    # HiP-MDP minus average, per trial over the episodes: -6, -0.7, -1 (trial 0:
    # -310 - 30 - 17 - 33 over 10 episodes = -39 against -33); one setting,
    # so "setting as unit" has no interval; episode 2: -8 on every trial
    header, *rows = _table(report, "## Paired differences")
    row = {r[0]: r for r in rows}["hipmdp - average"]
    assert means(row[1:]) == [-2.567, -2.567, -15.67, -8.0]
    assert row[1] != row[2] == "-2.567 [no interval: one sample]"
    assert row[4] == "-8 [-8, -8]"
    header, *rows = _table(report, "on each test setting alone")
    assert [r[0] for r in rows] == ["(0.9, 1.1)"]

    assert "(each such episode has a return of −60)" in report
    header, *rows = _table(report, "-step limit\n")
    assert header[1:] == [f"episode {i}" for i in range(1, 11)]
    hip_rate = {r[0]: r for r in rows}["HiP-MDP"][1:]
    assert hip_rate == ["33%"] + ["0%"] * 7 + ["33%", "0%"]
    # gap -2.567; below the limit: the HiP-MDP's 28 other episodes sum to
    # -977 + 120, a mean of -30.61, against the average's -30
    header, *rows = _table(report, "How much of each gap")
    assert {r[0]: r for r in rows}["hipmdp - average"][1:] == ["-2.6", "-0.6", "-2.0"]

    header, *rows = _table(report, "The same on per-episode medians")
    assert header[1:5] == ["episode 1", "episode 2", "episode 5", "episode 10"]
    row = {r[0]: r for r in rows}["HiP-MDP"]
    assert [float(c) for c in row[1:5]] == [-40.0, -38.0, -32.0, -22.0]
    assert row[5] == "9"
    header, *rows = _table(report, "Test log-likelihood")
    assert [r[0] for r in rows] == list(metrics["loglik_difference"])


def test_report_puts_the_runs_counts_in_their_sentences(run, tmp_path):
    """report.md of the run's metrics under a config whose counts all differ:
    2 test settings × 4 trials, 3 training settings, and 7 train and 9 test
    transitions per setting in the prediction table."""
    config = dataclasses.replace(
        TINY, test_masses=((0.9, 1.1), (1.1, 0.9)), n_trials=4, mse_train=7,
        mse_test=9,
    )  # fmt: skip
    metrics = _nan_bounds(json.loads((run.out / "metrics.json").read_text()))
    swingup_report.write_report(tmp_path, config, metrics)
    report = (tmp_path / "report.md").read_text()
    n_batch, n_features = metrics["n_batch_transitions"], metrics["n_latent_features"]
    assert (
        "\n2 test mass settings × 4 trials per method;\nHiP-MDP fitted on "
        f"{n_batch} batch transitions from\n3 training settings; {n_features} latent"
    ) in report
    assert "so it answers for these 2 settings;" in report
    assert "7 train and 9 test transitions per setting\n(random split)" in report
    assert "Test log-likelihood over 9 test transitions" in report


def test_report_shows_the_floor_and_z_under_their_headings(run, tmp_path):
    """The approximation floor section holds the floor's table, not the test
    settings' one; z (hand-made: feature 1 uses only dtheta1, on every action)
    is a row of 1000 per action under a legend naming the dimensions in
    metrics' order."""
    metrics = _nan_bounds(json.loads((run.out / "metrics.json").read_text()))
    dims = list(metrics["mse"]["hipmdp"])
    assert dims == ["dtheta1", "dtheta2", "dtheta1_dot", "dtheta2_dot"]
    floor = {m: {d: {"mean": 0.5 * (i + 1), "low": 0.0, "high": 1.0 * (i + 1),
                     "n": 3} for i, d in enumerate(dims)}
             for m in metrics["mse"]}  # fmt: skip
    z = np.ones((2, 3, 4), dtype=int)
    z[1] = [1, 0, 0, 0]
    metrics |= {"approximation_floor": floor, "z": z.tolist()}
    swingup_report.write_report(tmp_path, TINY, metrics)
    report = (tmp_path / "report.md").read_text()
    section = report.split("## Approximation floor")[1].split("## ")[0]
    assert prediction.mse_table(floor) in section
    assert prediction.mse_table(metrics["mse"]) not in section
    latent = report.split("## Latent structure")[1]
    assert "z for dtheta1, dtheta2, dtheta1_dot, dtheta2_dot, in that order" in latent
    assert "| 1 | 1000 | 1000 | 1000 |" in latent


def test_each_added_method_has_a_colour_of_its_own():
    """In learning_curves.png and the recording, methods added with --method
    take ADDED_COLORS in turn: each differs from the others and from the three
    built-in methods', whatever its name."""
    methods = [*METHODS, "zeta", "alpha", "mid"]
    colours = [swingup_report.color(m, methods) for m in methods]
    assert len(set(colours)) == len(methods)
    assert colours[3:] == list(swingup_report.ADDED_COLORS[:3])


def test_learning_curves_number_episodes_from_1_and_draw_the_10_percent_line(
    monkeypatch,
):
    """learning_curves.png on hand-made curves of 3 episodes over 4 trials: each
    method's mean at real episodes 1, 2, 3 (numbered as report.md's tables),
    under its label, and the dashed line "episodes to near-optimal" counts by,
    10% below the true model's final mean return: -100 - 0.1 * 100 = -110."""
    import matplotlib.pyplot as plt

    figures = []
    monkeypatch.setattr(
        swingup_report, "save_figure", lambda fig, file: figures.append(fig)
    )
    means = {
        "true": [-120.0, -105.0, -100.0],
        "average": [-200.0, -180.0, -170.0],
        "hipmdp": [-150.0, -115.0, -108.0],
    }
    metrics = {
        "returns": {
            m: {"mean": v, "low": [x - 5 for x in v], "high": [x + 5 for x in v],
                "n_trials": 4}
            for m, v in means.items()
        },
        "near_optimal_target": {"true_model_final_mean_return": -100.0,
                                "margin": 0.1},
    }  # fmt: skip
    swingup_report._learning_curves("learning_curves.png", metrics)
    (fig,) = figures
    (ax,) = fig.axes
    lines = {line.get_label(): line for line in ax.get_lines()}
    plt.close(fig)
    for m, mean in means.items():
        line = lines[swingup_report.label(m)]
        np.testing.assert_array_equal(line.get_xdata(), [1, 2, 3])
        np.testing.assert_array_equal(line.get_ydata(), mean)
    target = lines["within 10% of the true model's final mean"]
    np.testing.assert_allclose(target.get_ydata(), [-110.0, -110.0])
    assert "over 4 trials" in ax.get_title()


def test_weights_figure_plots_the_latent_weights_against_each_settings_masses(
    monkeypatch,
):
    """weights.png is given the training weights without row 0 (the mean
    dynamics, w = 1, not a latent weight) and, per test setting in order, that
    setting's mean final belief: hand-made, 2 latent weights, 3 test settings."""
    given = {}
    monkeypatch.setattr(
        swingup_report, "weights_figure", lambda *args: given.update(args=args)
    )
    config = dataclasses.replace(TINY, test_masses=((0.9, 1.1), (1.1, 0.9), (1.3, 0.7)))
    hip = SimpleNamespace(weights=[[1.0, 1.0, 1.0], [2.0, 3.0, 4.0], [5.0, 6.0, 7.0]])
    metrics = {"test_belief_means": {"0": [10.0, 11.0], "1": [20.0, 21.0],
                                     "2": [30.0, 31.0]}}  # fmt: skip
    swingup_report._weights_figure("weights.png", config, metrics, hip)
    _, train_m, train_w, test_m, test_w, labels, _ = given["args"]
    np.testing.assert_array_equal(train_w, [[2.0, 3.0, 4.0], [5.0, 6.0, 7.0]])
    np.testing.assert_array_equal(test_w, [[10, 11], [20, 21], [30, 31]])
    np.testing.assert_array_equal(train_m, TINY.train_masses)
    np.testing.assert_array_equal(test_m, config.test_masses)
    assert labels == ("m1 (kg)", "m2 (kg)")


def test_every_file_a_run_writes_is_an_artefact_it_replaces(run):
    """run_dir deletes a previous run's files by ARTEFACTS before a run starts:
    a file main writes but ARTEFACTS leaves out would outlive the run that wrote
    it (a --no-record run beside the last run's acrobot.rrd)."""
    for file in run.out.iterdir():
        assert any(fnmatch.fnmatch(file.name, p) for p in swingup.ARTEFACTS), file


def test_paper_preset_has_the_documented_sizes():
    """README and the module docstring: --preset paper is 16 test settings x 30
    trials of 20 real episodes, the approximation floor on every training
    setting."""
    paper = PRESETS["paper"]
    assert len(set(paper.test_masses)) == 16 and paper.n_trials == 30
    assert paper.transfer.n_episodes == 20
    assert paper.n_floor_settings == len(paper.train_masses)


def test_quick_test_settings_are_on_the_grid_and_not_training_ones():
    """QUICK_TEST_MASSES' comment: four test settings of the paper's grid that
    are not training settings, one per m1 (the quick run's MSE table is then all
    "unseen"); every training setting is a point of the grid, so the paper
    preset's "seen" table has them all."""
    grid = set(swingup.TEST_MASSES)
    quick = PRESETS["quick"].test_masses
    assert set(quick) <= grid and not set(quick) & set(swingup.TRAIN_MASSES)
    assert sorted(m1 for m1, _ in quick) == sorted({m1 for m1, _ in grid})
    assert set(swingup.TRAIN_MASSES) <= grid and len(set(swingup.TRAIN_MASSES)) == 8


def test_run_streams_are_the_seeds_children_in_the_documented_order():
    """RunStreams' docstring: batch data, fit, average model, trials, prediction
    table, spawned in that order from the one seed; the checks on a finished run
    (and a user) rebuild them as SeedSequence(seed).spawn(5)."""
    streams = swingup.run_streams(7)
    for i, name in enumerate(("batch", "fit", "average", "trials", "mse")):
        ss = getattr(streams, name)
        assert (ss.entropy, ss.spawn_key) == (7, (i,)), name


def test_transfer_jobs_share_seeds_across_methods_and_trace_one_trial(monkeypatch):
    """Every method meets the same (setting, trial) seed, trial_seeds' seeds[i][t]
    (the layout acrobot_identified's run_seeds relies on), each (setting, trial)
    its own; only setting 0, trial 0 is traced, and nothing with record off."""
    jobs = []

    def pool_map(fn, given, label, **kwargs):  # record the jobs, run none
        jobs.extend(given)
        labels.extend(map(label, given))
        return []

    labels = []
    monkeypatch.setattr(swingup, "pool_map", pool_map)
    config = dataclasses.replace(
        TINY, test_masses=((0.7, 0.9), (1.3, 1.1)), n_trials=3, record=True
    )
    swingup.run_transfer(config, None, None, np.random.SeedSequence(5))
    seeds = trial_seeds(np.random.SeedSequence(5), 2, 3)
    assert len(jobs) == len(METHODS) * 2 * 3
    for job, label in zip(jobs, labels, strict=True):  # the bar names the trial
        assert label == trial_label(job)  # its text: tests/test_transfer.py
        assert job.seed == seeds[job.setting][job.trial]
        masses = job.params.link_mass_1, job.params.link_mass_2
        assert masses == pytest.approx(config.test_masses[job.setting])
    assert len({job.seed for job in jobs}) == 2 * 3
    traced = [(j.method, j.setting, j.trial) for j in jobs if j.record]
    assert sorted(traced) == sorted((m, 0, 0) for m in METHODS)
    jobs.clear()
    swingup.run_transfer(
        dataclasses.replace(config, record=False), None, None,
        np.random.SeedSequence(5),
    )  # fmt: skip
    assert jobs and not any(j.record for j in jobs)


def test_prediction_table_scores_the_test_settings_and_the_first_training_ones(
    monkeypatch,
):
    """Table 0 (test) on test_masses, table 1 (floor) on the first
    n_floor_settings training settings, each its own seed and its own key for
    the added methods' streams; with no floor settings, no floor table."""
    calls = []

    def score_spy(domain, models, average, batch, instances, **kwargs):
        masses = [(p.link_mass_1, p.link_mass_2) for p in instances]
        calls.append((masses, kwargs["table"], kwargs["seed"]))
        return []  # nothing to summarise

    monkeypatch.setattr(swingup, "score_settings", score_spy)
    config = dataclasses.replace(TINY, n_floor_settings=2)
    swingup.prediction_table(config, None, None, None, np.random.SeedSequence(1))
    (test, t0, s0), (floor, t1, s1) = calls
    assert test == list(config.test_masses) and t0 == 0
    assert floor == list(config.train_masses[:2]) and t1 == 1
    assert s0.spawn_key != s1.spawn_key
    calls.clear()
    config = dataclasses.replace(TINY, n_floor_settings=0)
    out = swingup.prediction_table(config, None, None, None, np.random.SeedSequence(1))
    assert calls[1][0] == [] and out["floor"] is None


def test_metrics_hold_the_runs_model_batch_and_prediction_tables(run):
    """metrics.json's model numbers are the saved model's, and its prediction
    numbers the test table's (the floor the training table's), as the table
    recomputed on the run's own models and seeds gives them: load_run's
    refitted average model is the one the run used ("batch only")."""
    from tasks.acrobot_identified import load_run

    m = json.loads((run.out / "metrics.json").read_text())
    finished = load_run(run.out)
    assert m["n_batch_transitions"] == len(finished.batch)
    np.testing.assert_array_equal(m["training_weights"], finished.hip.weights)
    table = swingup.prediction_table(
        TINY, finished.hip, finished.average, finished.batch,
        swingup.run_streams(TINY.seed).mse,
    )  # fmt: skip
    test = to_jsonable(table["test"])
    for key in ("mse", "coverage", "per_setting_mse", "per_setting_loglik"):
        _assert_close(m[key], test[key])
    _assert_close(m["approximation_floor"], to_jsonable(table["floor"]["mse"]))


def _assert_close(got, want):
    """Nested JSON values equal up to rounding (null where both are null): the
    test recomputes the table outside main's one BLAS thread, so sums may be
    ordered differently; 1e-9 relative is far below any printed digit."""
    if isinstance(want, dict):
        assert got.keys() == want.keys()
        for k in want:
            _assert_close(got[k], want[k])
    elif isinstance(want, list):
        assert len(got) == len(want)
        for g, w in zip(got, want, strict=True):
            _assert_close(g, w)
    elif isinstance(want, float):
        assert got == pytest.approx(want, rel=1e-9)
    else:
        assert got == want


def test_added_methods_are_paired_with_the_hipmdp_and_the_true_model():
    """run_pairs: PAIRS, then per added method the HiP-MDP against it and it
    against the true model; "a - b" is a's return minus b's. By hand, every
    episode: true -20, average -30, HiP-MDP -25, "mine" -40."""
    level = {"true": -20.0, "average": -30.0, "hipmdp": -25.0, "mine": -40.0}
    config = dataclasses.replace(
        TINY, n_trials=2, methods=("mine=tasks.methods:BayesianLinear",)
    )
    m = transfer_metrics(
        config, _trials({k: np.full((2, 2), v) for k, v in level.items()})
    )
    want = {
        "hipmdp - average": 5.0, "hipmdp - true": -5.0, "average - true": -10.0,
        "hipmdp - mine": 15.0, "mine - average": -10.0, "mine - true": -20.0,
    }  # fmt: skip
    got = m["paired_difference"]
    assert list(got) == list(want)
    assert {k: d["all_episodes"]["mean"] for k, d in got.items()} == want
    rows = m["paired_difference_per_setting"]
    assert {k: r[0]["mean"] for k, r in rows.items()} == want
    assert list(m["step_limit_split"]["pairs"]) == list(want)


def test_near_optimal_target_is_the_mean_of_the_last_final_window_episodes():
    """True model [-60, -40, -30, -20] on both trials, final_window 2: the
    target is -25 (the last three would give -30), within 10% is >= -27.5; the
    HiP-MDP's -29 at episode 1 is not, its -27 at episode 2 is. Two trials:
    n_trials 2 beside four episodes."""
    true = np.tile([-60.0, -40.0, -30.0, -20.0], (2, 1))
    hip = np.tile([-29.0, -27.0, -27.0, -27.0], (2, 1))
    config = dataclasses.replace(
        TINY, n_trials=2, final_window=2,
        transfer=dataclasses.replace(TINY.transfer, n_episodes=4, max_steps=100),
    )  # fmt: skip
    m = transfer_metrics(config, _trials({"true": true, "average": hip, "hipmdp": hip}))
    target = m["near_optimal_target"]
    assert target["true_model_final_mean_return"] == -25.0
    assert target["margin"] == 0.1  # the 10% that episodes_to_near_optimal uses
    assert m["episodes_to_near_optimal"]["hipmdp"] == 2
    assert all(c["n_trials"] == 2 for c in m["returns"].values())


def test_main_gives_the_fit_the_average_model_and_added_methods_their_streams(
    tmp_path, monkeypatch
):
    """The checks on a finished run (acrobot_refit, acrobot_identified's
    load_run) refit from run_streams(seed).fit and .average with the config's
    average_n_max and periodic dimensions; the added methods draw from the run's
    seed (tasks.methods.method_seed). Seed 3, so a hard-coded 0 shows."""

    class Stop(Exception):
        pass

    seen, fit = {}, hipmdp.fit

    def fit_spy(batch, config, *, rng):
        seen["fit"] = rng.bit_generator.seed_seq
        return fit(batch, config, rng=rng)

    def fit_all_spy(loaded, batch, seed, **kwargs):
        seen["methods"] = seed
        return ()

    def average_spy(batch, *, rng, n_max, periodic):
        seen["average"] = rng.bit_generator.seed_seq, n_max, periodic
        seen["periodic"] = tuple(batch.angle_dims)
        raise Stop

    monkeypatch.setattr(hipmdp, "fit", fit_spy)
    monkeypatch.setattr(swingup, "fit_all", fit_all_spy)
    monkeypatch.setattr(swingup.baselines, "batch_only", average_spy)
    config = dataclasses.replace(
        TINY, seed=3, record=False, average_n_max=123,
        fit=dataclasses.replace(TINY.fit, periodic=True),  # angles: (0, 1)
    )  # fmt: skip
    with pytest.raises(Stop):
        main(config, tmp_path)
    streams = swingup.run_streams(3)
    assert seen["methods"] == 3
    assert (seen["fit"].entropy, seen["fit"].spawn_key) == (3, streams.fit.spawn_key)
    ss, n_max, periodic = seen["average"]
    assert (ss.entropy, ss.spawn_key) == (3, streams.average.spawn_key)
    assert n_max == 123 and periodic == seen["periodic"] and periodic
    # and no periodic dimension where the fit has none
    flat = dataclasses.replace(
        config, fit=dataclasses.replace(config.fit, periodic=False)
    )
    with pytest.raises(Stop):
        main(flat, tmp_path / "flat")
    assert tuple(seen["average"][2]) == ()


def _summary_metrics(margin_2: tuple, ahead: tuple, n_episodes: int = 3) -> dict:
    """Hand-made metrics: three methods' mean returns, the HiP-MDP's episode-2
    margin (mean, low, high) and its paired lead over the average model."""

    def ci(mean, low, high, n=10):
        return {"mean": mean, "low": low, "high": high, "n": n}

    returns = {
        m: {"mean": [base - e for e in range(n_episodes)], "low": [0.0] * n_episodes,
            "high": [0.0] * n_episodes, "n_trials": 10}
        for m, base in (("true", -100.0), ("average", -150.0), ("hipmdp", -130.0))
    }  # fmt: skip
    margin = {k: [-50.0, v][:n_episodes] for k, v in zip(("mean", "low", "high"),
              margin_2, strict=True)}  # fmt: skip
    return {
        "returns": returns,
        "margin_to_target": {"hipmdp": {**margin, "n": 10}},
        "paired_difference": {"hipmdp - average": {"all_episodes": ci(*ahead)}},
        "episodes_to_near_optimal": {"true": 1, "average": None, "hipmdp": 2},
    }


@pytest.mark.parametrize(
    "margin_2, ahead, verdicts",
    [
        ((5.0, 1.0, 9.0), (20.0, 4.0, 36.0), ("(met)", "(clearly ahead)")),
        ((-5.0, -9.0, -1.0), (-20.0, -36.0, -4.0), ("(missed)", "(clearly behind)")),
        ((-5.0, -9.0, 1.0), (2.0, -4.0, 8.0), ("(not settled)", "(not clearly ahead)")),
        (
            (-5.0, None, None),
            (2.0, None, None),
            ("(not settled)", "(not clearly ahead)"),
        ),
        # an interval that reaches 0 does not lie wholly on one side of it
        (
            (5.0, 0.0, 9.0),
            (-20.0, -36.0, 0.0),
            ("(not settled)", "(not clearly ahead)"),
        ),
    ],
)
def test_the_printed_summary_states_each_target_by_its_interval(
    margin_2, ahead, verdicts
):
    """A target is met or missed only where its 95% interval lies wholly on one
    side of 0; an interval across 0, or none (one sample), settles nothing. The
    returns are shown at episodes 1, 2 and the last; a method that never gets
    within 10% is "never"."""
    lines = swingup_report.summary_lines(_summary_metrics(margin_2, ahead))
    assert lines[0] == "mean return per real episode over 10 trials (episode 1, 2, 3):"
    assert lines[1:4] == [
        "  true model       -100.0    -101.0    -102.0",
        "  average model    -150.0    -151.0    -152.0",
        "  HiP-MDP          -130.0    -131.0    -132.0",
    ]
    assert lines[4].startswith("HiP-MDP within 10% of the true model by episode 2")
    assert lines[4].endswith(verdicts[0])
    assert lines[5].startswith("HiP-MDP - average model")
    assert lines[5].endswith(verdicts[1])
    assert lines[6].endswith("true model 1, average model never, HiP-MDP 2")


def test_a_one_episode_summary_has_no_episode_2_target():
    lines = swingup_report.summary_lines(
        _summary_metrics((0.0, 0.0, 0.0), (1.0, 0.5, 1.5), n_episodes=1)
    )
    assert lines[0].endswith("(episode 1):")
    assert not any("by episode 2" in line for line in lines)


def test_a_two_episode_summary_states_the_episode_2_target():
    lines = swingup_report.summary_lines(
        _summary_metrics((5.0, 1.0, 9.0), (1.0, 0.5, 1.5), n_episodes=2)
    )
    assert lines[0].endswith("(episode 1, 2):")
    assert lines[4] == (
        "HiP-MDP within 10% of the true model by episode 2, margin per trial: "
        f"{fmt_ci({'mean': 5.0, 'low': 1.0, 'high': 9.0}, signed=True)} (met)"
    )


def test_cli_prints_where_it_wrote_and_the_summary(tmp_path, monkeypatch, capsys):
    """The folder, with its recording (acrobot.rrd) if the run wrote one, the
    summary lines, and where the report is."""
    metrics = _summary_metrics((5.0, 1.0, 9.0), (20.0, 4.0, 36.0))

    def fake_main(config, out):
        (tmp_path / "acrobot.rrd").touch()  # the run recorded
        return swingup.Results(tmp_path, metrics)

    monkeypatch.setattr(swingup, "main", fake_main)
    assert swingup.cli(["--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"wrote {tmp_path}/ (report.md, metrics.json, figures, recording)"
    assert out[1:-1] == swingup_report.summary_lines(metrics)
    assert out[-1] == f"tables and plain-language results: {tmp_path / 'report.md'}"


def test_the_report_names_the_fit_choices_the_flags_changed(run, tmp_path):
    """As the cart-pole's: ``--filter-weights`` and ``--new-features``, when
    changed, are named in report.md."""
    assert_names_fit_choices(run, swingup_report.write_report, TINY, tmp_path, " ")
