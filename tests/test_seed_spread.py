"""tasks.seed_spread: headline numbers across seeds, on hand-made run folders whose
summaries are computed here by hand. That it reads real runs is tested beside each
experiment's smoke test."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from scipy import stats

from tasks.experiment import write_json
from tasks.seed_spread import cli, main, report

DIMS = ("dtheta1", "dtheta2")
BASELINES = ("batch only", "train only")


def _ci(mean, half, n):
    return {"mean": mean, "low": mean - half, "high": mean + half, "n": n}


def _ratio(log: float) -> dict:
    return {"geometric_mean": float(np.exp(log)), "low": float(np.exp(log - 0.5)),
            "high": float(np.exp(log + 0.5)), "n": 16, "hipmdp_lower": 16}  # fmt: skip


def _acrobot_metrics(k: float) -> dict:
    """Metrics whose numbers move with ``k``. The HiP-MDP's MSE ratio against
    batch only is ``exp(k)`` with log half-width 0.5, against train only
    ``exp(-k)``; batch only is the best baseline unless k > 2."""
    mse = {
        "hipmdp": {d: {"mean": 1.0} for d in DIMS},
        "batch only": {d: {"mean": 2.0} for d in DIMS},
        "train only": {d: {"mean": 3.0 if k <= 2 else 1.5} for d in DIMS},
    }
    ratios = {"batch only": _ratio(k), "train only": _ratio(-k)}
    return {
        "episodes_to_near_optimal": {
            "true": None,
            "average": None if k > 2 else 13,
            "hipmdp": 2 + k,
        },
        "margin_to_target": {
            "hipmdp": {
                "mean": [-20.0, -8.0 + k],
                "low": [-30.0, -18.0 + k],
                "high": [-10.0, 2.0 + k],
                "n": 480,
            }
        },  # fmt: skip
        "paired_difference": {
            "hipmdp - average": {
                "all_episodes": _ci(0.5 + k, 4.0, 480),
                "by_setting": _ci(0.5 + k, 10.0, 16),
            }
        },
        "mse": mse,
        "mse_ratio_per_setting": {b: {d: ratios[b] for d in DIMS} for b in BASELINES},
        "loglik_difference": {b: _ci(100.0 * k, 50.0, 16) for b in BASELINES},
        "unseen": None,
        "n_latent_features": 9 + k,
        "seconds": {"total": 1.0},
    }


def _write_runs(tmp_path, runs) -> list:
    """A folder ``seed<i>`` per ``(config, metrics)`` of ``runs``, in order."""
    out = []
    for i, (config, metrics) in enumerate(runs):
        path = tmp_path / f"seed{i}"
        path.mkdir()
        write_json(path / "config.json", config)
        write_json(path / "metrics.json", metrics)
        out.append(path)
    return out


def _runs(tmp_path, ks=(0.0, 1.0, 3.0), configs=None):
    # the name is a label, and workers only schedule: both may differ
    return _write_runs(tmp_path, [
        (
            (configs or {}).get(
                i, {"name": f"s{i}", "seed": i, "fit": {"n_sweeps": 60}, "workers": i}
            ),
            _acrobot_metrics(k),
        )
        for i, k in enumerate(ks)
    ])  # fmt: skip


def _number(result, label):
    (n,) = [n for n in result["numbers"] if n["label"] == label]
    return n


def test_across_seeds_is_a_t_interval_over_the_seeds_values(tmp_path):
    ks = np.array([0.0, 1.0, 3.0])
    result = main(_runs(tmp_path, ks))
    assert result["experiment"] == "acrobot_swingup" and result["seeds"] == [0, 1, 2]
    n = _number(result, "return, hipmdp - average (trials)")
    assert [p["value"] for p in n["per_seed"]] == list(0.5 + ks)
    a = n["across_seeds"]
    half = stats.t.ppf(0.975, 2) * np.std(0.5 + ks, ddof=1) / np.sqrt(3)
    assert a["mean"] == pytest.approx(0.5 + ks.mean()) and a["n"] == 3
    assert (a["low"], a["high"]) == pytest.approx((a["mean"] - half, a["mean"] + half))
    # the runs' own SE: half-width 4 over t(479); the seeds' sd over it
    se = 4.0 / stats.t.ppf(0.975, 479)
    assert a["sd_over_se"] == pytest.approx(np.std(ks, ddof=1) / se)
    # the report's across-seeds cell: the mean and its interval, to 3 significant
    # digits (rounding moves a value by at most half a unit of the third: 0.5%)
    (row,) = [r for r in report(result).splitlines() if r.startswith(f"| {n['label']}")]
    cell = row.split(" | ")[-2]
    assert [float(v) for v in re.findall(r"[-\d.]+", cell)] == pytest.approx(
        [a["mean"], a["low"], a["high"]], rel=5e-3
    )
    margin = _number(result, "HiP-MDP margin to the 10% target, episode 2")
    assert [p["value"] for p in margin["per_seed"]] == list(-8.0 + ks)
    assert [p["low"] for p in margin["per_seed"]] == list(-18.0 + ks)


def test_ratios_are_averaged_on_the_log_scale(tmp_path):
    ks = np.array([0.0, 1.0, 3.0])
    result = main(_runs(tmp_path, ks))
    # against the first run's best baseline, batch only, on every seed (the third
    # seed's best is train only)
    n = _number(result, "HiP-MDP MSE / batch only's, dtheta1 (per-setting "
                        "geometric mean)")  # fmt: skip
    assert [p["value"] for p in n["per_seed"]] == pytest.approx(np.exp(ks))
    a = n["across_seeds"]
    assert a["mean"] == pytest.approx(np.exp(ks.mean()))  # geometric, not arithmetic
    half = stats.t.ppf(0.975, 2) * np.std(ks, ddof=1) / np.sqrt(3)
    assert a["low"] == pytest.approx(np.exp(ks.mean() - half))
    se = 0.5 / stats.t.ppf(0.975, 15)
    assert a["sd_over_se"] == pytest.approx(np.std(ks, ddof=1) / se)


def test_counts_get_median_and_range_with_never_last(tmp_path):
    result = main(_runs(tmp_path, (0.0, 1.0, 3.0)))
    hip = _number(result, "episodes to near-optimal, hipmdp")["across_seeds"]
    assert hip == {"median": 3.0, "min": 2.0, "max": 5.0, "never": 0}
    avg = _number(result, "episodes to near-optimal, average")["across_seeds"]
    assert avg == {"median": 13.0, "min": 13.0, "max": np.inf, "never": 1}
    text = report(result)
    assert "| episodes to near-optimal, true | never | never | never | never |" in text
    assert "| 13 | 13 | never | median 13 (13-never) |" in text
    assert "median 3 (2-5)" in text


def test_a_number_that_does_not_move_has_zero_spread(tmp_path):
    result = main(_runs(tmp_path, (1.0, 1.0)))
    for n in result["numbers"]:
        if n["scale"] != "count":
            assert n["across_seeds"]["sd"] == 0.0, n["label"]


@pytest.mark.parametrize(
    "configs, match",
    [
        ({1: {"name": "acrobot_swingup", "seed": 1, "fit": {"n_sweeps": 30}}},
         r"differs .* in more than the seed: fit.n_sweeps \(60 vs 30\)"),
        ({1: {"name": "acrobot_swingup", "seed": 0, "fit": {"n_sweeps": 60}}},
         r"distinct seeds, got \[0, 0, 2\]"),
        # a run older than --split ran the random split, not the time split
        ({1: {"name": "s1", "seed": 1, "fit": {"n_sweeps": 60}, "split": "time"}},
         r"in more than the seed: split \('random' vs 'time'\)"),
        # a run with a --method against runs without: the list is one setting
        ({1: {"name": "s1", "seed": 1, "fit": {"n_sweeps": 60},
              "methods": [{"name": "m", "spec": "mine:M"}]}},
         r"seed: methods \(\[\] vs \[\{'name': 'm', 'spec': 'mine:M'\}\]\)$"),
    ],
)  # fmt: skip
def test_runs_that_are_not_seeds_of_one_experiment_are_refused(
    tmp_path, configs, match
):
    with pytest.raises(ValueError, match=match):
        main(_runs(tmp_path, configs=configs))


def test_a_run_older_than_a_field_counts_as_its_old_behaviour(tmp_path):
    """Runs made before ``split`` existed ran the random split: they are seeds
    of the same experiment as newer runs with ``split: random``."""
    newer = {"name": "s1", "seed": 1, "fit": {"n_sweeps": 60}, "split": "random"}
    newer["methods"] = []  # and before --method, none was added
    assert main(_runs(tmp_path, configs={1: newer}))["seeds"] == [0, 1, 2]


def test_runs_of_other_experiments_are_refused(tmp_path):
    runs = _runs(tmp_path)
    m = json.loads((runs[1] / "metrics.json").read_text())
    del m["episodes_to_near_optimal"]
    write_json(runs[1] / "metrics.json", m | {"mse_ratio_to_best_baseline": {}})
    with pytest.raises(
        ValueError,
        match=r"runs of one experiment, got runs of acrobot_swingup and "
        r"cartpole_prediction: .*seed1: cartpole_prediction, .*seed2: acr",
    ):
        main(runs)
    write_json(runs[1] / "metrics.json", {"rmse": 1.0})
    with pytest.raises(ValueError, match=r"seed1: another"):
        main(runs)
    # runs of one experiment, but not one seed_spread knows
    for run in runs:
        write_json(run / "metrics.json", {"rmse": 1.0})
    with pytest.raises(ValueError, match=r"expected runs of one of .*seed0: another"):
        main(runs)


def _edit(run, edit):
    m = json.loads((run / "metrics.json").read_text())
    edit(m)
    write_json(run / "metrics.json", m)


def test_missing_values_read_as_not_available(tmp_path):
    runs = _runs(tmp_path)
    _edit(runs[1], lambda m: m["mse_ratio_per_setting"]["batch only"].update(
        dtheta2=None))  # fmt: skip
    result = main(runs)
    n = _number(result, "HiP-MDP MSE / batch only's, dtheta2 (per-setting "
                        "geometric mean)")  # fmt: skip
    assert n["per_seed"][1]["value"] is None
    assert n["across_seeds"]["mean"] is None and n["across_seeds"]["sd"] is None
    assert "| 1 [0.607, 1.65] | n/a | 20.1 [12.2, 33.1] | n/a |  |" in report(result)


def test_runs_whose_intervals_have_no_width_have_no_sd_over_se(tmp_path):
    runs = _runs(tmp_path)
    for run in runs:
        _edit(run, lambda m: m["paired_difference"]["hipmdp - average"].update(
            all_episodes=_ci(1.0, 0.0, 480)))  # fmt: skip
    n = _number(main(runs), "return, hipmdp - average (trials)")
    assert n["across_seeds"]["sd"] == 0.0 and n["across_seeds"]["sd_over_se"] is None


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda m: m["loglik_difference"].update({"train only": {"mean": "nine"}}),
         r"seed1: log-likelihood, HiP-MDP - train only: expected an interval of "
         r"numbers \{mean, low, high, n\}, got \{'mean': 'nine'\}"),
        # bounds are null only for one sample (mean_ci); over 16 it is a broken file
        (lambda m: m["loglik_difference"].update(
            {"train only": {"mean": 1.0, "low": None, "high": None, "n": 16}}),
         r"seed1: log-likelihood, HiP-MDP - train only: expected an interval of "),
        (lambda m: m.update(n_latent_features="nine"),
         r"seed1: latent features: expected a number, got 'nine'"),
    ],
)  # fmt: skip
def test_values_that_are_not_numbers_are_named(tmp_path, edit, match):
    runs = _runs(tmp_path)
    _edit(runs[1], edit)
    with pytest.raises(ValueError, match=match):
        main(runs)


@pytest.mark.parametrize("seed", [{}, {"seed": True}, {"seed": 1.0}])
def test_a_config_without_an_integer_seed_is_refused(tmp_path, seed):
    """No seed, or a seed that is not an integer (``true`` is a bool in JSON,
    which Python would count as the integer 1)."""
    configs = {0: {"name": "s0", "fit": {"n_sweeps": 60}} | seed}
    with pytest.raises(ValueError, match=r"seed0: config.json: expected an integer "):
        main(_runs(tmp_path, configs=configs))


def test_one_run_and_missing_folders_are_refused(tmp_path):
    runs = _runs(tmp_path)
    with pytest.raises(ValueError, match="at least 2 run folders, got 1"):
        main(runs[:1])
    with pytest.raises(FileNotFoundError, match="no config.json"):
        main([runs[0], tmp_path / "nowhere"])


@pytest.mark.parametrize("which", [0, 2])  # the first run sets the rows
def test_a_run_from_an_older_version_is_named(tmp_path, which):
    runs = _runs(tmp_path)
    _edit(runs[which], lambda m: m.pop("margin_to_target"))
    with pytest.raises(
        ValueError, match=f"seed{which}: metrics.json lacks .*older hipmdp"
    ):
        main(runs)


@pytest.mark.parametrize(
    "which, edit",
    [
        # a later run with one episode's margin: the first run's row reads episode 2
        (2, lambda m: m["margin_to_target"].update(
            hipmdp={"mean": [-20.0], "low": [-30.0], "high": [-10.0], "n": 480})),
        (0, lambda m: m["margin_to_target"].update(hipmdp=None)),
    ],
)  # fmt: skip
def test_a_run_with_headlines_of_another_shape_is_named(tmp_path, which, edit):
    """Not a traceback from deep inside (IndexError, TypeError): the run named."""
    runs = _runs(tmp_path)
    _edit(runs[which], edit)
    with pytest.raises(ValueError, match=f"seed{which}: metrics.json lacks "):
        main(runs)


def test_cli_prints_the_table_and_writes_json(tmp_path, capsys):
    runs = _runs(tmp_path)
    out = tmp_path / "spread.json"
    assert cli([*map(str, runs), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.startswith("acrobot_swingup: 3 seeds")
    assert "| number | seed 0 | seed 1 | seed 2 | across seeds | sd / SE |" in text
    assert json.loads(out.read_text())["seeds"] == [0, 1, 2]
    with pytest.raises(SystemExit) as err:
        cli([str(runs[0])])
    assert err.value.code == 2
    assert "at least 2 run folders" in capsys.readouterr().err
    with pytest.raises(SystemExit) as err:  # before the runs are read
        cli(["no_run", "no_run_either", "--out", str(tmp_path)])
    assert err.value.code == 2
    assert f"out: {tmp_path} is a folder" in capsys.readouterr().err
    # nor over a run's own files (a run's metrics.json replaced, it was no run)
    before = (runs[1] / "metrics.json").read_text()
    with pytest.raises(SystemExit) as err:
        cli([*map(str, runs), "--out", str(runs[1] / "metrics.json")])
    assert err.value.code == 2 and "is one of the run" in capsys.readouterr().err
    assert (runs[1] / "metrics.json").read_text() == before


def test_runs_made_at_different_code_are_named_in_the_report(tmp_path):
    """A difference between seeds can be one of code: the report says which run
    was made at which commit when they differ, and nothing when they agree."""
    runs = _runs(tmp_path)
    for run in runs:
        _edit(run, lambda m: m.update(environment={"git_commit": "aaa"}))
    result = main(runs)
    assert result["git_commits"] == ["aaa"] * 3
    assert "different commits" not in report(result)
    _edit(runs[2], lambda m: m.update(environment={"git_commit": "bbb"}))
    text = report(main(runs))
    assert f"Note: the runs were made at different commits ({runs[0]}: aaa," in text
    assert f"{runs[2]}: bbb)" in text


def _cartpole_metrics(i: int) -> dict:
    """Cart-pole metrics of seed ``i``: the HiP-MDP's mean MSE is ``1 + i`` on dx
    and 3 on dtheta. The first run's best baseline is batch only (2) on dx and
    train only (5) on dtheta; the second run's batch only predicts dx exactly
    (a ratio of means to it has no value). The log-likelihood leads are over two
    test settings, half-width ``1 + i²``; on the unseen settings, ``10 * i``."""
    dims = ("dx", "dtheta")
    mse = {
        "hipmdp": {"dx": {"mean": 1.0 + i}, "dtheta": {"mean": 3.0}},
        "batch only": {"dx": {"mean": 0.0 if i == 1 else 2.0}, "dtheta": {"mean": 8.0}},
        "train only": {"dx": {"mean": 4.0}, "dtheta": {"mean": 5.0}},
    }
    return {
        "mse_ratio_to_best_baseline": {d: None for d in dims},  # not read
        "mse": mse,
        "mse_ratio_per_setting": {b: {d: None for d in dims} for b in BASELINES},
        "loglik_difference": {"batch only": _ci(float(i), 1.0 + i * i, 2)},
        "unseen": {"loglik_difference": {"batch only": _ci(10.0 * i, 1.0, 2)}},
        "n_latent_features": [i, 2 * i, 6 * i],
    }


def _cartpole_runs(tmp_path, n=3):
    return _write_runs(
        tmp_path,
        [
            ({"name": "cp", "seed": i, "fit": {}}, _cartpole_metrics(i))
            for i in range(n)
        ],
    )


def test_cartpole_ratio_of_means_is_against_the_first_runs_best_baseline(tmp_path):
    """Each dimension's row divides the HiP-MDP's mean MSE by the baseline the
    first run found best on that dimension, on every seed; a baseline that
    predicts a dimension exactly gives no ratio (not a division by zero). Kills
    rows that read another dimension or baseline, and the ratio upside down."""
    result = main(_cartpole_runs(tmp_path))
    assert result["experiment"] == "cartpole_prediction"
    dx = _number(result, "HiP-MDP MSE / batch only's, dx (ratio of means)")
    assert [p["value"] for p in dx["per_seed"]] == [0.5, None, 1.5]
    assert dx["across_seeds"]["mean"] is None
    dtheta = _number(result, "HiP-MDP MSE / train only's, dtheta (ratio of means)")
    assert [p["value"] for p in dtheta["per_seed"]] == [0.6, 0.6, 0.6]


def test_cartpole_ratio_of_means_carries_each_runs_bootstrap_interval(tmp_path):
    """Each seed's cell carries its run's bootstrap interval of the ratio to
    the row's baseline: the run's stored one where that baseline is the run's
    own best (seed 0; the stored bounds are marked, so a recomputation would
    show), else drawn as the run drew its own, from its seed, against the row's
    baseline (seed 1, whose best on dx is train only). The bootstrap gives no
    standard error, so the row has no sd / SE. A run from before the intervals
    gives the ratio alone."""
    from tasks.cartpole_prediction import DIM_NAMES, N_BOOTSTRAP

    rng = np.random.default_rng(4)
    batch = rng.lognormal(size=(6, 4))
    hip = 0.5 * batch * rng.uniform(0.5, 1.5, size=batch.shape)
    runs = []
    for seed, train_dx in ((0, 3.0), (1, 0.5)):
        train = 4.0 * batch
        train[:, 0] = train_dx * batch[:, 0]  # seed 1: the best on dx
        per_setting = {"hipmdp": hip, "batch only": batch, "train only": train}
        mse = {
            m: {d: {"mean": float(v[:, j].mean())} for j, d in enumerate(DIM_NAMES)}
            for m, v in per_setting.items()
        }
        stored = {d: {"low": 0.125, "high": 0.875} for d in DIM_NAMES}
        metrics = _cartpole_metrics(seed) | {
            "mse": mse,
            "per_setting_mse": {m: v.tolist() for m, v in per_setting.items()},
            "mse_ratio_to_best_baseline_interval": stored,
            "mse_ratio_per_setting": {b: dict.fromkeys(DIM_NAMES) for b in BASELINES},
        }
        runs.append(({"name": "cp", "seed": seed, "fit": {}}, metrics))
    older = dict(runs[0][1])
    del older["mse_ratio_to_best_baseline_interval"]
    runs.append(({"name": "cp", "seed": 2, "fit": {}}, older))
    result = main(_write_runs(tmp_path, runs))
    dx = _number(result, "HiP-MDP MSE / batch only's, dx (ratio of means)")
    first, second, old = dx["per_seed"]
    assert (first["low"], first["high"], first["n"]) == (0.125, 0.875, None)
    assert first["value"] == pytest.approx(hip[:, 0].mean() / batch[:, 0].mean())
    draws = np.random.default_rng(np.random.SeedSequence(1, spawn_key=(4,))).integers(
        6, size=(N_BOOTSTRAP, 6)
    )
    ratios = [hip[i, 0].mean() / batch[i, 0].mean() for i in draws]
    want = np.percentile(ratios, [2.5, 97.5])
    assert [second["low"], second["high"]] == pytest.approx(want, rel=1e-12)
    assert second["value"] == first["value"]
    assert (old["value"], old["low"], old["high"]) == (first["value"], None, None)
    assert dx["across_seeds"]["sd_over_se"] is None
    assert "[" in report(result).split("dx (ratio of means) |")[1].split("|")[1]


def test_cartpole_rows_read_the_unseen_settings_and_the_mean_over_fits(tmp_path):
    """The unseen rows read the leads on the unseen settings alone, not on all
    settings; "latent features (mean over fits)" is the mean of each run's fits
    (9 fits' worth: 0, 3 and 6 on seeds 0, 1, 2)."""
    result = main(_cartpole_runs(tmp_path))
    unseen = _number(result, "log-likelihood on unseen settings, HiP-MDP - batch only")
    assert [p["value"] for p in unseen["per_seed"]] == [0.0, 10.0, 20.0]
    features = _number(result, "latent features (mean over fits)")
    assert [p["value"] for p in features["per_seed"]] == [0.0, 3.0, 6.0]


def test_sd_over_se_takes_the_median_of_runs_over_two_settings(tmp_path):
    """A run over two test settings (as a small cart-pole run is) has a standard
    error: half-width over t(1). The seeds' leads 0, 1, 2 have sd 1; their
    half-widths 1, 2, 5 give SEs whose median is 2 / t(1) (their mean, 8/3 / t(1),
    or largest would be another number)."""
    result = main(_cartpole_runs(tmp_path))
    a = _number(result, "log-likelihood, HiP-MDP - batch only")["across_seeds"]
    assert a["sd"] == pytest.approx(1.0)
    assert a["sd_over_se"] == pytest.approx(stats.t.ppf(0.975, 1) / 2.0)


def test_an_interval_of_one_setting_reads_as_a_value_without_interval(tmp_path):
    """A run with one test setting writes its leads as ``mean_ci`` of one sample,
    bounds null: the value is read, with no interval and no SE."""
    runs = _cartpole_runs(tmp_path, n=2)
    for i, run in enumerate(runs):
        one = {"mean": float(i), "low": None, "high": None, "n": 1}
        _edit(run, lambda m, one=one: m.update(loglik_difference={"batch only": one}))
    result = main(runs)
    n = _number(result, "log-likelihood, HiP-MDP - batch only")
    assert [(p["value"], p["low"], p["n"]) for p in n["per_seed"]] == [
        (0.0, None, 1),
        (1.0, None, 1),
    ]
    assert n["across_seeds"]["sd_over_se"] is None
    assert "| log-likelihood, HiP-MDP - batch only | 0 | 1 |" in report(result)


def test_a_count_never_reached_on_most_seeds_has_median_never(tmp_path):
    """The average model reaches near-optimal on seed 0 only (k > 2 on the
    others): its median over three seeds is "never"."""
    out = tmp_path / "spread.json"
    result = main(_runs(tmp_path, (0.0, 3.0, 4.0)), out=out)
    avg = _number(result, "episodes to near-optimal, average")["across_seeds"]
    assert avg == {"median": np.inf, "min": 13.0, "max": np.inf, "never": 2}
    assert "| 13 | never | never | median never (13-never) |" in report(result)
    # In --out's JSON (no infinity there) "never" is null, counted by `never`.
    (written,) = [
        n["across_seeds"]
        for n in json.loads(out.read_text())["numbers"]
        if n["label"] == "episodes to near-optimal, average"
    ]
    assert written == {"median": None, "min": 13.0, "max": None, "never": 2}


def test_the_seeds_are_columns_in_the_order_the_runs_are_given(tmp_path):
    """Runs given seed 2 first: the seeds, the columns and the values all follow
    that order (sorted seeds would label seed 2's values "seed 0"); a count's
    range is still smallest to largest (the HiP-MDP's: 5, 2, 3 episodes)."""
    runs = _runs(tmp_path, (0.0, 1.0, 3.0))
    result = main([runs[2], runs[0], runs[1]])
    assert result["seeds"] == [2, 0, 1]
    n = _number(result, "return, hipmdp - average (trials)")
    assert [p["value"] for p in n["per_seed"]] == [3.5, 0.5, 1.5]
    assert "| number | seed 2 | seed 0 | seed 1 |" in report(result)
    hip = _number(result, "episodes to near-optimal, hipmdp")["across_seeds"]
    assert hip == {"median": 3.0, "min": 2.0, "max": 5.0, "never": 0}


def test_few_seeds_are_said_to_give_wide_intervals(tmp_path):
    """Under 5 seeds the report says how many standard errors an across-seeds
    interval spans (the t quantile: 12.7 with 2 seeds, 4.30 with 3), and from 5
    seeds it says nothing."""

    def text(name, ks):
        (tmp_path / name).mkdir()
        return report(main(_runs(tmp_path / name, ks=ks)))

    two = text("two", (0.0, 1.0))
    assert "with 2 seeds an across-seeds interval is the mean ± 12.7 standard " in two
    assert "(Student t, 1 degree of freedom), so it is wide; 5 seeds give ± 2.78" in two
    three = text("three", (0.0, 1.0, 3.0))
    assert "with 3 seeds an across-seeds interval is the mean ± 4.3 " in three
    assert "(Student t, 2 degrees of freedom)" in three
    five = text("five", (0.0, 1.0, 3.0, 4.0, 6.0))
    assert "5 seeds:" not in five and "Student t" not in five


def _with_added_method(k: float, paired_with_average: bool) -> dict:
    metrics = _acrobot_metrics(k)
    pairs = ["hipmdp - d", "d - true"] + ["d - average"] * paired_with_average
    for pair in pairs:
        metrics["paired_difference"][pair] = {
            "all_episodes": _ci(k, 4.0, 480), "by_setting": _ci(k, 9.0, 16)
        }  # fmt: skip
    return metrics


@pytest.mark.parametrize("older", [0, 2])  # the first run sets the rows
def test_runs_older_than_an_added_methods_pair_leave_it_out_named(tmp_path, older):
    """Seeds of a run with an added method, one from before its ``NAME -
    average`` pair: the pair's rows are left out, named, whichever run is the
    older (they were left out silently where the first run was, and the run
    refused as older where a later one was); its other rows stay."""
    config = {"fit": {"n_sweeps": 60}, "methods": ["d=mine:D"]}
    runs = _write_runs(tmp_path, [
        ({"name": f"s{i}", "seed": i} | config, _with_added_method(i, i != older))
        for i in range(3)
    ])  # fmt: skip
    result = main(runs)
    labels = [n["label"] for n in result["numbers"]]
    assert not [label for label in labels if "d - average" in label]
    assert "return, d - true (trials)" in labels
    assert result["not_in_every_run"] == ["d - average"]
    assert "left out, as some runs are older than them: d - average." in report(result)
    (tmp_path / "new").mkdir()  # every run paired it: its rows
    runs = _write_runs(tmp_path / "new", [
        ({"name": f"s{i}", "seed": i} | config, _with_added_method(i, True))
        for i in range(3)
    ])  # fmt: skip
    result = main(runs)
    assert "return, d - average (trials)" in [n["label"] for n in result["numbers"]]
    assert "not_in_every_run" not in result
