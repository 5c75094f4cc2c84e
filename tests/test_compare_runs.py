"""tasks.compare_runs: where two run folders part, on small hand-made folders."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from tasks.compare_runs import cli, compare_arrays, flatten, main, report
from tasks.experiment import write_json

ENV = {"packages": {"numpy": "2.4.6"}, "blas": [{"architecture": "SkylakeX"}]}


def _run(path, *, returns=None, config=None, metrics=None, env=ENV, progress=True):
    path.mkdir()
    write_json(path / "config.json", config or {"seed": 0, "progress": progress})
    m = metrics or {"paired_difference": {"hipmdp - average": -0.5}, "n": [1, 2]}
    m = m | {"seconds": {"total": 1.0}} | ({"environment": env} if env else {})
    write_json(path / "metrics.json", m)
    r = np.arange(12.0).reshape(3, 4) if returns is None else returns
    meta = np.array(json.dumps({"config": {"n_support": 5, "progress": progress}}))
    np.savez(path / "trials.npz", returns=r, methods=np.array(["a", "b", "c"]))
    np.savez(path / "model.npz", f=np.ones(3), meta_json=meta)
    return path


def test_a_copy_is_identical_whatever_its_timings(tmp_path):
    a = _run(tmp_path / "a")
    b = _run(tmp_path / "b")
    m = json.loads((b / "metrics.json").read_text())
    m["seconds"]["total"] = 99.0  # timings never count
    write_json(b / "metrics.json", m)
    result = main(a, b)
    assert result.identical and not result.config and result.environment == {}
    assert set(result.arrays) == {
        "model.npz:f", "model.npz:meta_json", "trials.npz:methods",
        "trials.npz:returns",
    }  # fmt: skip
    assert "verdict: identical results" in report(result)
    with pytest.raises(ValueError, match="is one of the run"):  # before any reading
        main(a, b, out=b / "config.json")


def test_an_experiment_older_than_a_field_counts_as_its_old_behaviour(tmp_path):
    """A run made before ``split`` and ``methods`` existed ran the random split
    with no added method: its config equals a newer run's with those values,
    and not one with others."""
    old = {"seed": 0, "fit": {"n_sweeps": 60}}
    a = _run(tmp_path / "a", config=old)
    b = _run(tmp_path / "b", config=old | {"split": "random", "methods": []})
    assert main(a, b).config == {}
    c = _run(tmp_path / "c", config=old | {"split": "time", "methods": ["x=m:A"]})
    assert main(a, c).config == {
        "methods": [[], ["x=m:A"]],  # a list is one setting
        "split": ["random", "time"],
    }
    assert "\n  methods: [] vs ['x=m:A']\n  split: 'random' vs 'time'\n" in report(
        main(a, c)
    )
    # and within the fit: before periodic and filter_weights, neither was on
    fit = {"n_sweeps": 60, "periodic": False}
    d = _run(
        tmp_path / "d", config=old | {"fit": fit | {"filter_weights": "prior_mean"}}
    )
    assert main(a, d).config == {}
    e = _run(tmp_path / "e", config=old | {"fit": fit | {"filter_weights": "training"}})
    assert main(a, e).config == {"fit.filter_weights": ["prior_mean", "training"]}
    # before new_features the sampler took the paper's step
    f = _run(tmp_path / "f", config=old | {"fit": fit | {"new_features": "paper"}})
    assert main(a, f).config == {}
    g = _run(
        tmp_path / "g", config=old | {"fit": fit | {"new_features": "multiple_try"}}
    )
    assert main(a, g).config == {"fit.new_features": ["paper", "multiple_try"]}


def test_a_model_from_before_the_data_digest_is_compared_without_it():
    """A model saved before ``info["data_sha256"]`` and one of the same fit after:
    identical results (the digest records the data, which ``batch.npz`` holds);
    two digests that differ are a difference."""

    def meta(**info):
        return np.array(
            json.dumps(
                {"format_version": 1, "filter_weights": "prior_mean",
                 "info": {"config": {"periodic": False}, "n_transitions": 9, **info}}
            )
        )  # fmt: skip

    assert compare_arrays(meta(), meta(data_sha256="ab")) == "identical"
    assert compare_arrays(meta(data_sha256="ab"), meta()) == "identical"
    assert compare_arrays(meta(data_sha256="ab"), meta(data_sha256="cd")) == {
        "json": {"info.data_sha256": ["ab", "cd"]}
    }
    assert compare_arrays(meta(), meta(data_sha256="ab", n_transitions=8)) == {
        "json": {"info.n_transitions": [9, 8]}
    }


def test_a_model_older_than_a_field_counts_as_its_old_behaviour():
    """A model file written before ``filter_weights`` (and its fit config before
    ``periodic``) filtered at μ_w with kernels not periodic."""

    def meta(**new):
        return np.array(
            json.dumps(
                {
                    "format_version": 1,
                    "info": {"config": {"n_support": 5, **new}},
                    **({"filter_weights": new["filter_weights"]} if new else {}),
                }
            )
        )

    old = meta()
    assert compare_arrays(old, meta(filter_weights="prior_mean", periodic=False)) == (
        "identical"
    )
    assert compare_arrays(old, meta(filter_weights="training", periodic=False)) == {
        "json": {
            "filter_weights": ["prior_mean", "training"],
            "info.config.filter_weights": ["prior_mean", "training"],
        }
    }


def test_differences_are_located_and_counted(tmp_path):
    a = _run(tmp_path / "a")
    returns = np.arange(12.0).reshape(3, 4)
    returns[1, 2] += 3.0
    returns[2, 0] -= 1.0
    b = _run(
        tmp_path / "b",
        returns=returns,
        config={"seed": 1, "progress": False},  # seed counts, progress does not
        progress=False,  # nor in the model's metadata
        metrics={"paired_difference": {"hipmdp - average": -1.5}, "n": [1, 2]},
        env={"packages": {"numpy": "2.3.0"}, "blas": [{"architecture": "Haswell"}]},
    )
    result = main(a, b)
    assert result.config == {"seed": [0, 1]}
    assert result.environment == {
        "blas.0.architecture": ["SkylakeX", "Haswell"],
        "packages.numpy": ["2.4.6", "2.3.0"],
    }
    assert result.arrays["trials.npz:returns"] == {
        "max_abs_diff": 3.0, "n_differ": 2, "size": 12
    }  # fmt: skip
    assert result.arrays["model.npz:meta_json"] == "identical"  # progress only
    assert result.metrics == {"paired_difference.hipmdp - average": [-0.5, -1.5]}
    text = report(result)
    assert "paired_difference: 1 value, largest relative difference 0.67" in text
    assert "verdict: the results differ" in text


def test_runs_from_before_the_environment_was_recorded(tmp_path):
    result = main(_run(tmp_path / "a"), _run(tmp_path / "b", env=None))
    assert result.environment == "unrecorded" and result.identical


def test_a_metric_added_since_is_named_not_compared(tmp_path):
    """A run written before ``per_setting_loglik`` existed reproduces a newer
    one if everything both have agrees; where both have it, it counts."""
    base = {"paired_difference": {"hipmdp - average": -0.5}, "n": [1, 2]}
    a = _run(tmp_path / "a", metrics=base)
    b = _run(tmp_path / "b", metrics=base | {"per_setting_loglik": {"x": [1.0]}})
    result = main(a, b)
    assert result.identical and result.not_compared == ("per_setting_loglik",)
    assert "not compared (one run is older than them): per_setting_loglik" in (
        report(result)
    )
    c = _run(tmp_path / "c", metrics=base | {"per_setting_loglik": {"x": [2.0]}})
    result = main(b, c)
    assert result.metrics == {"per_setting_loglik.x.0": [1.0, 2.0]}
    assert not result.not_compared and not result.identical
    # a metric not known to be newer, nor an added method's, is a difference
    d = _run(tmp_path / "d", metrics=base | {"other": 1})
    result = main(a, d)
    assert result.metrics == {"other": [None, 1]}
    assert not result.identical and not result.shared_identical


def test_an_added_methods_pair_added_since_is_named_not_compared(tmp_path):
    """Runs with the same added method, one from before its ``NAME - average``
    pair existed: the pair is named, not compared, wherever it sits (as a
    metric of ADDED_METRICS is); where both have it, it counts; another pair
    one run lacks, or the pair of a method the runs did not both add, is not
    taken for it."""
    added = {"seed": 0, "progress": True, "methods": ["d=mine:D"]}
    old = {
        "paired_difference": {"hipmdp - average": -0.5, "d - true": -1.0},
        "split": {"pairs": {"d - true": {"gap": 2.0}}},
    }
    new = {
        "paired_difference": old["paired_difference"] | {"d - average": 0.5},
        "split": {"pairs": old["split"]["pairs"] | {"d - average": {"gap": 1.0}}},
    }
    a = _run(tmp_path / "a", metrics=old, config=added)
    b = _run(tmp_path / "b", metrics=new, config=added)
    result = main(a, b)
    assert result.identical and result.not_compared == (
        "paired_difference.d - average", "split.pairs.d - average"
    )  # fmt: skip
    assert result == main(b, a)._replace(extra=result.extra)  # either order
    assert (
        "not compared (one run is older than them): paired_difference.d - average, "
        "split.pairs.d - average"
    ) in report(result)
    changed = json.loads(json.dumps(new))
    changed["paired_difference"]["d - average"] = 0.7
    c = _run(tmp_path / "c", metrics=changed, config=added)
    result = main(b, c)
    assert result.metrics == {"paired_difference.d - average": [0.5, 0.7]}
    assert not result.not_compared and not result.identical
    # a pair that is not new: a difference
    lacking = json.loads(json.dumps(new))
    del lacking["paired_difference"]["d - true"]
    d = _run(tmp_path / "d", metrics=lacking, config=added)
    assert main(b, d).metrics == {"paired_difference.d - true": [-1.0, None]}
    # the method only one run added: its entries, the pair among them
    e = _run(tmp_path / "e", metrics=new, config={"seed": 0, "progress": True})
    result = main(a, e)
    assert "d - average" not in " ".join(result.not_compared)
    assert not result.shared_identical  # e lacks d's config: its entries differ


def test_a_run_with_an_added_method_is_compared_on_what_both_ran(tmp_path):
    """A run with a method added (``--method``) against one without: the
    built-in methods' rows of trials.npz and every shared metric are compared,
    the added method's are named. (They were reported as differing: shapes
    (3, 4) against (4, 4), and its metric values counted as changed.)"""
    base = {"returns": {"a": [1.0], "b": [2.0]}, "n": [1, 2]}
    added = {"seed": 0, "progress": True, "methods": ["d=mine:D"]}
    a = _run(tmp_path / "a", metrics=base)
    more = {**base, "returns": base["returns"] | {"d": [3.0]}}
    b = _run(tmp_path / "b", metrics=more, config=added)
    returns = np.r_[np.arange(12.0).reshape(3, 4), np.full((1, 4), 7.0)]
    np.savez(b / "trials.npz", returns=returns, methods=np.array(["a", "b", "c", "d"]))
    result = main(a, b)
    assert result.arrays["trials.npz:returns"] == "identical"
    assert result.arrays["trials.npz:methods"] == {"methods_only_in": [[], ["d"]]}
    assert result.metrics == {} and result.extra[str(b)] == ["returns.d.0"]
    assert result.shared_identical and not result.identical
    text = report(result)
    assert "compared on the methods both ran; only the second ran ['d']" in text
    assert "verdict: identical where both runs have results" in text
    assert cli([str(a), str(b)]) == 0  # the exit status: the same where both ran
    # the rows are matched by name, not position
    order = [2, 0, 1, 3]
    names = np.array(["a", "b", "c", "d"])[order]
    np.savez(b / "trials.npz", returns=returns[order], methods=names)
    assert main(a, b).arrays["trials.npz:returns"] == "identical"
    # a built-in method's row that moved is a difference
    returns[1, 2] += 1.0
    np.savez(b / "trials.npz", returns=returns[order], methods=names)
    result = main(a, b)
    assert result.arrays["trials.npz:returns"]["n_differ"] == 1
    assert not result.shared_identical
    assert "verdict: the results differ" in report(result)


def test_a_method_in_one_trials_file_that_no_config_added_is_a_difference(
    tmp_path,
):
    """Rows of a method one ``trials.npz`` names and the other lacks are set apart
    only for a method that run's config names as added (``--method``): a
    built-in method missing from one file (a damaged or hand-edited file), or
    one the other run's config names, is a difference."""
    a = _run(tmp_path / "a")
    returns = np.arange(12.0).reshape(3, 4)
    np.savez(a / "trials.npz", returns=returns, methods=np.array(["a", "b", "c"]))
    b = _run(tmp_path / "b")
    np.savez(b / "trials.npz", returns=returns[:2], methods=np.array(["a", "b"]))
    result = main(a, b)
    assert result.arrays["trials.npz:methods"] == {"methods_differ": [["c"], []]}
    assert result.arrays["trials.npz:returns"] == "identical"  # on a and b
    assert not result.shared_identical
    text = report(result)
    assert "arrays: 3 identical, 1 differ" in text
    assert "verdict: the results differ" in text
    # named as added, but by the run that lacks it
    added = {"seed": 0, "progress": True, "methods": ["c=mine:C"]}
    b = _run(tmp_path / "b2", config=added)
    np.savez(b / "trials.npz", returns=returns[:2], methods=np.array(["a", "b"]))
    assert main(a, b).arrays["trials.npz:methods"] == {"methods_differ": [["c"], []]}
    # named as added by the run that has it: set apart
    c = _run(tmp_path / "c", config=added)
    result = main(c, tmp_path / "b")
    assert result.arrays["trials.npz:methods"] == {"methods_only_in": [["c"], []]}
    assert result.shared_identical


