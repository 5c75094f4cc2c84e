"""Refitting a finished (tiny) swing-up run's HiP-MDP with changed fit settings."""

from __future__ import annotations

import functools
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import hipmdp
from tasks import acrobot_identified, acrobot_refit


@pytest.fixture(scope="module")
def run(tiny_swingup_run):
    return tiny_swingup_run


def _arrays(path):
    with np.load(path, allow_pickle=False) as f:
        return {k: f[k] for k in f.files if k != "meta_json"}


def test_no_change_reproduces_the_runs_model(run, tmp_path):
    # the run's own fit stream and settings: the same model, array for array
    out = acrobot_refit.main(run, tmp_path / "same", {}, progress=False).out
    want, got = _arrays(run / "hipmdp_model.npz"), _arrays(out / "hipmdp_model.npz")
    assert want.keys() == got.keys()
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    assert (out / "batch.npz").read_bytes() == (run / "batch.npz").read_bytes()
    old = json.loads((run / "config.json").read_text())
    new = json.loads((out / "config.json").read_text())
    assert new["fit"] == {**old["fit"], "periodic": False}
    environment = new["refit"].pop("environment")  # what ran the refit
    assert new["refit"] == {"from": str(run), "changes": {}}
    assert environment["packages"]["numpy"] == np.__version__


def test_changed_settings_reach_the_model_and_the_checks(run, tmp_path):
    out = tmp_path / "periodic"
    changes = {"periodic": True, "n_support": 40}
    # progress bars for this refit only: a check fitting from the config shows none
    res = acrobot_refit.main(run, out, changes, progress=True)
    model = hipmdp.load(out / "hipmdp_model.npz")
    assert model.hyper.periodic == (0, 1) and len(model.support) == 40
    assert res.model.n_features == model.n_features
    config = json.loads((out / "config.json").read_text())
    assert config["fit"]["periodic"] is True and config["fit"]["n_support"] == 40
    assert config["fit"]["progress"] is False
    assert config["refit"]["changes"] == changes  # the record of what was changed
    # a check reads the new folder as a run, its average model periodic too
    finished = acrobot_identified.load_run(out)
    assert finished.hip.hyper.periodic == finished.average.hyper.periodic == (0, 1)


def test_a_run_without_filter_weights_refits_with_the_filter_it_ran(
    run, tmp_path, monkeypatch
):
    # a run written before FitConfig.filter_weights filtered at μ_w: a refit
    # keeps that, and changing only the filter leaves every fitted array as it was
    old = tmp_path / "old"
    old.mkdir()
    for name in ("batch.npz", "config.json", "hipmdp_model.npz"):
        (old / name).write_bytes((run / name).read_bytes())
    config = json.loads((old / "config.json").read_text())
    assert config["fit"].pop("filter_weights") == "prior_mean"  # TINY's
    (old / "config.json").write_text(json.dumps(config))
    # even were FitConfig's default another, the old run's value is its own
    other_default = functools.partial(hipmdp.FitConfig, filter_weights="training")
    monkeypatch.setattr(acrobot_refit.hipmdp, "FitConfig", other_default)
    same = acrobot_refit.main(old, tmp_path / "same", {}, progress=False).model
    assert same.filter_weights == "prior_mean"
    monkeypatch.undo()
    res = acrobot_refit.main(
        old, tmp_path / "new", {"filter_weights": "training"}, progress=False
    )
    assert res.model.filter_weights == "training"
    config = json.loads((tmp_path / "new" / "config.json").read_text())
    assert config["fit"]["filter_weights"] == "training"
    want = _arrays(run / "hipmdp_model.npz")
    got = _arrays(tmp_path / "new" / "hipmdp_model.npz")
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)


def test_parse_fit_types_and_errors():
    got = acrobot_refit.parse_fit(
        ["n_smooth=4000", "alpha=1.5", "periodic=TRUE", "filter_weights=training"]
    )
    assert got == {
        "n_smooth": 4000,
        "alpha": 1.5,
        "periodic": True,
        "filter_weights": "training",
    }
    for item, match in [
        ("n_smooth", "expected name=value"),
        ("nope=1", "expected name=value with name in n_support"),
        ("progress=true", "expected name=value"),
        ("n_smooth=4e3", "expected a int value for n_smooth"),
        ("periodic=yes", "expected a bool value for periodic"),
    ]:
        with pytest.raises(ValueError, match=match):
            acrobot_refit.parse_fit([item])


