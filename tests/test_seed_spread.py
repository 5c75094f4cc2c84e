"""tasks.seed_spread: headline numbers across seeds, on hand-made run folders whose
summaries are computed here by hand. That it reads real runs is tested beside each
experiment's smoke test."""

from __future__ import annotations

import json

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


def _runs(tmp_path, ks=(0.0, 1.0, 3.0), configs=None):
    out = []
    for i, k in enumerate(ks):
        path = tmp_path / f"seed{i}"
        path.mkdir()
        # the name is a label, and workers only schedule: both may differ
        config = {"name": f"s{i}", "seed": i, "fit": {"n_sweeps": 60}, "workers": i}
        write_json(path / "config.json", (configs or {}).get(i, config))
        write_json(path / "metrics.json", _acrobot_metrics(k))
        out.append(path)
    return out


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
    assert a["mean"] == pytest.approx(0.5 + ks.mean())
    assert (a["low"], a["high"]) == pytest.approx((a["mean"] - half, a["mean"] + half))
    # the runs' own SE: half-width 4 over t(479); the seeds' sd over it
    se = 4.0 / stats.t.ppf(0.975, 479)
    assert a["sd_over_se"] == pytest.approx(np.std(ks, ddof=1) / se)
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
    with pytest.raises(ValueError, match=r"seed1: cartpole_prediction, .*seed2: acr"):
        main(runs)
    write_json(runs[1] / "metrics.json", {"rmse": 1.0})
    with pytest.raises(ValueError, match=r"seed1: another"):
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
        (lambda m: m.update(n_latent_features="nine"),
         r"seed1: latent features: expected a number, got 'nine'"),
    ],
)  # fmt: skip
def test_values_that_are_not_numbers_are_named(tmp_path, edit, match):
    runs = _runs(tmp_path)
    _edit(runs[1], edit)
    with pytest.raises(ValueError, match=match):
        main(runs)


def test_a_config_without_a_seed_is_refused(tmp_path):
    configs = {0: {"name": "s0", "fit": {"n_sweeps": 60}}}
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