def test_an_added_methods_steps_are_set_apart_as_its_returns(tmp_path):
    """trials.npz's ``steps`` has a row per method, as ``returns`` has: a run with
    an added method is compared on the built-in methods' steps (it was reported
    as differing, shapes (3, 4) against (4, 4)), and a built-in's step that
    moved is a difference."""
    a = _run(tmp_path / "a")
    steps = np.arange(12).reshape(3, 4) + 100
    np.savez(a / "trials.npz", returns=np.arange(12.0).reshape(3, 4),
             steps=steps, methods=np.array(["a", "b", "c"]))  # fmt: skip
    b = _run(tmp_path / "b", config={"seed": 0, "progress": True,
                                     "methods": ["d=mine:D"]})  # fmt: skip
    more = np.r_[steps, np.full((1, 4), 7)]
    returns = np.r_[np.arange(12.0).reshape(3, 4), np.full((1, 4), 7.0)]
    names = np.array(["a", "b", "c", "d"])
    np.savez(b / "trials.npz", returns=returns, steps=more, methods=names)
    result = main(a, b)
    assert result.arrays["trials.npz:steps"] == "identical"
    assert result.shared_identical and cli([str(a), str(b)]) == 0
    more[0, 1] += 1
    np.savez(b / "trials.npz", returns=returns, steps=more, methods=names)
    result = main(a, b)
    assert result.arrays["trials.npz:steps"] == {
        "max_abs_diff": 1.0, "n_differ": 1, "size": 12
    }  # fmt: skip
    assert not result.shared_identical