def test_bad_folders_and_values_fail_before_any_file_is_written(run, tmp_path):
    with pytest.raises(ValueError, match="other than the run"):
        acrobot_refit.main(run, run, {})
    full = tmp_path / "full"
    full.mkdir()
    (full / "x").write_text("")
    with pytest.raises(ValueError, match="^out: .* exists and is not an empty folder"):
        acrobot_refit.main(run, full, {})
    with pytest.raises(FileNotFoundError, match="config.json"):
        acrobot_refit.main(tmp_path / "none", tmp_path / "o", {})
    file = tmp_path / "file"
    file.write_text("mine")
    with pytest.raises(ValueError, match="exists and is not a folder"):
        acrobot_refit.main(run, file, {})
    with pytest.raises(ValueError, match="is not a folder, so"):
        acrobot_refit.main(run, file / "sub", {})
    with pytest.raises(ValueError, match="FitConfig.n_support"):
        acrobot_refit.main(run, tmp_path / "bad", {"n_support": 0})
    with pytest.raises(ValueError, match="FitConfig.filter_weights: expected one"):
        acrobot_refit.main(run, tmp_path / "bad", {"filter_weights": "mean"})
    damaged = tmp_path / "damaged"  # a field FitConfig lacks gave a TypeError
    shutil.copytree(run, damaged)
    config = json.loads((damaged / "config.json").read_text())
    config["fit"]["sweeps"] = 3
    (damaged / "config.json").write_text(json.dumps(config))
    match = "config.json: not a swing-up run's config: fit: unknown FitConfig fields"
    with pytest.raises(ValueError, match=match):
        acrobot_refit.main(damaged, tmp_path / "bad", {})
    assert not (tmp_path / "bad").exists()


def test_a_failed_fit_leaves_nothing_so_the_same_command_can_run_again(
    run, tmp_path, monkeypatch
):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    fit = acrobot_refit.hipmdp.fit
    monkeypatch.setattr(acrobot_refit.hipmdp, "fit", interrupted)
    with pytest.raises(KeyboardInterrupt):
        acrobot_refit.main(run, tmp_path / "refit", {}, progress=False)
    assert not (tmp_path / "refit").exists()
    monkeypatch.setattr(acrobot_refit.hipmdp, "fit", fit)
    out = acrobot_refit.main(run, tmp_path / "refit", {}, progress=False).out
    assert (out / "batch.npz").read_bytes() == (run / "batch.npz").read_bytes()


def test_a_failed_save_or_a_killed_refit_leaves_no_half_folder(
    run, tmp_path, monkeypatch
):
    def dies_saving(self, path):
        Path(path).write_bytes(b"half a model")
        raise KeyboardInterrupt

    save = acrobot_refit.hipmdp.HipMDP.save
    monkeypatch.setattr(acrobot_refit.hipmdp.HipMDP, "save", dies_saving)
    with pytest.raises(KeyboardInterrupt):
        acrobot_refit.main(run, tmp_path / "refit", {}, progress=False)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(acrobot_refit.hipmdp.HipMDP, "save", save)
    killed = tmp_path / ".refit.k1ll_2x9.tmp"  # what a kill while saving leaves
    killed.mkdir()
    (killed / "batch.npz").write_bytes(b"half a batch")
    out = acrobot_refit.main(run, tmp_path / "refit", {}, progress=False).out
    assert [p.name for p in tmp_path.iterdir()] == ["refit"]
    assert sorted(p.name for p in out.iterdir()) == [
        "batch.npz",
        "config.json",
        "hipmdp_model.npz",
    ]


def test_cli_reports_bad_options(run, tmp_path, capsys):
    with pytest.raises(SystemExit):
        acrobot_refit.cli([str(run), str(tmp_path / "o"), "--fit", "nope=1"])
    assert "--fit 'nope=1'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    # more support points than the batch has states: known once the batch is
    # read, before the fit (it was a traceback from inside the fit)
    with pytest.raises(SystemExit) as stopped:
        acrobot_refit.cli(
            [
                str(run),
                str(tmp_path / "o"),
                "--fit",
                "n_support=100000",
                "n_candidates=100000",
            ]
        )
    assert stopped.value.code == 2
    assert "FitConfig.n_support: expected at most" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_cli_passes_the_changes_and_progress_to_main(monkeypatch, capsys, tmp_path):
    calls = []

    def fake_main(run, out, fit, *, progress):
        calls.append((run, out, fit, progress))
        model = SimpleNamespace(
            n_features=3, support=np.zeros((40, 5)), info={"best_log_joint": -12.5}
        )
        return acrobot_refit.Results(tmp_path / "o", fit, 2.0, model)

    monkeypatch.setattr(acrobot_refit, "main", fake_main)
    assert acrobot_refit.cli(["RUN", "OUT", "--fit", "n_smooth=4000"]) == 0
    acrobot_refit.cli(["RUN", "OUT", "--no-progress"])
    assert calls == [
        ("RUN", "OUT", {"n_smooth": 4000}, True),
        ("RUN", "OUT", {}, False),
    ]
    assert "3 features, 40 support points, log joint -12.5" in capsys.readouterr().out
