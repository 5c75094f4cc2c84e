"""The compounding-error check on a finished (tiny) swing-up run."""

from __future__ import annotations

import inspect
import json

import numpy as np
import pytest

from hipmdp.planning import LearnedModel, open_loop_errors
from tasks import acrobot_horizon
from tasks.agents import ACROBOT
from tasks.prediction import gather_split
from tests._cli import fake_main
from tests.test_acrobot_swingup import TINY


@pytest.fixture(scope="module")
def run(tiny_swingup_run):
    out = tiny_swingup_run
    return out, acrobot_horizon.main(
        out, horizons=(1, 4), identify=30, evaluate=40, progress=False
    )


def test_writes_errors_per_model_horizon_and_setting(run):
    out, results = run
    data = json.loads((out / "horizon.json").read_text())
    assert data["horizons"] == [1, 4]
    assert data["test_masses"] == [list(m) for m in TINY.test_masses]
    for model in acrobot_horizon.MODELS:
        for k in ("1", "4"):
            rmse = np.array(data["rmse"][model][k])
            p99 = np.array(data["p99"][model][k])
            assert rmse.shape == p99.shape == (len(TINY.test_masses), 4)
            assert np.all(np.isfinite(rmse) & (rmse > 0) & (p99 > 0))
    # fewer 4-step windows than 1-step ones: none crosses an episode end
    assert 0 < data["windows"]["4"][0] < data["windows"]["1"][0]
    assert data["windows"]["1"][0] >= 40
    # the same seed, the same numbers
    # (but for "environment"'s git state: a working tree edited between the two
    # runs reads as another commit)
    first = json.loads((out / "horizon.json").read_text())
    acrobot_horizon.main(out, horizons=(1, 4), identify=30, evaluate=40, progress=False)
    again = json.loads((out / "horizon.json").read_text())
    for written in (first, again):
        written["environment"].pop("git_commit")
    assert again == first
    np.testing.assert_array_equal(
        results.summary["rmse"]["identified"]["4"], data["rmse"]["identified"]["4"]
    )


def test_setting_0_rebuilt_from_the_seed(run):
    """Setting 0's numbers from its own seeds: the belief filtered on its
    `identify` transitions (not the prior), each model's (the average GP's too)
    k-step errors on its held-out episodes, their root mean square and 99th
    percentile of |error| per dimension."""
    out, results = run
    config, hip, batch = acrobot_horizon.read_run(out)
    params = acrobot_horizon.run_test_instances(config)[0]
    ss_identify, ss_evaluate = (
        np.random.SeedSequence(321).spawn(len(TINY.test_masses))[0].spawn(2)
    )
    train = gather_split(
        ACROBOT, params, 30, 0, rng=np.random.default_rng(ss_identify)
    ).train
    held_out = gather_split(
        ACROBOT, params, 0, 40, rng=np.random.default_rng(ss_evaluate)
    ).episodes
    identified = hip.update(hip.prior(), train)
    assert not np.allclose(identified.mean, hip.prior().mean)
    average = acrobot_horizon.average_model(config, batch)  # refitted as the run did
    models = {
        "average": LearnedModel(average, None, ACROBOT.angle_dims),
        "prior": LearnedModel(hip, hip.prior(), ACROBOT.angle_dims),
        "identified": LearnedModel(hip, identified, ACROBOT.angle_dims),
    }
    for name, model in models.items():
        for k, err in open_loop_errors(model, held_out, (1, 4)).items():
            got = results.summary
            np.testing.assert_array_equal(
                got["rmse"][name][str(k)][0], np.sqrt(np.mean(err**2, axis=0))
            )
            np.testing.assert_array_equal(
                got["p99"][name][str(k)][0], np.percentile(np.abs(err), 99, axis=0)
            )


class _WorkBegan(Exception):
    """Raised in place of ``inputs_checked``: the options passed every check."""


def _work_began():
    raise _WorkBegan