def test_a_statistic_named_as_an_added_method_is_compared(tmp_path):
    """An added method may bear the name of a statistic (README's example method
    is ``mean``): a metric one run has more under ``margin_to_target.hipmdp.mean``
    (a list the other run also has, shorter) is a difference, not the added
    method's entry; ``returns.mean`` is the method's."""
    added = {"seed": 0, "progress": True, "methods": ["mean=mine:MeanDelta"]}
    margin = {"hipmdp": {"mean": [-20.0], "n": 480}}
    base = {"returns": {"hipmdp": [1.0]}, "margin_to_target": margin}
    b = _run(tmp_path / "b", metrics=base)
    longer = {"hipmdp": {"mean": [-20.0, -8.0], "n": 480}}
    more = {"returns": {"hipmdp": [1.0], "mean": [2.0]}, "margin_to_target": longer}
    a = _run(tmp_path / "a", metrics=more, config=added)
    result = main(a, b)
    assert result.extra[str(a)] == ["returns.mean.0"]
    assert result.metrics == {"margin_to_target.hipmdp.mean.1": [-8.0, None]}
    assert not result.shared_identical


def test_settings_that_only_show_or_schedule_a_run_are_no_difference(tmp_path):
    """``progress``, ``workers`` and ``record`` (PRESENTATION) change no result;
    any other setting that differs is named."""
    shown = {"seed": 0, "progress": True, "workers": 1, "record": True}
    a = _run(tmp_path / "a", config=shown)
    b = _run(tmp_path / "b", config={**shown, "progress": False, "workers": 4,
                                     "record": False})  # fmt: skip
    assert main(a, b).config == {}
    c = _run(tmp_path / "c", config={**shown, "record": False, "trials": 3})
    assert main(a, c).config == {"trials": [None, 3]}


