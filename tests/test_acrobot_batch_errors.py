"""The batch-error check on a finished (tiny) swing-up run."""

from __future__ import annotations

import dataclasses
import inspect
import json
import shutil

import numpy as np
import pytest

import hipmdp
from tasks import acrobot_batch_errors
from tasks.acrobot_identified import load_run
from tests._cli import fake_main


@pytest.fixture(scope="module")
def run(tiny_swingup_run):
    return tiny_swingup_run


def test_errors_are_the_plain_predictions_on_each_instances_rows(run, tmp_path):
    # against predict_mean / predict (not the fast mean_predictor), row by row
    res = acrobot_batch_errors.main(run, fast=3.0, out=tmp_path / "e.json")
    s = json.loads(res.out.read_text())
    assert s == json.loads(json.dumps(res.summary))
    assert s["fast"] == 3.0
    _, hip, average, batch = load_run(run)
    K = hip.n_features - 1
    for col, b in enumerate(hip.instance_ids):
        data = batch.select(instances=[int(b)])
        fast = np.abs(data.states[:, 3]) >= 3.0
        assert s["fast_share"][col] == pytest.approx(fast.mean())
        weights = {"own": hip.weights[1:, col], "prior": hip.mu_w[1:]}
        for m in ("own", "prior", "average"):
            if m == "average":
                pred = average.predict(data.states, data.actions)[0]
            else:
                belief = hipmdp.Belief(weights[m], np.eye(K))
                pred = hip.predict(data.states, data.actions, belief)[0]
            err = (pred - data.deltas)[:, 2:]
            for band, rows in (("fast", fast), ("slow", ~fast)):
                want = np.sqrt((err[rows] ** 2).mean(0))
                np.testing.assert_allclose(s["rmse"][m][band][col], want, rtol=1e-8)
    # own weights fit their own instance's transitions: better than the prior mean
    own, prior = (np.array(s["rmse"][m]["slow"]) for m in ("own", "prior"))
    assert np.mean(own) < np.mean(prior)


@pytest.mark.filterwarnings("error")  # no "Mean of empty slice" for a user to read
def test_a_threshold_above_every_state_leaves_no_fast_rows(run, tmp_path):
    res = acrobot_batch_errors.main(run, fast=1e6, out=tmp_path / "e.json")
    s = res.summary
    assert s["fast_share"] == [0.0] * len(s["instance_ids"])
    assert np.isnan(s["rmse"]["own"]["fast"]).all()
    assert json.loads(res.out.read_text())["rmse"]["own"]["fast"][0] == [None, None]


def test_bad_options_fail_before_loading(tmp_path, run, capsys):
    with pytest.raises(FileNotFoundError, match="config.json"):
        acrobot_batch_errors.main(tmp_path)
    for bad in (0.0, -1.0, np.inf, np.nan):  # inf: no fast states at all
        with pytest.raises(ValueError, match="fast: expected a finite number > 0"):
            acrobot_batch_errors.main(run, fast=bad)
    assert acrobot_batch_errors.cli([str(run), "--out", str(tmp_path / "c.json")]) == 0
    assert "wrote" in capsys.readouterr().out


def test_instances_are_matched_by_id_not_by_position(run, tmp_path):
    # the same model with its weight columns in reverse order: every number must
    # follow the instance ids (and the parameters come from the table by id)
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    hip = hipmdp.load(run / "hipmdp_model.npz")
    assert len(hip.instance_ids) > 2
    dataclasses.replace(
        hip, instance_ids=hip.instance_ids[::-1], weights=hip.weights[:, ::-1]
    ).save(copy / "hipmdp_model.npz")
    a = acrobot_batch_errors.main(run, fast=3.0, out=tmp_path / "a.json").summary
    b = acrobot_batch_errors.main(copy, fast=3.0, out=tmp_path / "b.json").summary
    assert b["instance_ids"] == a["instance_ids"][::-1]
    for key in ("fast_share", "instance_parameters"):
        assert b[key] == a[key][::-1]
    for m in acrobot_batch_errors.MODELS:
        for band in ("fast", "slow"):
            np.testing.assert_allclose(
                b["rmse"][m][band], a["rmse"][m][band][::-1], rtol=1e-10
            )
    table = hipmdp.data.ParameterTable.load(run / "batch.npz")
    for i, inst in enumerate(a["instance_ids"]):
        row = list(table.instances).index(inst)
        assert a["instance_parameters"][i] == table.values[row].tolist()


def test_a_state_exactly_at_the_threshold_is_fast(run, tmp_path):
    """Fast is ``|θ̇₂| ≥ fast``: at the largest |θ̇₂| of an instance's rows as the
    threshold, that one row (speeds are continuous: no tie) is its fast share."""
    hip = hipmdp.load(run / "hipmdp_model.npz")
    batch = hipmdp.Transitions.load(run / "batch.npz")
    b = int(hip.instance_ids[0])
    speeds = np.abs(batch.select(instances=[b]).states[:, 3])
    res = acrobot_batch_errors.main(run, fast=speeds.max(), out=tmp_path / "e.json")
    assert res.summary["fast_share"][0] == 1 / len(speeds)
    assert np.isfinite(res.summary["rmse"]["own"]["fast"][0]).all()


def test_cli_passes_its_options_and_prints_each_instances_row(
    monkeypatch, capsys, tmp_path
):
    """The CLI's ``--fast`` reaches ``main`` (its default is ``main``'s), and each
    printed row is that instance's: its id, parameters, fast share in percent and
    its (Δθ̇₁, Δθ̇₂) RMS errors per model and band, from a hand-made summary."""
    default = inspect.signature(acrobot_batch_errors.main).parameters["fast"].default
    models = acrobot_batch_errors.MODELS
    summary = {
        "fast": 3.0,
        "instance_ids": [4, 7],
        "parameters": ["link_mass_1", "link_mass_2"],
        "instance_parameters": [[0.7, 1.3], [1.3, 0.7]],
        "fast_share": [0.25, 0.5],
        "rmse": {
            m: {"fast": [[i + 0.125, i + 0.25], [i + 2.5, i + 3.75]],
                "slow": [[i + 0.5, i + 0.625], [i + 4.25, i + 5.5]]}
            for i, m in enumerate(models)
        },
    }  # fmt: skip
    calls = fake_main(monkeypatch, acrobot_batch_errors, tmp_path / "e.json", summary)
    assert acrobot_batch_errors.cli(["RUN"]) == 0
    assert calls == [("RUN", {"fast": default, "out": None})]
    acrobot_batch_errors.cli(["RUN", "--fast", "2.5", "--out", "e.json"])
    assert calls[1] == ("RUN", {"fast": 2.5, "out": "e.json"})
    rows = [
        line.replace(",", " ").split()
        for line in capsys.readouterr().out.splitlines()
        if line.split()[:1] in (["4"], ["7"])
    ]
    for row, i in zip(rows, [0, 1, 0, 1], strict=True):  # two calls' printouts
        assert [int(row[0]), *map(float, row[1:4])] == [
            summary["instance_ids"][i],
            *summary["instance_parameters"][i],
            100 * summary["fast_share"][i],
        ]
        cells = [float(x) for x in row[4:]]
        assert cells == [
            x
            for m in models
            for band in ("fast", "slow")
            for x in summary["rmse"][m][band][i]
        ]