def test_rejects_bad_options(tmp_path, run, monkeypatch):
    # every refusal comes before the work (the CLI shows it as a usage error, not
    # a traceback after the average model's fit and the gathering)
    monkeypatch.setattr(acrobot_horizon, "inputs_checked", _work_began)
    with pytest.raises(FileNotFoundError, match="has no config.json"):
        acrobot_horizon.main(tmp_path)
    with pytest.raises(ValueError, match=r"horizons\[0\]: expected >= 1"):
        acrobot_horizon.main(run[0], horizons=(0,))
    with pytest.raises(ValueError, match="horizons: expected integers >= 1, got none"):
        acrobot_horizon.main(run[0], horizons=())
    # int() made these horizons of 1 and 3
    for bad in [(1.5,), (1, True), ("3",)]:
        with pytest.raises(ValueError, match=r"horizons\[\d\]: expected an integer"):
            acrobot_horizon.main(run[0], horizons=bad)
    with pytest.raises(ValueError, match="evaluate: expected >= 1"):
        acrobot_horizon.main(run[0], evaluate=0)
    with pytest.raises(ValueError, match="identify: expected >= 1"):
        acrobot_horizon.main(run[0], identify=0)
    with pytest.raises(ValueError, match="seed: expected >= 0"):
        acrobot_horizon.main(run[0], seed=-1)
    # a horizon longer than any episode crashed after all the work; a repeated one
    # was printed twice
    with pytest.raises(ValueError, match="horizons: expected at most 500 .*got 501"):
        acrobot_horizon.main(run[0], horizons=(1, 501))
    with pytest.raises(ValueError, match="horizons: expected distinct"):
        acrobot_horizon.main(run[0], horizons=(5, 5))
    # an episode's 500 steps hold one window of k = 500: the limit is accepted
    with pytest.raises(_WorkBegan):
        acrobot_horizon.main(run[0], horizons=(1, 500), progress=False)


def test_a_horizon_no_held_out_episode_reaches_is_recorded_as_no_windows(
    run, tmp_path, monkeypatch, capsys
):
    """When every held-out episode ends (at the goal) within k steps there are no
    k-step windows: no error (the 99th percentile of nothing raised after all
    the work), NaN (null) errors and 0 windows. One window is enough for
    numbers: its |error| is both the RMS and the 99th percentile."""
    k_long = 300
    real = acrobot_horizon.open_loop_errors
    one = np.array([[0.5, -1.0, 2.0, -3.0]])  # the one 2-step window's error

    def fewer_windows(model, episodes, horizons):
        errors = real(model, episodes, horizons)
        return errors | {2: one, k_long: np.empty((0, 4))}

    monkeypatch.setattr(acrobot_horizon, "open_loop_errors", fewer_windows)
    out = tmp_path / "h.json"
    acrobot_horizon.main(
        run[0], horizons=(1, 2, k_long), identify=30, evaluate=40, progress=False,
        out=out,
    )  # fmt: skip
    data = json.loads(out.read_text())
    assert data["windows"][str(k_long)] == [0] * len(TINY.test_masses)
    assert data["windows"]["2"] == [1] * len(TINY.test_masses)
    assert data["windows"]["1"][0] >= 40
    for stat in ("rmse", "p99"):
        assert np.isnan(np.array(data[stat]["identified"][str(k_long)], float)).all()
        assert np.isfinite(data[stat]["identified"]["1"]).all()
        np.testing.assert_array_equal(data[stat]["identified"]["2"][0], np.abs(one[0]))
    # the printed table says so (its means were over settings without windows)
    acrobot_horizon.cli([
        str(run[0]), "--horizons", "1", "2", str(k_long), "--identify", "30",
        "--evaluate", "40", "--out", str(out), "--no-progress",
    ])  # fmt: skip
    printed = capsys.readouterr().out
    n = len(TINY.test_masses)
    assert printed.count(f"(k = {k_long}: windows on 0 of {n} settings)") == 2
    assert "(k = 1:" not in printed and "(k = 2:" not in printed