def test_only_an_added_methods_entries_are_set_apart(tmp_path):
    """What one run lacks counts as a difference unless it is an entry of a
    method only the other run added: a shorter list, a None against a value,
    an empty list against a filled one, a missing file, or two runs that share
    no method do not pass as "identical where both runs have results"."""
    added = {"seed": 0, "progress": True, "methods": ["d=mine:D"]}
    base = {"returns": {"a": [1.0, 2.0]}, "floor": {"a": 1.0}, "n": [1]}
    a = _run(tmp_path / "a", metrics=base)
    for name, changed in [
        ("shorter", {"returns": {"a": [1.0]}}),
        ("none", {"floor": None}),
        ("empty", {"n": []}),
    ]:
        b = _run(tmp_path / name, metrics=base | changed, config=added)
        result = main(a, b)
        assert result.metrics and not result.shared_identical, name
        assert "verdict: the results differ" in report(result), name
    more = base | {"returns": {"a": [1.0, 2.0], "d": [3.0]}}
    b = _run(tmp_path / "more", metrics=more, config=added)
    assert main(a, b).shared_identical and main(a, b).extra[str(b)] == ["returns.d.0"]
    (b / "model.npz").unlink()
    assert not main(a, b).shared_identical  # a missing file
    c = _run(tmp_path / "other_methods", metrics=base)
    np.savez(c / "trials.npz", returns=np.arange(12.0).reshape(3, 4),
             methods=np.array(["x", "y", "z"]))  # fmt: skip
    result = main(a, c)
    assert result.arrays["trials.npz:methods"]["n_differ"] == 3
    assert not result.shared_identical
    # only per-method arrays are cut to the shared rows: test_masses of as many
    # settings as methods is compared whole; the same methods reordered match
    masses = np.arange(6.0).reshape(3, 2)
    for run, names, m in (
        (a, ["a", "b", "c"], masses),
        (c, ["c", "a", "b"], masses + np.eye(3, 2)),
    ):
        order = [["a", "b", "c"].index(n) for n in names]
        np.savez(run / "trials.npz", returns=np.arange(12.0).reshape(3, 4)[order],
                 methods=np.array(names), test_masses=m)  # fmt: skip
    result = main(a, c)
    assert result.arrays["trials.npz:returns"] == "identical"
    assert result.arrays["trials.npz:methods"] == "identical"
    assert result.arrays["trials.npz:test_masses"]["n_differ"] == 2


def test_an_added_methods_entries_are_named_by_its_name_alone_or_in_a_pair(tmp_path):
    """The added method's entries are set apart wherever its name stands: alone
    (``returns.d``) or in a pair (``hipmdp - d``). Its entries make the runs
    identical only where both have results; so do its rows of trials.npz.
    What the run lacks apart from them is a difference: a metric under no
    method's name, or one of a method both runs added."""
    added = {"seed": 0, "progress": True, "methods": ["d=mine:D"]}
    base = {"returns": {"a": [1.0]}, "paired_difference": {"hipmdp - a": 0.5}}
    a = _run(tmp_path / "a", metrics=base)
    more = {
        "returns": {"a": [1.0], "d": [3.0]},
        "paired_difference": {"hipmdp - a": 0.5, "hipmdp - d": 0.1},
    }
    b = _run(tmp_path / "b", metrics=more, config=added)  # trials.npz as a's
    result = main(a, b)
    assert result.metrics == {} and result.arrays["trials.npz:returns"] == "identical"
    assert result.extra == {
        str(a): [], str(b): ["paired_difference.hipmdp - d", "returns.d.0"]
    }  # fmt: skip
    assert result.shared_identical and not result.identical
    assert "verdict: identical where both runs have results" in report(result)
    # its rows of trials.npz alone (no metric of it) are also more, not the same
    c = _run(tmp_path / "c", metrics=base, config=added)
    returns = np.r_[np.arange(12.0).reshape(3, 4), np.full((1, 4), 7.0)]
    np.savez(c / "trials.npz", returns=returns, methods=np.array(["a", "b", "c", "d"]))
    result = main(a, c)
    assert result.metrics == {} and not any(result.extra.values())
    assert result.shared_identical and not result.identical
    # a metric under no method's name
    d = _run(tmp_path / "d", metrics=more | {"floor": 1.0}, config=added)
    assert main(a, d).metrics == {"floor": [None, 1.0]}
    # the added method's entry that only one of two runs adding it has
    fewer = more | {"paired_difference": base["paired_difference"]}
    e = _run(tmp_path / "e", metrics=fewer, config=added)
    result = main(b, e)
    assert result.metrics == {"paired_difference.hipmdp - d": [0.1, None]}
    assert not result.shared_identical