def test_out_writes_the_named_file_and_leaves_the_default_alone(
    run, tmp_path, monkeypatch
):
    """``out`` names the file; the file records the options it ran with, and the
    gathering got them: ``identify`` transitions to filter on, at least
    ``evaluate`` held-out ones, per setting."""
    real, gathered = acrobot_horizon.gather_split, []

    def spying(domain, params, n_train, n_test, *, rng):
        gathered.append((n_train, n_test))
        return real(domain, params, n_train, n_test, rng=rng)

    monkeypatch.setattr(acrobot_horizon, "gather_split", spying)
    out = run[0]
    before = (out / "horizon.json").read_text()
    other = acrobot_horizon.main(
        out, horizons=(2,), identify=30, evaluate=40, seed=7, progress=False,
        out=tmp_path / "h.json",
    )  # fmt: skip
    assert other.out == tmp_path / "h.json"
    written = json.loads(other.out.read_text())
    assert written["horizons"] == [2]
    assert written["seed"] == 7 and written["identify_transitions"] == 30
    assert written["evaluate_transitions"] == 40
    assert gathered == [(30, 0), (0, 40)] * len(TINY.test_masses)
    assert (out / "horizon.json").read_text() == before


def test_cli_passes_its_options_and_prints_means_over_settings_with_windows(
    monkeypatch, capsys, tmp_path
):
    """The CLI's options reach ``main`` (its defaults are ``main``'s), and each
    printed row is the mean over the settings that have windows of length k: a
    setting without any (NaN) leaves the mean of the others. Two hand-made
    settings: at k = 1 both have windows, means (1 + 3) / 2 = 2, ...; at k = 4
    only the first, whose numbers are printed as they are."""
    defaults = {
        name: p.default
        for name, p in inspect.signature(acrobot_horizon.main).parameters.items()
        if name != "run"
    }
    nan = [float("nan")] * 4
    summary = {
        "test_masses": [[0.9, 1.1], [1.2, 0.8]],
        "horizons": [1, 4],
        "dimensions": list(acrobot_horizon.STATE_NAMES),
        "windows": {"1": [9, 9], "4": [3, 0]},
        "rmse": {m: {"1": [[1, 2, 3, 4], [3, 4, 5, 6]], "4": [[1, 2, 3, 4], nan]}
                 for m in acrobot_horizon.MODELS},
        "p99": {m: {"1": [[10, 20, 30, 40], [30, 40, 50, 60]],
                    "4": [[10, 20, 30, 40], nan]}
                for m in acrobot_horizon.MODELS},
    }  # fmt: skip
    calls = fake_main(monkeypatch, acrobot_horizon, tmp_path / "h.json", summary)
    assert acrobot_horizon.cli(["RUN"]) == 0
    assert calls.pop() == ("RUN", defaults)
    acrobot_horizon.cli([
        "RUN", "--horizons", "1", "4", "--identify", "7", "--evaluate", "9",
        "--seed", "5", "--out", "o.json", "--no-progress",
    ])  # fmt: skip
    assert calls.pop() == (
        "RUN",
        {"horizons": (1, 4), "identify": 7, "evaluate": 9, "seed": 5,
         "out": "o.json", "progress": False},
    )  # fmt: skip
    rows = [
        line.split()
        for line in capsys.readouterr().out.splitlines()
        if line.split()[:1] and line.split()[0] in acrobot_horizon.MODELS
    ]
    want = {"1": [2, 3, 4, 5], "4": [1, 2, 3, 4]}
    # per model and k, the RMS table then the 99th percentile table (x 10)
    expected = [
        [m, k, *(str(scale * x) for x in want[k])]
        for scale in (1, 10)
        for k in ("1", "4")
        for m in acrobot_horizon.MODELS
    ]
    assert rows[len(expected) :] == expected  # the second call's printout