def test_a_metric_null_in_one_run_and_missing_in_the_other_is_a_difference(tmp_path):
    """A metric written as null (no value: an interval of one sample, a target
    never reached) is not the same as no metric at all."""
    base = {"n": [1, 2]}
    a = _run(tmp_path / "a", metrics=base | {"episodes_to_within": None})
    b = _run(tmp_path / "b", metrics=base)
    result = main(a, b)
    assert list(result.metrics) == ["episodes_to_within"] and not result.identical


def test_a_folder_without_metrics_is_not_a_run(tmp_path):
    """Only a refit folder (``refit`` in its config) has no metrics.json: any
    other folder without one is refused, not compared as a run with no
    metrics."""
    a, b = _run(tmp_path / "a"), _run(tmp_path / "b")
    (b / "metrics.json").unlink()
    with pytest.raises(FileNotFoundError, match="no metrics.json; expected a fin"):
        main(a, b)


def test_the_order_blas_libraries_were_loaded_in_is_no_difference(tmp_path):
    """threadpoolctl lists numpy's and scipy's BLAS in load order, which varies
    from process to process: two runs in one environment read as differing."""
    blas = [{"version": "0.3.31"}, {"version": "0.3.30"}]
    a = _run(tmp_path / "a", env={"blas": blas})
    b = _run(tmp_path / "b", env={"blas": blas[::-1]})
    assert main(a, b).environment == {}


def test_files_and_arrays_only_one_run_has(tmp_path):
    a, b = _run(tmp_path / "a"), _run(tmp_path / "b")
    (b / "model.npz").unlink()
    np.savez(b / "trials.npz", returns=np.arange(12.0).reshape(3, 4))
    result = main(a, b)
    assert result.only_in == {str(a): ["model.npz"], str(b): []}
    assert result.arrays["trials.npz:methods"] == {"only_in": str(a)}
    assert not result.identical
    np.savez(b / "trials.npz", **np.load(a / "trials.npz"))
    assert not main(a, b).identical  # a missing file alone is a difference


def test_a_refit_folder_compares_with_its_run(tmp_path):
    a = _run(tmp_path / "a")
    b = tmp_path / "b"
    b.mkdir()
    write_json(b / "config.json", {"seed": 0, "refit": {"environment": ENV}})
    np.savez(b / "model.npz", f=np.ones(3) + 1e-12, meta_json=np.array("{}"))
    result = main(a, b)
    assert result.config == {"refit": [None, {}]}  # only the refit itself
    assert result.environment == {}  # read from config.json's refit
    assert result.arrays["model.npz:f"] == {
        "max_abs_diff": pytest.approx(1e-12, rel=0.01), "n_differ": 3, "size": 3
    }  # fmt: skip


def test_a_damaged_array_is_named_unreadable(tmp_path):
    """A changed byte in one run's array file (zipfile's BadZipFile, which
    stopped the comparison) is reported for that array, naming the file."""
    from hipmdp.data import npz_bytes
    from tests.test_data import flipped, member_data

    a, b = _run(tmp_path / "a"), _run(tmp_path / "b")
    arrays = {"returns": np.arange(12.0), "methods": np.array(["a", "b", "c"])}
    good = npz_bytes(arrays)
    for run, content in (
        (a, good),
        (b, flipped(good, member_data(good, "returns.npy").stop - 2)),
    ):
        (run / "trials.npz").write_bytes(content)
    result = main(a, b)
    unreadable = result.arrays["trials.npz:returns"]["unreadable"]
    assert unreadable.startswith(f"{b / 'trials.npz'}: array 'returns' cannot be read")
    assert result.arrays["trials.npz:methods"] == "identical"
    # the methods array too (it is read first, to line up the rows)
    (b / "trials.npz").write_bytes(
        flipped(good, member_data(good, "methods.npy").stop - 2)
    )
    result = main(a, b)
    unreadable = result.arrays["trials.npz:methods"]["unreadable"]
    assert unreadable.startswith(f"{b / 'trials.npz'}: array 'methods' cannot be read")
    assert result.arrays["trials.npz:returns"] == "identical"


def test_a_trials_file_with_fewer_rows_than_methods_is_unreadable(tmp_path):
    """A trials.npz whose ``returns`` has fewer rows than its ``methods`` names
    (a damaged or hand-edited file), against a run that shares some methods:
    lining up the shared rows raised an IndexError that stopped the comparison."""

    def trials(run, rows, *methods):
        np.savez(run / "trials.npz", returns=np.zeros((rows, 2)), methods=methods)

    a, b = _run(tmp_path / "a"), _run(tmp_path / "b")
    trials(a, 3, "true", "mine", "hipmdp")
    trials(b, 2, "x", "true", "hipmdp")
    result = main(a, b)
    assert result.arrays["trials.npz:returns"] == {
        "unreadable": "returns: expected a row per entry of its file's methods "
        "(3), got shape (2, 2)"
    }
    assert not result.identical
    # the row missing is of a method the other run lacks: the shared rows exist,
    # and were compared as if the file were whole
    trials(a, 2, "true", "hipmdp", "mine")
    trials(b, 2, "true", "hipmdp")
    unreadable = main(a, b).arrays["trials.npz:returns"]["unreadable"]
    assert unreadable.endswith("methods (3), got shape (2, 2)")


def test_compare_arrays_nan_shapes_dtypes_and_strings():
    nan = np.array([1.0, np.nan, 3.0])
    assert compare_arrays(nan, nan.copy()) == "identical"
    moved = np.array([1.0, 2.0, np.nan])  # NaN moved: two entries differ
    assert compare_arrays(nan, moved) == {
        "max_abs_diff": 0.0, "n_differ": 2, "size": 3
    }  # fmt: skip
    # a NaN where both have one is no difference: one entry of these two differs
    assert compare_arrays(np.array([np.nan, 1.0]), np.array([np.nan, 3.0])) == {
        "max_abs_diff": 2.0, "n_differ": 1, "size": 2
    }  # fmt: skip
    big = np.array([2**53, 1], dtype=np.int64)
    assert compare_arrays(big, big + [0, 5]) == {
        "max_abs_diff": 5.0, "n_differ": 1, "size": 2
    }  # fmt: skip
    assert compare_arrays(np.zeros(2), np.zeros(3)) == {
        "shapes": [[2], [3]], "overlap": {"shape": [2], "comparison": "identical"}
    }  # fmt: skip
    # a rerun with more trials: the rows both hold are compared, axis by axis
    rows = np.arange(12.0).reshape(4, 3)
    more = np.vstack([rows, rows])
    more[1, 2] += 0.5  # outside the first comparison's overlap, inside the second's
    assert compare_arrays(rows[:, :2], more) == {
        "shapes": [[4, 2], [8, 3]],
        "overlap": {"shape": [4, 2], "comparison": "identical"},
    }
    assert compare_arrays(rows, more)["overlap"] == {
        "shape": [4, 3],
        "comparison": {"max_abs_diff": 0.5, "n_differ": 1, "size": 12},
    }
    for a, b in [(np.zeros(2), np.zeros((2, 1))), (np.zeros(0), np.zeros(2))]:
        assert compare_arrays(a, b) == {"shapes": [list(a.shape), list(b.shape)]}
    assert compare_arrays(np.array(["x", "y"]), np.array(["x", "zz"])) == {
        "n_differ": 1, "size": 2
    }  # fmt: skip
    # a single string that is not a JSON object (a label, a JSON list) is
    # compared as a string
    for x, y in [("cartpole", "acrobot"), ("[1, 2]", "[1, 3]")]:
        assert compare_arrays(np.array(x), np.array(y)) == {"n_differ": 1, "size": 1}
        assert compare_arrays(np.array(x), np.array(x)) == "identical"
    assert compare_arrays(np.zeros(2), np.array(["a", "b"])) == {
        "dtypes": ["float64", "<U1"]
    }  # fmt: skip
    # complex entries by their modulus of difference, not their real parts
    assert compare_arrays(np.array([1 + 1j]), np.array([1 + 3j])) == {
        "max_abs_diff": 2.0, "n_differ": 1, "size": 1
    }  # fmt: skip
    # booleans are numbers: 0 and 1, as integers are
    assert compare_arrays(np.array([True, False]), np.array([1, 0])) == "identical"
    assert compare_arrays(np.array([True, False]), np.array([True, True])) == {
        "max_abs_diff": 1.0, "n_differ": 1, "size": 2
    }  # fmt: skip
    assert flatten({"a": [1, {"b": 2}]}) == {"a.0": 1, "a.1.b": 2}
    assert flatten({"a": []}) != flatten({})


def test_cli_reports_and_rejects_a_folder_that_is_not_a_run(tmp_path, capsys):
    a = _run(tmp_path / "a")
    shutil.copytree(a, tmp_path / "b")
    out = tmp_path / "cmp.json"
    assert cli([str(a), str(tmp_path / "b"), "--out", str(out)]) == 0
    assert "identical results" in capsys.readouterr().out
    assert json.loads(out.read_text())["identical"] is True
    # results that differ: status 1, as diff's (it was 0 whatever the verdict)
    _run(tmp_path / "c", returns=np.arange(12.0).reshape(3, 4) + 1)
    assert cli([str(a), str(tmp_path / "c")]) == 1
    assert "the results differ" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        cli([str(a), str(tmp_path)])
    assert exit_info.value.code == 2
    assert "no config.json" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:  # before the runs are read
        cli(["no_run", "no_run_either", "--out", str(out / "sub")])
    assert exit_info.value.code == 2
    assert f"out: {out} is not a folder, so" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:  # no rows at all
        cli([str(a), str(tmp_path / "b"), "--show", "0"])
    assert exit_info.value.code == 2
    assert "--show: expected >= 1, got 0" in capsys.readouterr().err


def test_the_report_says_how_many_more_rows_only_when_there_are_more(tmp_path):
    a = _run(tmp_path / "a")
    b = _run(tmp_path / "b", config={"seed": 1, "split": "time", "progress": True})
    result = main(a, b)
    assert len(result.config) == 2
    assert "more (--show N" not in report(result, limit=2)
    assert "  … and 1 more (--show N, or --out FILE)" in report(result, limit=1)


@pytest.mark.parametrize("damage", ["a folder", "a symlink loop"])
def test_cli_an_unreadable_file_is_a_usage_error_not_a_difference(
    tmp_path, capsys, damage
):
    """A run file that cannot be opened (a folder, a symlink loop) is status 2
    with the file named, not a traceback, whose status 1 reads as "differ"."""
    a = _run(tmp_path / "a")
    b = shutil.copytree(a, tmp_path / "b")
    (b / "trials.npz").unlink()
    if damage == "a folder":
        (b / "trials.npz").mkdir()
    else:
        (b / "trials.npz").symlink_to(b / "trials.npz")
    with pytest.raises(SystemExit) as exit_info:
        cli([str(a), str(b)])
    assert exit_info.value.code == 2
    assert "trials.npz" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("config", "env", "match"),
    [
        (None, [1], r"metrics.json: environment: expected an object"),
        ({"seed": 0, "refit": 3}, ENV, r"config.json: refit: expected an object"),
        ({"seed": 0, "refit": {"environment": 2}}, None,
         r"config.json: refit.environment: expected an object"),
    ],
)  # fmt: skip
def test_cli_a_run_file_of_the_wrong_shape_is_a_usage_error(
    tmp_path, capsys, config, env, match
):
    """Each was an AttributeError traceback, whose status 1 reads as "differ"."""
    a = _run(tmp_path / "a")
    b = _run(tmp_path / "b", config=config, env=env)
    with pytest.raises(SystemExit) as exit_info:
        cli([str(a), str(b)])
    assert exit_info.value.code == 2
    assert re.search(match, capsys.readouterr().err)
