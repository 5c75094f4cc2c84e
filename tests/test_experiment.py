"""Shared experiment utilities: intervals, thresholds, JSON artefacts."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import fnmatch
import importlib
import io
import json
import os
import pickle
import re
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from threadpoolctl import threadpool_info, threadpool_limits

import tasks
from hipmdp.data import lock_folder
from tasks import acrobot_swingup, cartpole_prediction, experiment
from tasks.experiment import (
    RUN_FILES,
    check_counts,
    check_folder_out,
    check_out_file,
    check_settings,
    count,
    describe_environment,
    environment,
    first_episode_within,
    flag_error,
    fmt_bounds,
    fmt_ci,
    margin_to_target,
    markdown_table,
    mean_ci,
    one_blas_thread,
    paired_difference,
    path_argument,
    pool_map,
    read_json_object,
    releases_run_folders,
    run_dir,
    to_jsonable,
    trial_seeds,
    with_added_fields,
    write_json,
    write_text,
    writes_metrics,
)


def test_mean_ci_matches_t_interval_and_covers_at_nominal_rate():
    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 2.0, size=(20, 400))
    ci = mean_ci(x, axis=0)
    low, high = stats.t.interval(
        0.95, df=19, loc=x[:, 0].mean(), scale=stats.sem(x[:, 0])
    )
    np.testing.assert_allclose([ci["low"][0], ci["high"][0]], [low, high])
    # 400 independent intervals: coverage ~ Binomial(400, .95)/400, sd ~ 0.011
    coverage = np.mean((ci["low"] <= 3.0) & (3.0 <= ci["high"]))
    assert abs(coverage - 0.95) < 4 * np.sqrt(0.95 * 0.05 / 400)


def test_mean_ci_counts_the_samples_along_its_axis():
    """Along axis 1, each row's t-interval: n (and so the t quantile's degrees
    of freedom and the standard error) is the length of that axis, not of the
    first one (3 rows of 5 samples: df 4, not 2)."""
    x = np.random.default_rng(5).normal(size=(3, 5))
    ci = mean_ci(x, axis=1)
    assert ci["n"] == 5
    for i, row in enumerate(x):
        low, high = stats.t.interval(0.95, df=4, loc=row.mean(), scale=stats.sem(row))
        np.testing.assert_allclose([ci["low"][i], ci["high"][i]], [low, high])


def test_an_older_config_reads_with_the_values_it_ran_with():
    old = {"seed": 0, "fit": {"n_sweeps": 60}}
    assert with_added_fields(old) == {
        "seed": 0,
        "split": "random",
        "methods": [],
        "fit": {
            "n_sweeps": 60,
            "periodic": False,
            "filter_weights": "prior_mean",
            "new_features": "paper",
        },
    }
    new = {"seed": 0, "split": "time", "methods": ["m"], "fit": {"periodic": True}}
    assert with_added_fields(new)["fit"]["periodic"] is True  # its own kept
    assert with_added_fields(new)["split"] == "time"
    assert old == {"seed": 0, "fit": {"n_sweeps": 60}}  # not changed in place


def test_mean_ci_of_one_sample_has_no_interval():
    """It was the point itself, printed as "+91.5 [91.5, 91.5]": a zero-width
    interval that reads as certainty (README's --trials 1 prediction runs). It
    says so without numpy's warnings (a standard deviation of ddof 1, a t
    quantile of df 0), which a --trials 1 run would print once per interval."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ci = mean_ci([2.5])
    assert ci["mean"] == 2.5 and ci["n"] == 1
    assert np.isnan(ci["low"]) and np.isnan(ci["high"])
    assert fmt_ci(ci, signed=True) == "+2.5 [no interval: one sample]"
    rows = mean_ci(np.array([[1.0, 2.0]]), axis=0)  # per column, one sample each
    assert rows["low"].shape == (2,) and np.isnan(rows["high"]).all()
    assert fmt_ci({"mean": 1.0, "low": None, "high": None}) == (
        "1 [no interval: one sample]"
    )  # as a metrics.json read back holds it
    assert fmt_ci(mean_ci([1.0, 3.0])) == "2 [-10.7, 14.7]"


@pytest.mark.parametrize("level", [0.0, 1.0, 95])
def test_mean_ci_refuses_a_level_outside_0_1(level):
    # 95 for 0.95 gave a NaN interval (the t quantile of 48): no error, no interval
    with pytest.raises(ValueError, match="level: expected a number in \\(0, 1\\)"):
        mean_ci([1.0, 2.0, 3.0], level=level)


def test_report_counts_are_singular_for_one():
    assert [count(n, "test setting") for n in (0, 1, 2)] == [
        "0 test settings", "1 test setting", "2 test settings"
    ]  # fmt: skip


def test_first_episode_within_uses_negative_returns():
    # returns are -steps: the true model ends at -100, so within 10% is >= -110
    curve = np.array([-500.0, -200.0, -111.0, -109.0, -100.0])
    assert first_episode_within(curve, target=-100.0) == 4
    assert first_episode_within(curve, target=-10.0) is None
    # on the threshold counts as within (returns are whole steps: ties happen)
    assert first_episode_within(np.array([-111.0, -110.0]), target=-100.0) == 2
    # the margin is the one given: within 12% is >= -112, within 0% is >= -100
    assert first_episode_within(curve, target=-100.0, margin=0.12) == 3
    assert first_episode_within(curve, target=-100.0, margin=0.0) == 5


def test_paired_difference_cancels_what_the_trials_share():
    # trial-to-trial spread 50, a constant gap of 7: unpaired intervals would be
    # ~±20 wide; paired, the shared part cancels and the gap is exact
    rng = np.random.default_rng(1)
    shared = rng.normal(-120.0, 50.0, size=(24, 5))
    d = paired_difference(shared + 7.0, shared)
    np.testing.assert_allclose(d["per_episode"]["mean"], 7.0)
    np.testing.assert_allclose(d["per_episode"]["low"], 7.0)
    np.testing.assert_allclose(d["per_episode"]["high"], 7.0)
    assert d["all_episodes"]["n"] == 24
    np.testing.assert_allclose(
        [d["all_episodes"]["low"], d["all_episodes"]["high"]], [7.0, 7.0]
    )


def test_paired_difference_is_the_t_interval_of_per_trial_mean_gaps():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(10, 4)), rng.normal(size=(10, 4))
    gaps = (a - b).mean(axis=1)
    low, high = stats.t.interval(0.95, df=9, loc=gaps.mean(), scale=stats.sem(gaps))
    d = paired_difference(a, b)["all_episodes"]
    np.testing.assert_allclose(
        [d["mean"], d["low"], d["high"]], [gaps.mean(), low, high]
    )


def test_paired_difference_with_the_setting_as_the_unit():
    """4 settings × 6 trials whose gaps are 10, 0, −10 and 20 with small trial
    noise: over the settings' means (n = 4) the interval is the t-interval of
    those 4 means. Over the 24 trials it treats them as independent: about
    √6 · t₃/t₂₃ ≈ 3.8 times narrower when the gap is all setting-to-setting."""
    rng = np.random.default_rng(3)
    effect = np.repeat([10.0, 0.0, -10.0, 20.0], 6)
    b = rng.normal(-120.0, 5.0, size=(24, 5))
    a = b + effect[:, None] + rng.normal(0.0, 1.0, size=(24, 5))
    groups = np.repeat(np.arange(4), 6)
    d = paired_difference(a, b, groups=groups)
    means = [(a - b)[groups == g].mean() for g in range(4)]
    low, high = stats.t.interval(0.95, df=3, loc=np.mean(means), scale=stats.sem(means))
    by = d["by_setting"]
    np.testing.assert_allclose(
        [by["mean"], by["low"], by["high"]], [np.mean(means), low, high]
    )
    assert by["n"] == 4 and by["mean"] == pytest.approx(d["all_episodes"]["mean"])
    assert by["high"] - by["low"] > 3 * (
        d["all_episodes"]["high"] - d["all_episodes"]["low"]
    )
    with pytest.raises(ValueError, match="groups: expected shape"):
        paired_difference(a, b, groups=groups[:-1])


def test_margin_to_target_is_the_curve_above_the_threshold_with_an_interval():
    rng = np.random.default_rng(4)
    true = rng.normal(-100.0, 10.0, size=(30, 5))
    other = rng.normal(-115.0, 10.0, size=(30, 5))
    d = margin_to_target(other, true, window=3)
    target = true[:, -3:].mean()
    # its mean is the curve minus the threshold first_episode_within compares with
    np.testing.assert_allclose(d["mean"], other.mean(0) - 1.1 * target)
    for e in range(5):
        assert (d["mean"][e] >= 0) == (
            first_episode_within(other.mean(0)[e : e + 1], target) == 1
        )
    # the interval is over trials of per-trial margins
    per_trial = other[:, 1] - 1.1 * true[:, -3:].mean(axis=1)
    low, high = stats.t.interval(
        0.95, df=29, loc=per_trial.mean(), scale=stats.sem(per_trial)
    )
    np.testing.assert_allclose([d["low"][1], d["high"][1]], [low, high])
    # another margin moves every trial's threshold by the margin's change times
    # |r_i| (the reference's returns are negative: |r_i| = -r_i)
    wider = margin_to_target(other, true, window=3, margin=0.25)
    np.testing.assert_allclose(
        wider["mean"] - d["mean"], 0.15 * np.abs(true[:, -3:].mean(axis=1)).mean()
    )
    with pytest.raises(ValueError, match="same trials"):
        margin_to_target(other[:5], true, window=3)
    # [:, -0:] is every episode: a window of 0 was the mean over all of them
    with pytest.raises(ValueError, match="window: expected >= 1, got 0"):
        margin_to_target(other, true, window=0)


def test_paired_difference_rejects_unpaired_shapes():
    with pytest.raises(ValueError, match="a, b: expected equal shapes"):
        paired_difference(np.zeros((3, 2)), np.zeros((4, 2)))
    # equal shapes of another rank are not (trials, episodes) either: 3-D ones
    # were averaged over their second axis as if it were the episodes
    for shape in [(6,), (3, 2, 4)]:
        with pytest.raises(ValueError, match=r"expected equal shapes \(trials, ep"):
            paired_difference(np.zeros(shape), np.zeros(shape))


def test_json_artefacts_are_plain_and_nan_free(tmp_path):
    obj = {"a": np.arange(3), "b": np.float64(np.nan), "c": (1, np.int64(2))}
    assert to_jsonable(obj) == {"a": [0, 1, 2], "b": None, "c": [1, 2]}
    path = write_json(tmp_path / "m.json", obj)
    assert json.loads(path.read_text())["a"] == [0, 1, 2]
    # numpy booleans, paths and numpy integer keys (none of which json takes)
    # become what reading the file back gives
    obj = {"ok": np.bool_(True), "out": Path("runs/x"), "per": {np.int64(3): 1.5}}
    plain = {"ok": True, "out": "runs/x", "per": {"3": 1.5}}
    assert to_jsonable(obj) == plain and type(to_jsonable(obj)["ok"]) is bool
    assert json.loads(write_json(tmp_path / "m.json", obj).read_text()) == plain


def test_a_write_removes_what_killed_writes_of_the_same_file_left(tmp_path):
    """A check (tasks.acrobot_horizon, say) killed while writing its JSON into a
    run folder left .horizon.json.<random>.tmp there for good: no later run or
    check removed it."""
    stale = [".m.json.k2x_9abc.tmp", ".m.json.00000000.tmp"]
    kept = [".m.json.backup.tmp", ".m.json.x.abcdefgh.tmp", ".n.json.abcdefgh.tmp",
            ".m.jsonXabcdefgh.tmp", "m.json.abcdefgh.tmp"]  # fmt: skip
    for name in stale + kept:
        (tmp_path / name).write_text('{"half')
    write_json(tmp_path / "m.json", {"a": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(kept + ["m.json"])
    write_text(tmp_path / "[r].md", "x")  # a name that is a glob pattern
    (tmp_path / ".[r].md.abcdefgh.tmp").write_text("half")
    write_text(tmp_path / "[r].md", "y")
    assert not (tmp_path / ".[r].md.abcdefgh.tmp").exists()


def test_fmt_ci_signs_a_positive_mean_only_when_asked():
    ci = {"mean": 1.5, "low": -0.25, "high": 3.0}
    assert fmt_ci(ci) == "1.5 [-0.25, 3]"
    assert fmt_ci(ci, signed=True) == "+1.5 [-0.25, 3]"
    assert fmt_ci({**ci, "mean": -1.5}, signed=True) == "-1.5 [-0.25, 3]"
    assert fmt_ci({**ci, "mean": 2e-4}, signed=True) == "+2.00e-04 [-0.25, 3]"
    # large values whole, not as 1.19e+03 (nor 999.6 as 1e+03)
    big = {"mean": 1187.1, "low": -324.4, "high": 999.6}
    assert fmt_ci(big, signed=True) == "+1187 [-324, 1000]"
    # zero, and small values from 1e-3 up, as plain decimals (scientific notation
    # starts below 1e-3: a 0 reads as 0, not 0.00e+00)
    small = {"mean": 0.0, "low": 0.001, "high": 0.005}
    assert fmt_ci(small) == "0 [0.001, 0.005]"
    # the bounds take the digits asked for, as the mean does
    five = {"mean": 1.234567, "low": 0.1234567, "high": 2.345678}
    assert fmt_ci(five, digits=5) == "1.2346 [0.12346, 2.3457]"


def test_fmt_bounds_give_no_interval_where_either_bound_is_missing():
    assert fmt_bounds(1.0, 2.0, str) == "[1.0, 2.0]"
    for low, high in [(np.nan, 2.0), (1.0, np.nan), (None, 2.0), (1.0, None)]:
        assert fmt_bounds(low, high, str) == "[no interval: one sample]"


def test_markdown_table_has_a_rule_of_as_many_columns_as_its_header():
    """GitHub renders a table only if the rule under the header has one cell per
    column."""
    assert markdown_table(["a", "b", "c"], [[1, 2.5, None]]) == (
        "| a | b | c |\n|---|---|---|\n| 1 | 2.5 | None |"
    )


def test_check_counts_names_the_first_value_below_one():
    check_counts(trials=1, states=3000)
    with pytest.raises(ValueError, match=r"^states: expected >= 1, got 0$"):
        check_counts(trials=2, states=0, real=-1)


def test_trial_seeds_are_setting_major_children_of_the_stream():
    seeds = trial_seeds(np.random.SeedSequence(7), 3, 4)
    assert [len(row) for row in seeds] == [4, 4, 4]
    for i, row in enumerate(seeds):
        for t, (entropy, spawn_key) in enumerate(row):
            assert entropy == 7 and spawn_key == (i * 4 + t,)


def test_trial_seeds_of_a_spawned_stream_keep_its_whole_spawn_key():
    """A run's trial stream is itself a child (``run_streams``: spawn key
    (3,)), so a trial's seed is a grandchild, (3, k): rebuilt from its value it
    draws as the child it stands for, and no trial's seed is one of the run's
    other streams (keeping only the last key, trial 0 would draw the batch
    data's stream, (0,))."""
    root = np.random.SeedSequence(7)
    streams = root.spawn(5)
    seeds = trial_seeds(streams[3], 2, 3)
    children = np.random.SeedSequence(7, spawn_key=(3,)).spawn(6)
    for k, (entropy, spawn_key) in enumerate(s for row in seeds for s in row):
        assert spawn_key == (3, k)
        rebuilt = np.random.SeedSequence(entropy, spawn_key=spawn_key)
        np.testing.assert_array_equal(
            rebuilt.generate_state(4), children[k].generate_state(4)
        )
        for stream in streams:
            assert not np.array_equal(
                rebuilt.generate_state(4), stream.generate_state(4)
            )


def _blas_threads(_=None) -> list[int]:
    return sorted(
        {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}
    )


@pytest.fixture
def two_blas_threads():
    """The caller's process as a user's may be: numpy imported before ``tasks``,
    so OpenBLAS runs several threads."""
    with threadpool_limits(limits=2):
        if _blas_threads() != [2]:
            pytest.skip("this BLAS cannot be set to two threads")
        yield


def test_one_blas_thread_limits_the_call_and_restores_the_callers(two_blas_threads):
    assert one_blas_thread(_blas_threads)() == [1]
    assert _blas_threads() == [2]


_INSTALLED: list[str] = []


def _install(value: str) -> None:
    _INSTALLED[:] = [value]


def _threads_and_installed(_) -> tuple[list[int], list[str]]:
    return _blas_threads(), list(_INSTALLED)


@pytest.mark.parametrize("workers", [1, 2])
def test_pool_jobs_run_one_blas_thread_after_the_initializer(two_blas_threads, workers):
    _INSTALLED.clear()  # forked workers would inherit what another test left
    got = pool_map(
        _threads_and_installed, [0, 1, 2], workers=workers, desc="", progress=False,
        initializer=_install, initargs=("models",),
    )  # fmt: skip
    assert got == [([1], ["models"])] * 3


def _mininterval(monkeypatch, seconds: float) -> None:
    """Bars drawn at most every ``seconds`` (as ``TQDM_MININTERVAL``, which
    tqdm reads as it is imported)."""
    import tqdm.auto

    bar = tqdm.auto.tqdm
    monkeypatch.setattr(
        tqdm.auto, "tqdm", lambda *a, **k: bar(*a, **k, mininterval=seconds)
    )


def test_the_bar_names_the_job_it_waits_for(capsys, monkeypatch):
    """A slow job (an added method's trial, say) stops the bar: the bar names it,
    and names nothing once every job is done (drawn at once: no mininterval)."""
    _mininterval(monkeypatch, 0)
    shown = []

    def job(name: str) -> str:
        shown.append(capsys.readouterr().err.rsplit("\r", 1)[-1])  # the bar now
        return name.upper()

    got = pool_map(job, ["a", "b", "c"], workers=1, desc="trials", progress=True,
                   label=lambda name: f"job {name}")  # fmt: skip
    assert got == ["A", "B", "C"]
    assert [("job a" in s, "job b" in s, "job c" in s) for s in shown] == [
        (True, False, False), (False, True, False), (False, False, True)
    ]  # fmt: skip
    last = capsys.readouterr().err.rsplit("\r", 1)[-1]
    assert "3/3" in last and "job" not in last


def _upper(name: str) -> str:
    return name.upper()


def test_the_bar_names_the_jobs_at_two_workers(capsys, monkeypatch):
    _mininterval(monkeypatch, 0)
    got = pool_map(_upper, ["a", "b", "c"], workers=2, desc="trials",
                   progress=True, label=lambda name: f"job {name}")  # fmt: skip
    err = capsys.readouterr().err
    assert got == ["A", "B", "C"]
    assert 0 <= err.index("job a") < err.index("job b") < err.index("job c")
    assert "job" not in err.rsplit("\r", 1)[-1]


def test_naming_the_job_keeps_to_the_bars_mininterval(capsys, monkeypatch):
    """``TQDM_MININTERVAL=60`` thins every bar to one update a minute (README):
    naming each job redrew the bar once per job, a line each in a log file."""
    _mininterval(monkeypatch, 60)
    got = pool_map(_upper, list("abcdefghij" * 20), workers=1, desc="trials",
                   progress=True, label=lambda name: f"job {name}")  # fmt: skip
    assert len(got) == 200
    assert capsys.readouterr().err.count("trials") <= 3  # opened, closed


def test_a_job_that_stops_the_bar_is_named_once_its_mininterval_has_passed(
    capsys, monkeypatch
):
    _mininterval(monkeypatch, 0.3)
    shown = []

    def job(name: str) -> str:
        if name == "slow":  # the bar was drawn for "fast" just now
            time.sleep(1.5)
            shown.append(capsys.readouterr().err.rsplit("\r", 1)[-1])
        return name

    pool_map(job, ["fast", "slow"], workers=1, desc="trials", progress=True,
             label=lambda name: f"job {name}")  # fmt: skip
    assert "job slow" in shown[0]


class TwoPartError(Exception):
    """An exception pickle cannot rebuild: __init__ takes two arguments and
    passes one on, as a user's own exception class might."""

    def __init__(self, code, detail):
        super().__init__(f"{code}: {detail}")


def _raise_two_part(job: int) -> int:
    if job == 2:
        err = TwoPartError(42, "no action 2 here")
        err.add_note("(setting 0, trial 2)")
        raise err
    return job


@pytest.mark.parametrize("workers", [1, 2])
def test_an_error_a_worker_cannot_send_back_keeps_its_message(workers):
    """At 2 workers such an error broke the pool (BrokenProcessPool, its message
    lost); it now arrives as a RuntimeError naming its type, message and note.
    In this process it is raised as it is; so it is from a worker where pickle
    can rebuild it after all (dask's distributed, once imported, installs
    tblib's pickling of exceptions, which forked workers inherit)."""
    try:
        pickle.loads(pickle.dumps(TwoPartError(42, "x")))
        rebuilt = True
    except TypeError:
        rebuilt = False
    expected = TwoPartError if workers == 1 or rebuilt else RuntimeError
    with pytest.raises(expected) as raised:
        pool_map(_raise_two_part, [0, 1, 2, 3], workers=workers, desc="",
                 progress=False)  # fmt: skip
    text = str(raised.value) + "".join(getattr(raised.value, "__notes__", []))
    assert "42: no action 2 here" in text and "(setting 0, trial 2)" in text
    if expected is RuntimeError:
        assert "test_experiment.TwoPartError raised in a worker" in text
    assert pool_map(_raise_two_part, [0, 1], workers=workers, desc="",
                    progress=False) == [0, 1]  # fmt: skip


def _fail_or_mark(job: tuple[str, str]) -> None:
    """Job ("fail", _) raises at once; ("mark", path) writes path, then takes
    0.5 s (so that running the queue takes 10 s at 2 workers)."""
    kind, path = job
    if kind == "fail":
        raise RuntimeError("the first job failed")
    Path(path).write_text("ran")
    time.sleep(0.5)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failed_job_stops_the_pool_without_running_the_queued_ones(tmp_path, workers):
    """40 jobs of 0.5 s queued behind one that fails: the pool raises its error
    and drops the queue (were the queue run, each of the 40 would write its
    file). ``Executor.map`` cancels its pending jobs when its result fails;
    ``pool_map``'s own cancel is for an interrupt outside it (untested here)."""
    marks = [("mark", str(tmp_path / f"{i}.ran")) for i in range(40)]
    with pytest.raises(RuntimeError, match="the first job failed"):
        pool_map(
            _fail_or_mark, [("fail", ""), *marks], workers=workers, desc="",
            progress=False,
        )  # fmt: skip
    ran = len(list(tmp_path.glob("*.ran")))
    # the jobs already handed to a worker ran (about 2 per worker); the queue
    # did not. The margin of 20 jobs is 5 s of work at 2 workers: only a main
    # process that takes that long to see the failed result (a machine loaded far
    # beyond the suite's two cores) could run that many (at 0.1 s a job the
    # margin was 1 s, near enough to scheduling delays to fail on a busy machine)
    assert ran <= len(marks) // 2
    if workers == 1:
        assert ran == 0


def checkout_env() -> dict[str, str]:
    """The environment for a script run in a subprocess, with this checkout's
    ``tasks`` and ``hipmdp`` first on its path: a script's folder, not the
    current one, heads its sys.path, so without this it imports the installed
    ones (another checkout's)."""
    source = str(Path(tasks.__file__).resolve().parents[1])
    path = os.pathsep.join(filter(None, [source, os.environ.get("PYTHONPATH")]))
    return {**os.environ, "PYTHONPATH": path}


_OWNERS = {
    "pool_map": """
import os, signal, sys, threading, time
from pathlib import Path

from tasks.experiment import pool_map

marks = Path(sys.argv[1])


def job(i):  # each worker's first job marks its pid, then runs for a minute
    (marks / str(os.getpid())).write_text("")
    time.sleep(60)


def die():  # once both workers are in a job: SIGKILL, no shutdown of the pool
    while len(list(marks.iterdir())) < 2:
        time.sleep(0.02)
    os.kill(os.getpid(), signal.SIGKILL)


if __name__ == "__main__":
    threading.Thread(target=die, daemon=True).start()
    pool_map(job, [0, 1, 2, 3], workers=2, desc="", progress=False)
""",
    # tasks.generate's pool (forkserver): ask for pids until both workers have
    # answered, give each a minute's job, SIGKILL
    "generate": """
import os, signal, sys, time
from pathlib import Path

from tasks.generate import executor_for

if __name__ == "__main__":
    with executor_for(2, None) as pool:
        pids = set()
        while len(pids) < 2:
            pids |= {f.result() for f in [pool.submit(os.getpid) for _ in range(4)]}
        for pid in pids:
            (Path(sys.argv[1]) / str(pid)).write_text("")
        jobs = [pool.submit(time.sleep, 60) for _ in range(4)]
        time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGKILL)
""",
}


def _running(pid: int) -> bool:
    """Whether ``pid`` is a live process (a zombie, which a container's first
    process may never reap, is not)."""
    return _state(pid) not in (None, "Z")


def _state(pid: int) -> str | None:
    """The state of process ``pid`` (``/proc``: ``R``, ``S``, ``Z``...), None if
    there is none."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return None


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
@pytest.mark.parametrize("reaped", [True, False], ids=["reaped", "zombie"])
@pytest.mark.parametrize("pool", list(_OWNERS))
def test_pool_workers_end_when_their_owner_is_killed(tmp_path, pool, reaped):
    """An owner of a pool (pool_map's, or tasks.generate's forkserver pool)
    killed by SIGKILL mid-job, with no shutdown, left its two workers running
    for ever: after their job, they wait on a pipe whose writing end they hold
    themselves. exit_with ends them within its 0.5 s polls, once the owner is
    reaped, and while it is a zombie too: a killed owner stays one until its
    parent waits for it, and ``os.kill(owner, 0)`` succeeds on a zombie (a
    parent reading the owner's output to its end first, as
    ``subprocess.run(capture_output=True)`` does, waited for ever on a pipe the
    forkserver's workers still held). The bounds of 60 s (the owner's death)
    and 30 s (the workers'), against jobs of 60 s, only wait out a loaded
    machine."""

    script, marks = tmp_path / "owner.py", tmp_path / "marks"
    script.write_text(_OWNERS[pool])
    marks.mkdir()
    owner = subprocess.Popen(
        [sys.executable, str(script), str(marks)], env=checkout_env()
    )
    try:  # the workers marked are killed whatever happens, a timeout too
        if reaped:
            assert owner.wait(timeout=60) == -9
        else:
            deadline = time.monotonic() + 60
            while _state(owner.pid) != "Z" and time.monotonic() < deadline:
                time.sleep(0.05)
            assert _state(owner.pid) == "Z"  # killed, and not waited for
        workers = [int(p.name) for p in marks.iterdir()]
        assert len(workers) == 2
        deadline = time.monotonic() + 30
        while any(map(_running, workers)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(map(_running, workers))
        assert owner.wait(timeout=60) == -9  # the zombie too: its own SIGKILL
    finally:
        for pid in filter(_running, [int(p.name) for p in marks.iterdir()]):
            os.kill(pid, 9)
        owner.kill()  # if it hangs; nothing if it is dead
        owner.wait(timeout=60)


@pytest.mark.parametrize(
    "entry",
    [
        "tasks.acrobot_swingup:main", "tasks.cartpole_prediction:main",
        "tasks.acrobot_identified:main", "tasks.acrobot_energy:main",
        "tasks.acrobot_horizon:main", "tasks.acrobot_batch_errors:main",
        "tasks.acrobot_refit:main", "tasks.generate:run_shard",
    ],
)  # fmt: skip
def test_every_entry_point_that_computes_results_is_limited(entry):
    # the limit's behaviour is tested above and in the swing-up smoke test; this
    # checks that every entry point that computes results carries it
    module, name = entry.split(":")
    assert getattr(importlib.import_module(module), name).one_blas_thread


def test_environment_is_plain_json_naming_versions_blas_and_commit():
    env = json.loads(json.dumps(environment()))
    assert env["packages"]["numpy"] == np.__version__
    assert env["blas"] and all(b["num_threads"] >= 1 for b in env["blas"])
    commit = env["git_commit"]
    if (Path(tasks.__file__).parent.parent / ".git").exists():  # CI's clone too
        assert re.fullmatch(r"[0-9a-f]{40}(\+dirty)?", commit)
    else:  # an installed copy names no commit
        assert commit is None
    line = describe_environment(env)
    assert f"numpy {np.__version__}" in line and env["blas"][0]["version"] in line
    assert describe_environment(None) == ""


def test_run_dir_replaces_the_previous_run_of_the_same_experiment(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    write_json(out / "config.json", {"name": "exp"})
    for name in ("metrics.json", "fit_run3.npz", "identified.json"):
        (out / name).write_text("old")
    # a killed run's temporaries, of its artefacts and of another file
    for name in (".fit_run1.npz.x1.tmp", ".metrics.json.y2.tmp", ".notes.txt.z.tmp"):
        (out / name).write_text("partial")
    assert run_dir(out, "exp", ("config.json", "metrics.json", "fit_run*.npz")) == out
    # the experiment's own files are gone (a shorter run cannot mix with them),
    # with their temporaries; a check's file on the old run stays, and is named
    left = sorted(f.name for f in out.iterdir())
    assert left == [".notes.txt.z.tmp", "identified.json"]
    assert capsys.readouterr().err == (
        f"{out}: replaced the previous run's files; kept identified.json, which "
        "this run does not write (any made from the previous run describe that "
        "run, not this one)\n"
    )


def test_run_dir_in_a_folder_without_a_previous_run_says_nothing(tmp_path, capsys):
    """Other files in a folder that holds no run: nothing is replaced, so the
    message that the previous run's files were replaced would be false."""
    (tmp_path / "notes.txt").write_text("mine")
    assert run_dir(tmp_path, "exp", ("config.json", "metrics.json")) == tmp_path
    assert (tmp_path / "notes.txt").read_text() == "mine"
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("config", [None, {"name": "other"}, {"seed": 0}, [1]])
def test_run_dir_refuses_a_folder_that_is_not_its_run(tmp_path, config):
    """A folder holding files named like the artefacts (a user's report.md, or
    another experiment's run, or a config.json of no run: no name, not an
    object) is not deleted from: nothing is touched."""
    (tmp_path / "report.md").write_text("mine")
    if config is not None:
        write_json(tmp_path / "config.json", config)
    with pytest.raises(ValueError, match="^out: .* choose a new or empty folder"):
        run_dir(tmp_path, "exp", ("config.json", "report.md"))
    assert (tmp_path / "report.md").read_text() == "mine"
    file = tmp_path / "report.md"
    with pytest.raises(ValueError, match="exists and is not a folder"):
        run_dir(file, "exp")


@contextlib.contextmanager
def holding(folder: Path):
    """Another process holding ``folder``'s run lock for the ``with`` block
    (until its stdin closes; ``with proc`` closes its pipes and waits for it)."""

    code = (
        "import sys; from hipmdp.data import lock_folder; "
        f"fd = lock_folder({str(folder)!r}); print('held', flush=True); "
        "sys.stdin.read()"
    )
    with subprocess.Popen(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        text=True,
    ) as proc:  # fmt: skip
        assert proc.stdout.readline().strip() == "held"
        yield


def test_a_run_folder_another_run_writes_to_is_refused(tmp_path):
    """Two runs into one folder at once left one run's config beside the
    other's metrics: while another process holds the folder, the command line's
    check and run_dir refuse it, before anything is deleted; once it ends, it is
    taken. In one process, a main's lock is released when the main ends."""
    out = tmp_path / "run"
    out.mkdir()
    write_json(out / "config.json", {"name": "exp"})
    (out / "metrics.json").write_text("the other run's")
    with holding(out):
        for call in (experiment.check_out, run_dir):
            with pytest.raises(ValueError, match="^out: another run is writing to"):
                call(out, "exp", ("config.json", "metrics.json"))
        assert (out / "metrics.json").read_text() == "the other run's"

    @releases_run_folders
    def main():
        run_dir(out, "exp", ("config.json", "metrics.json"))
        run_dir(out, "exp", ("config.json", "metrics.json"))  # its own: taken
        with pytest.raises(BlockingIOError):  # held while the main runs
            os.close(lock_folder(out, wait=False))

    main()
    os.close(lock_folder(out, wait=False))  # and released when it ends


def test_a_generated_datasets_folder_is_no_run_folder(tmp_path):
    """An experiment wrote its files beside a dataset's manifest and shards."""
    (tmp_path / "manifest.json").write_text("{}")
    with pytest.raises(ValueError, match="holds a tasks.generate dataset"):
        run_dir(tmp_path, "exp", ("config.json",))
    assert sorted(f.name for f in tmp_path.iterdir()) == ["manifest.json"]


@pytest.mark.parametrize("make", [run_dir, lambda out, *a: check_out_file(out)])
def test_outputs_that_cannot_be_written_are_refused_before_any_work(tmp_path, make):
    """An empty path (the working directory, as a Path) and a path through a
    file; nothing is made. A missing parent folder is fine: it is made."""
    file = tmp_path / "file"
    file.write_text("mine")
    for blank in ("", " "):  # Path(" ") would be a folder named by a space
        with pytest.raises(
            ValueError, match=f"^out: expected a (folder|file) path, got '{blank}'"
        ):
            make(blank, "exp")
    with pytest.raises(ValueError, match=f"^out: {file} is not a folder, so"):
        make(file / "sub" / "deeper", "exp")
    assert file.read_text() == "mine" and sorted(tmp_path.iterdir()) == [file]
    make(tmp_path / "new" / "out.json", "exp")


@pytest.mark.skipif(not Path("/sys").is_dir(), reason="needs Linux's sysfs")
@pytest.mark.parametrize("make", [run_dir, lambda out, *a: check_out_file(out)])
def test_an_output_in_a_folder_that_takes_no_files_is_refused_before_any_work(make):
    """sysfs takes no new files, even from root (for whom a read-only mode bit
    would not do): a check's output there failed only after all its work, as a
    traceback from the temporary file's creation."""
    with pytest.raises(ValueError, match="^out: cannot write in /sys"):
        make("/sys/hipmdp_out", "exp")
    with pytest.raises(ValueError, match="^--out: cannot write in /sys"):
        check_folder_out(Path("/sys/hipmdp_out"), "--out")


@pytest.mark.parametrize("make", [run_dir, lambda out, *a: check_out_file(out)])
def test_an_output_through_a_symlink_loop_or_to_nowhere_is_refused_by_name(
    tmp_path, make
):
    """A folder path through a symbolic link loop was a RuntimeError traceback
    (``tasks.generate``: "File exists", after its planning); a link to a
    missing place was "File exists". Both are named before any work, and
    nothing is made."""
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    (tmp_path / "gone").symlink_to(tmp_path / "missing")
    loop = "cannot be resolved .*a symbolic link on it leads back to itself"
    for out in (tmp_path / "a", tmp_path / "a" / "sub"):
        with pytest.raises(ValueError, match=rf"^out: {re.escape(str(out))} {loop}"):
            make(out, "exp")
    where = re.escape(str(tmp_path))
    gone = rf"^out: {where}/gone is a symbolic link to {where}/missing, which"
    with pytest.raises(ValueError, match=gone):
        make(tmp_path / "gone", "exp")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b", "gone"]
    with pytest.raises(ValueError, match="^--out: .* leads back to itself"):
        check_folder_out(tmp_path / "a", "--out")


def test_an_existing_folder_that_takes_no_files_is_refused_though_its_parent_does(
    tmp_path, monkeypatch
):
    """A folder that exists is probed itself, not its parent: a read-only
    folder (a read-only mount point, say) in a writable one would otherwise
    pass, and the run fail at its first file. File systems that refuse files
    even to root are not at hand in a test, so the probe's file creation is
    refused for that one folder."""
    import errno
    import tempfile

    ro = tmp_path / "ro"
    ro.mkdir()
    real = tempfile.TemporaryFile

    def refusing(*args, dir=None, **kwargs):
        if dir is not None and Path(dir) == ro:
            raise OSError(errno.EROFS, "Read-only file system")
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", refusing)
    with pytest.raises(
        ValueError, match=f"^out: cannot write in {re.escape(str(ro))} "
    ):
        run_dir(ro, "exp")
    assert run_dir(tmp_path / "rw", "exp") == tmp_path / "rw"


def test_a_check_may_not_write_over_its_runs_files(tmp_path):
    """``--out RUN/config.json`` replaced the run's config with the check's JSON,
    and the run was no longer a run."""
    run, other = tmp_path / "run", tmp_path / "other"
    run.mkdir()
    for name in ("config.json", "metrics.json", "report.md", "batch.npz", "w.png"):
        with pytest.raises(ValueError, match=f"^out: .*{name} is one of the run"):
            check_out_file(run / name, [other, run])
        with pytest.raises(ValueError, match="is one of the run"):  # by another path
            check_out_file(tmp_path / "other" / ".." / "run" / name, [run])
    # a check's own file beside the run's, and the same names elsewhere, are fine
    assert check_out_file(run / "identified.json", [run]) == run / "identified.json"
    assert check_out_file(other / "config.json", [run]) == other / "config.json"
    # every experiment's artefacts are run files
    for module in (acrobot_swingup, cartpole_prediction):
        for artefact in module.ARTEFACTS:
            assert any(fnmatch.fnmatch(artefact, p) for p in RUN_FILES), artefact


def _mark_pid(folder: str) -> None:
    (Path(folder) / str(os.getpid())).touch()


def test_the_pool_starts_no_more_workers_than_jobs(tmp_path):
    """``--workers 300`` started 300 processes for 16 jobs (a pool starts all of
    its workers at once): each worker's initializer marks its process."""
    out = pool_map(
        abs, [-1, -2], workers=8, desc="", progress=False, initializer=_mark_pid,
        initargs=(str(tmp_path),),
    )  # fmt: skip
    assert out == [1, 2] and len(list(tmp_path.iterdir())) == 2
    for f in tmp_path.iterdir():
        f.unlink()
    assert pool_map(abs, [-3], workers=8, desc="", progress=False) == [3]
    assert pool_map(abs, [], workers=8, desc="", progress=False) == []


def test_a_file_output_is_not_a_folder():
    with pytest.raises(ValueError, match="is a folder; expected a file path"):
        check_out_file(Path(__file__).parent)
    with pytest.raises(argparse.ArgumentTypeError, match="expected a path, got ' '"):
        path_argument(" ")
    assert path_argument("runs/x") == Path("runs/x")


def test_run_or_exit_reports_bad_input_as_usage_and_lets_later_errors_through(
    capsys,
):
    import argparse

    from tasks.experiment import inputs_checked, run_or_exit

    parser = argparse.ArgumentParser(prog="check")

    def bad_input():
        raise FileNotFoundError("run: x has no config.json")

    def failed_work():
        inputs_checked()
        raise ValueError("a bug, an hour in")

    with pytest.raises(SystemExit) as stopped:
        run_or_exit(parser, bad_input)
    assert stopped.value.code == 2
    assert "check: error: run: x has no config.json" in capsys.readouterr().err
    with pytest.raises(ValueError, match="a bug, an hour in"):
        run_or_exit(parser, failed_work)
    # the mark is the call's own: the next call starts unchecked again
    with pytest.raises(SystemExit):
        run_or_exit(parser, bad_input)
    assert run_or_exit(parser, lambda: 7) == 7


def test_paired_difference_takes_its_level_in_every_interval():
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(8, 3)), rng.normal(size=(8, 3))
    groups = np.repeat(np.arange(4), 2)
    d = paired_difference(a, b, level=0.5, groups=groups)
    diff = a - b
    means = [diff[groups == g].mean() for g in range(4)]
    expected = {
        "all_episodes": mean_ci(diff.mean(axis=1), level=0.5),
        "per_episode": mean_ci(diff, axis=0, level=0.5),
        "by_setting": mean_ci(means, level=0.5),
    }
    for key, ci in expected.items():
        for bound in ("mean", "low", "high"):
            np.testing.assert_allclose(d[key][bound], ci[bound], err_msg=key)
        wide = paired_difference(a, b, groups=groups)[key]
        assert np.all(wide["high"] - wide["low"] > d[key]["high"] - d[key]["low"])


class _InterruptAfterTheFirst:
    """A progress bar through which Ctrl-C arrives after the first result."""

    disable = True

    def __init__(self, *args, **kwargs):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n=1):
        raise KeyboardInterrupt


def test_an_interrupt_drops_the_queued_jobs(tmp_path, monkeypatch):
    """Ctrl-C while results arrive: pool_map cancels the queue before it waits
    for the running jobs (a plain ``with`` pool would run all 40, 10 s)."""
    import tqdm.auto

    monkeypatch.setattr(tqdm.auto, "tqdm", _InterruptAfterTheFirst)
    marks = [("mark", str(tmp_path / f"{i}.ran")) for i in range(40)]
    with pytest.raises(KeyboardInterrupt):
        pool_map(_fail_or_mark, marks, workers=2, desc="", progress=False)
    assert len(list(tmp_path.glob("*.ran"))) <= len(marks) // 2


def test_a_write_is_flushed_to_disk_before_its_rename_and_the_rename_after(
    tmp_path, monkeypatch
):
    """atomic_write fsyncs the temporary file before renaming it over the
    target, then the folder, so that a power cut leaves the old or the new
    file, never an empty one."""
    import os
    import stat

    real, synced = os.fsync, []
    target = tmp_path / "metrics.json"

    def spying(fd):
        st = os.fstat(fd)
        synced.append((stat.S_ISDIR(st.st_mode), st.st_ino, target.exists()))
        return real(fd)

    monkeypatch.setattr(os, "fsync", spying)
    write_json(target, {"a": 1})
    assert synced == [
        (False, target.stat().st_ino, False),  # the data, before the rename
        (True, tmp_path.stat().st_ino, True),  # the folder's entry, after it
    ]


def test_git_commit_marks_uncommitted_changes_and_ignores_an_enclosing_checkout(
    monkeypatch,
):
    """HEAD, with +dirty when tracked files changed; None when the code's
    folder is not the top of a checkout (an install in another project's
    .venv)."""

    from tasks import experiment

    root = Path(experiment.__file__).resolve().parent.parent
    answers = {"rev-parse": {"--show-toplevel": str(root), "HEAD": "a" * 40}}
    run = subprocess.run

    def git(args, **kwargs):
        if args[0] != "git":  # platform's own calls
            return run(args, **kwargs)
        command, rest = args[4], args[5:]
        out = answers[command] if command == "status" else answers[command][rest[0]]
        return subprocess.CompletedProcess(args, 0, stdout=out + "\n", stderr="")

    monkeypatch.setattr(experiment.subprocess, "run", git)
    answers["status"] = ""
    assert experiment._git_commit() == "a" * 40
    answers["status"] = " M tasks/experiment.py"
    assert experiment._git_commit() == "a" * 40 + "+dirty"
    env = environment()
    assert env["git_commit"] == "a" * 40 + "+dirty"
    assert "code aaaaaaaaaaaa+dirty." in describe_environment(env)
    answers["rev-parse"]["--show-toplevel"] = str(root.parent)
    assert experiment._git_commit() is None


def test_check_settings_wants_two_training_pairs_and_pairs_only():
    """Settings are (mass, mass) pairs, each checked by the domain's ``make``;
    the latent model needs at least two training instances to vary across."""

    @dataclasses.dataclass(frozen=True)
    class Config:
        train: tuple = ((1, 2), (3, 4))
        test: tuple = ((5, 6),)

    config = Config()
    checked = []
    check_settings(config, "train", "test", lambda *p: checked.append(p), "mass")
    assert config.train == ((1.0, 2.0), (3.0, 4.0)) and config.test == ((5.0, 6.0),)
    assert checked == [(1.0, 2.0), (3.0, 4.0), (5.0, 6.0)]
    for train, message in [
        (((1, 2),), "^train: expected at least two settings$"),
        (((1, 2), (3, 4, 5)), r"^train: expected mass pairs, got \(\(1.0, 2.0\), \(3"),
        ((), r"^train: expected mass pairs, got \(\)$"),
    ]:
        with pytest.raises(ValueError, match=message):
            check_settings(
                Config(train=train), "train", "test", lambda *p: None, "mass"
            )
    with pytest.raises(ValueError, match=r"^test: expected mass pairs"):
        check_settings(Config(test=((1,),)), "train", "test", lambda *p: None, "mass")


def test_flag_error_leads_with_the_flag_only_where_a_flag_sets_the_field():
    assert flag_error(ValueError("n_trials: expected >= 1, got 0")) == (
        "--trials (n_trials): expected >= 1, got 0"
    )
    for text in ("test_masses: expected mass pairs, got ()", "no field: here", "x"):
        assert flag_error(ValueError(text)) == text


@pytest.mark.parametrize(
    "text, kind",
    [("[1]", "an array"), ('"a"', "a string"), ("true", "a boolean"),
     ("3", "a number"), ("null", "null")],
)  # fmt: skip
def test_read_json_object_refuses_other_json_naming_the_file(tmp_path, text, kind):
    path = tmp_path / "config.json"
    path.write_text(text)
    with pytest.raises(
        ValueError,
        match=f"^{re.escape(str(path))}: expected a JSON object .* got {kind}$",
    ):
        read_json_object(path)
    path.write_text('{"seed": 0')  # cut short
    with pytest.raises(ValueError, match=f"^{re.escape(str(path))}: not a JSON file"):
        read_json_object(path)
    path.write_text('{"seed": 0}')
    assert read_json_object(path) == {"seed": 0}


def test_metrics_are_written_even_if_an_artefact_fails(tmp_path):
    """A figure that fails after an hour's run must not lose its numbers:
    metrics.json is written, with the timings and the machine, and the error
    still raised."""
    metrics, seconds = {"returns": [1.0]}, {"fit": 2.0}
    with pytest.raises(RuntimeError, match="no display"):
        with writes_metrics(
            tmp_path, metrics, seconds, time.perf_counter(), {"cpu": "x"}
        ):
            raise RuntimeError("no display")
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["returns"] == [1.0] and written["environment"] == {"cpu": "x"}
    assert set(written["seconds"]) == {"fit", "artefacts", "total"}
    assert written["seconds"]["total"] >= written["seconds"]["artefacts"] >= 0


def test_seed_zero_is_a_seed():
    """--seed takes every integer >= 0, 0 (the default) included."""
    from tasks.experiment import seed_argument

    assert seed_argument("0") == 0
    with pytest.raises(argparse.ArgumentTypeError, match=">= 0, got -1"):
        seed_argument("-1")


def _exit_status(module, argv: list[str]):
    """The exit status of ``module.cli(argv)``; a KeyboardInterrupt that escapes
    it (it would end pytest's session) as "KeyboardInterrupt"."""
    try:
        module.cli(argv)
    except SystemExit as exited:
        return exited.code
    except KeyboardInterrupt:
        return "KeyboardInterrupt"
    return 0


@pytest.mark.parametrize(
    "module", [acrobot_swingup, cartpole_prediction], ids=lambda m: m.__name__
)
@pytest.mark.parametrize(
    ("stop", "status", "how"),
    [("ctrl-c", 130, "interrupted (Ctrl-C)"), ("sigterm", 143, "terminated (SIGTERM)")],
)
def test_a_stopped_experiment_says_what_its_folder_holds(
    module, stop, status, how, tmp_path, monkeypatch, capsys
):
    """Ctrl-C or SIGTERM (a batch system's stop) while an experiment runs: status
    130 or 143 and one line naming the files the run finished (the previous
    run's, replaced, and a file it does not write are not named), not a
    traceback (Ctrl-C) or silence (SIGTERM), nor the temporary file of one it
    was writing. The SIGTERM handler is put back."""
    import signal

    out = tmp_path / "run"
    out.mkdir()
    (out / "check.json").write_text("{}")  # kept from before: not this run's
    old = time.time() - 3600
    os.utime(out / "check.json", (old, old))

    def stopped_main(config, folder):
        write_json(out / "config.json", {"name": config.name})
        write_json(out / "batch.npz", {})
        (out / ".metrics.json.k2x9abcd.tmp").write_text('{"half')  # being written
        if stop == "ctrl-c":
            raise KeyboardInterrupt
        if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:  # would end pytest
            raise AssertionError("no SIGTERM handler during the run")
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the signal's handler raises before this ends
        raise AssertionError("SIGTERM was not handled")

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(module, "main", stopped_main)
    assert _exit_status(module, ["--no-record", "--out", str(out)]) == status
    assert signal.getsignal(signal.SIGTERM) == before
    assert capsys.readouterr().err == (
        f"python -m {module.__name__}: {how} before the run ended: {out} holds the "
        "files it finished (batch.npz, config.json) and no metrics.json; the next "
        "run into it replaces them\n"
    )


def test_an_experiment_stopped_before_writing_says_so(tmp_path, monkeypatch, capsys):
    """A stop before the run's config.json is written: the folder is as it was
    (a previous run's files, left)."""
    out = tmp_path / "run"
    out.mkdir()
    write_json(out / "config.json", {"name": "cartpole_prediction"})
    old = time.time() - 3600
    os.utime(out / "config.json", (old, old))

    def stopped_main(config, folder):
        raise KeyboardInterrupt

    monkeypatch.setattr(cartpole_prediction, "main", stopped_main)
    assert _exit_status(cartpole_prediction, ["--no-record", "--out", str(out)]) == 130
    assert capsys.readouterr().err == (
        "python -m tasks.cartpole_prediction: interrupted (Ctrl-C) before the run "
        f"ended: it had written nothing to {out}\n"
    )

    def stopped_after_run_dir(config, folder):  # it deletes the previous files
        (out / "config.json").unlink()
        raise KeyboardInterrupt

    monkeypatch.setattr(cartpole_prediction, "main", stopped_after_run_dir)
    with contextlib.suppress(SystemExit, KeyboardInterrupt):
        cartpole_prediction.cli(["--no-record", "--out", str(out)])
    assert capsys.readouterr().err.endswith(
        f"it had written nothing to {out}, after removing the previous run's "
        "(config.json)\n"
    )


def test_a_caller_s_own_sigterm_handler_is_left_alone(tmp_path, monkeypatch):
    """An experiment run under a caller that handles SIGTERM itself: the caller's
    handler stays in place during the run."""
    import signal

    seen = []

    def callers(signum, frame):
        pass

    def main(config, folder):
        seen.append(signal.getsignal(signal.SIGTERM))
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, callers)
    try:
        monkeypatch.setattr(cartpole_prediction, "main", main)
        with contextlib.suppress(SystemExit, KeyboardInterrupt):
            cartpole_prediction.cli(["--no-record", "--out", str(tmp_path / "r")])
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert seen == [callers]


def test_help_gives_each_presets_default_and_plain_text(capsys):
    """``--help`` names the defaults a preset sets (each preset's when they
    differ, the default preset first) and shows the module docstring without
    reStructuredText's markup (``x``, :func:`x`)."""
    for module, wanted in [
        (acrobot_swingup, ["trials per setting (default quick 12, paper 30)",
                           "real episodes (default quick 6, paper 20)",
                           "worker processes (default: 2)"]),
        (cartpole_prediction, ["HiP-MDP fits (default quick 2, paper 5)"]),
    ]:  # fmt: skip
        with pytest.raises(SystemExit):
            module.cli(["--help"])
        text = " ".join(capsys.readouterr().out.split())  # argparse's wrapping undone
        for line in wanted:
            assert line in text
        assert "``" not in text and ":func:" not in text
        assert "Writes runs/<name>/:" in text
    assert experiment.plain_text("``a`` and :func:`b` or :class:`~c.D`") == (
        "a and b or c.D"
    )
    assert experiment.plain_text("`--vary NAME` (`x`)\n`y`") == "--vary NAME (x)\ny"


#: Every command line: (module, its entry function, which `python -m module` calls).
ENTRY_POINTS = [
    *[(f"tasks.{name}", "cli") for name in (
        "acrobot_batch_errors", "acrobot_energy", "acrobot_horizon",
        "acrobot_identified", "acrobot_refit", "acrobot_swingup",
        "cartpole_prediction", "compare_runs", "seed_spread",
    )],
    ("tasks.generate", "main"), ("tasks.minari_export", "main"),
    *[(f"benchmarks.{name}", "main") for name in (
        "control", "generate", "model", "simulation",
    )],
    ("benchmarks.sampler", "cli"),
]  # fmt: skip


def test_every_command_line_is_an_entry_point():
    """ENTRY_POINTS lists every module with a ``__main__`` block (which calls
    the entry function)."""
    root = Path(tasks.__file__).resolve().parents[1]
    found = set()
    for folder in ("tasks", "benchmarks"):
        for path in (root / folder).glob("*.py"):
            text = path.read_text(encoding="utf-8")
            if 'if __name__ == "__main__":' in text:
                found.add(f"{folder}.{path.stem}")
    assert found == {module for module, _ in ENTRY_POINTS}


@pytest.mark.parametrize(("module", "entry"), ENTRY_POINTS)
def test_help_prints_where_the_terminal_cannot_show_every_character(
    monkeypatch, module, entry
):
    """With an ASCII stdout (``PYTHONIOENCODING=ascii``; a Latin-1 locale lacks
    λ, σ and − too), ``--help`` raised UnicodeEncodeError in seven of the
    sixteen commands, and so did the closing summary of a run; every command
    line now writes such characters as escapes (``\\u03bb``)."""
    out, err = io.BytesIO(), io.BytesIO()
    monkeypatch.setattr(sys, "stdout", io.TextIOWrapper(out, encoding="ascii"))
    monkeypatch.setattr(sys, "stderr", io.TextIOWrapper(err, encoding="ascii"))
    with pytest.raises(SystemExit) as stopped:
        getattr(importlib.import_module(module), entry)(["--help"])
    sys.stdout.flush()
    assert stopped.value.code == 0
    assert out.getvalue().decode("ascii").startswith("usage: python -m " + module)
    # nine of them print no such character in their help, but may later (the
    # reports' "±" and "…"): the stream is set for them all
    assert (sys.stdout.errors, sys.stderr.errors) == ("backslashreplace",) * 2


def test_printable_output_escapes_only_what_the_stream_cannot_encode():
    """An ASCII stream writes λ as an escape, whether its errors were strict or
    surrogateescape; a UTF-8 stream, and one that is not a text file (no
    ``reconfigure``), are left as they were."""
    ascii_out, escape_out, utf8_out = io.BytesIO(), io.BytesIO(), io.BytesIO()
    streams = (
        io.TextIOWrapper(ascii_out, encoding="ascii"),
        # the C locale without UTF-8 mode: surrogateescape raises on λ too
        io.TextIOWrapper(escape_out, encoding="ascii", errors="surrogateescape"),
        io.TextIOWrapper(utf8_out, encoding="utf-8"),
    )
    for stream in streams:
        with contextlib.redirect_stdout(stream):
            experiment.printable_output()
            print("λ = 1", end="")
        stream.flush()
    assert ascii_out.getvalue() == escape_out.getvalue() == b"\\u03bb = 1"
    assert (utf8_out.getvalue(), streams[2].errors) == ("λ = 1".encode(), "strict")
    with contextlib.redirect_stdout(io.StringIO()):  # no reconfigure: no error
        experiment.printable_output()


def test_the_run_time_line_names_every_part_and_the_rest():
    """Every timed part of half a second or more, underscores as spaces, in the
    order measured; what no part timed as "the rest" (the report's parts did
    not add up to its total: the average model and the artefacts were left
    out)."""
    seconds = {"batch_data": 26.4, "added_methods": 0.0004, "fit": 23.6,
               "average_model": 14.2, "artefacts": 4.4, "total": 68.8}  # fmt: skip
    assert experiment.run_time_line(seconds) == (
        "Run time: 69 s (batch data 26 s, fit 24 s, average model 14 s, artefacts 4 s)."
    )
    assert experiment.run_time_line({"fit": 10.2, "total": 24.6}) == (
        "Run time: 25 s (fit 10 s, the rest 14 s)."
    )
    # three parts of 0.4 s: not shown, so counted in the rest (the shown parts
    # add up to the total)
    seconds = {"fit": 10.0, "load": 0.4, "plan": 0.4, "save": 0.4, "total": 11.6}
    assert experiment.run_time_line(seconds) == (
        "Run time: 12 s (fit 10 s, the rest 2 s)."
    )


def test_z_is_shown_as_a_table_of_features_by_action():
    """report.md's z: a row per feature (0 the mean dynamics), a column per
    action, each cell the dimensions' 0/1 in order (it was a raw nested list)."""
    z = [[[1, 1, 1], [1, 1, 1]], [[0, 1, 0], [1, 0, 0]]]
    assert experiment.z_table(z, ["dx", "dy", "dz"]) == (
        "Each cell: z for dx, dy, dz, in that order.\n\n"
        "| feature | action 0 | action 1 |\n|---|---|---|\n"
        "| 0 (mean dynamics) | 111 | 111 |\n| 1 | 010 | 100 |"
    )
    with pytest.raises(ValueError, match=r"z: expected \(features, actions, 2\)"):
        experiment.z_table(z, ["dx", "dy"])


def _sigterm_is_default(_job) -> bool:
    import signal

    return signal.getsignal(signal.SIGTERM) == signal.SIG_DFL


def test_pool_workers_die_on_sigterm_under_a_stopped_run_s_handler(tmp_path):
    """A forked pool worker inherited the run's SIGTERM handler: when another
    worker died (the out-of-memory killer), the pool's SIGTERM to the others
    raised in them instead of ending them, and the run hung instead of
    failing. The workers put the default back."""
    import signal

    with experiment.stops_reported("prog", tmp_path):
        assert signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL  # installed
        default = experiment.pool_map(
            _sigterm_is_default, [0, 1], workers=2, desc="", progress=False
        )
    assert default == [True, True]


def test_a_stop_names_what_the_run_wrote_whatever_the_clocks_say(
    tmp_path, monkeypatch, capsys
):
    """Files this run wrote, dated an hour back (a file server whose clock is
    behind), are named; a previous run's file it replaced is named, one it
    left is not; metrics.json, written when a stop comes during the figures
    (writes_metrics), is named and not said to be missing."""
    out = tmp_path / "run"
    out.mkdir()
    write_json(out / "config.json", {"name": "cartpole_prediction"})
    write_json(out / "check.json", {})  # not this run's: left as it was
    old = time.time() - 3600

    def stopped_main(config, folder):
        write_json(out / "config.json", {"name": config.name})  # replaced
        write_json(out / "metrics.json", {})
        for name in ("config.json", "metrics.json"):
            os.utime(out / name, (old, old))
        raise KeyboardInterrupt

    monkeypatch.setattr(cartpole_prediction, "main", stopped_main)
    assert _exit_status(cartpole_prediction, ["--no-record", "--out", str(out)]) == 130
    assert capsys.readouterr().err == (
        "python -m tasks.cartpole_prediction: interrupted (Ctrl-C) before the run "
        f"ended: {out} holds the files it finished (config.json, metrics.json); "
        "the next run into it replaces them\n"
    )


def test_json_has_no_infinity_and_keeps_the_order_it_was_given(tmp_path):
    """JSON has no NaN or infinity (Python's ``json`` writes them as ``NaN`` and
    ``Infinity``, which other readers refuse): every non-finite float, numpy's or
    Python's (``mean_ci`` of one sample gives ``float("nan")``), scalar or in an
    array, is null. Keys stay in the order given (methods in the order the
    experiment lists them), indented by two, with a final newline."""
    obj = {"z": np.inf, "y": -np.float32("inf"), "x": float("nan"),
           "w": np.array([np.nan, 1.5]), "v": [float("-inf")]}  # fmt: skip
    plain = {"z": None, "y": None, "x": None, "w": [None, 1.5], "v": [None]}
    assert to_jsonable(obj) == plain
    path = write_json(tmp_path / "m.json", obj)
    assert path.read_bytes() == (
        b'{\n  "z": null,\n  "y": null,\n  "x": null,\n  "w": [\n    null,\n'
        b'    1.5\n  ],\n  "v": [\n    null\n  ]\n}\n'
    )


def test_environment_lists_the_blas_libraries_alone_in_a_fixed_order(monkeypatch):
    """threadpoolctl lists numpy's and scipy's BLAS in the order the process
    loaded them, and OpenMP pools beside them: the record is the BLAS
    libraries alone, the same whatever the order of loading."""
    numpy_blas = {
        "user_api": "blas",
        "internal_api": "openblas",
        "version": "0.3.27",
        "architecture": "Haswell",
        "num_threads": 1,
    }
    scipy_blas = {
        "user_api": "blas",
        "internal_api": "openblas",
        "version": "0.3.21",
        "architecture": "Zen",
        "num_threads": 1,
    }
    openmp = {"user_api": "openmp", "internal_api": "openmp", "version": None,
              "num_threads": 2}  # fmt: skip
    listed = []
    for order in ([numpy_blas, openmp, scipy_blas], [scipy_blas, numpy_blas, openmp]):
        monkeypatch.setattr(experiment, "threadpool_info", lambda order=order: order)
        listed.append(environment()["blas"])
    assert listed[0] == listed[1]
    assert sorted(b["version"] for b in listed[0]) == ["0.3.21", "0.3.27"]


def test_the_machine_line_names_each_blas_its_threads_and_the_commit():
    """report.md's one line of the environment: each BLAS with its kernel and
    threads ("1 thread", "2 threads"), the commit's first 12 digits and
    whether it was dirty; "not found" and "not a git checkout" where there is
    none."""
    env = {
        "cpu": "Test CPU",
        "packages": {"numpy": "2.0.1", "scipy": "1.14.0", "mujoco": "3.2.0"},
        "blas": [
            {"internal_api": "openblas", "version": "0.3.27",
             "architecture": "Haswell", "num_threads": 1},
            {"internal_api": "mkl", "version": "2024.1",
             "architecture": "avx2", "num_threads": 2},
        ],
        "git_commit": "0123456789abcdef0123456789abcdef01234567+dirty",
    }  # fmt: skip
    assert describe_environment(env) == (
        "Machine: Test CPU; numpy 2.0.1, scipy 1.14.0, mujoco 3.2.0; BLAS openblas "
        "0.3.27 (Haswell, 1 thread), mkl 2024.1 (avx2, 2 threads); code "
        "0123456789ab+dirty. The learned models' results depend on these through "
        "round-off (`environment` in metrics.json)."
    )
    env = {**env, "blas": [], "git_commit": None}
    assert "; BLAS not found; code not a git checkout. " in describe_environment(env)


def test_a_stop_outside_the_main_thread_is_reported_and_sigterm_left_alone(
    tmp_path, capsys
):
    """Python takes signal handlers in the main thread alone (``signal.signal``
    raises ValueError elsewhere): a command run from another thread (a
    notebook's worker, say) still reports its Ctrl-C, and SIGTERM keeps its
    handler."""
    import signal
    import threading

    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # the case tested
    seen = []

    def command():
        try:
            with experiment.stops_reported("prog", tmp_path / "run"):
                seen.append(signal.getsignal(signal.SIGTERM))
                raise KeyboardInterrupt
        except BaseException as stop:  # noqa: BLE001 (what ended it, to look at)
            seen.append(stop)

    thread = threading.Thread(target=command)
    thread.start()
    thread.join(timeout=30)
    assert not thread.is_alive() and seen[0] == signal.SIG_DFL
    assert isinstance(seen[1], SystemExit) and seen[1].code == 130
    assert capsys.readouterr().err == (
        "prog: interrupted (Ctrl-C) before the run ended: it had written nothing "
        f"to {tmp_path / 'run'}\n"
    )


def test_a_run_without_out_takes_runs_name_and_holds_it_by_any_path(
    tmp_path, monkeypatch
):
    """No ``--out``: ``runs/<name>`` under the working directory. The run's lock
    is its folder's, whatever path names it: the same folder by its absolute
    path is the run's own, not another run's."""
    monkeypatch.chdir(tmp_path)

    @releases_run_folders
    def main():
        path = run_dir(None, "exp", ("config.json",))
        assert path == Path("runs/exp") and (tmp_path / "runs" / "exp").is_dir()
        assert run_dir(tmp_path / "runs" / "exp", "exp") == tmp_path / "runs" / "exp"
        with pytest.raises(BlockingIOError):  # held while the main runs
            os.close(lock_folder(path, wait=False))

    main()
    os.close(lock_folder(Path("runs/exp"), wait=False))  # released when it ends


def test_a_main_releases_the_folders_it_took_and_no_others(tmp_path):
    """A main run inside another releases its own folder and leaves the outer
    one's held; a folder released is another process's to take, and refused
    while it holds it (this process no longer counts it as its own)."""
    outer, inner = tmp_path / "outer", tmp_path / "inner"

    @releases_run_folders
    def inner_main():
        run_dir(inner, "exp")

    @releases_run_folders
    def outer_main():
        run_dir(outer, "exp")
        inner_main()
        with pytest.raises(BlockingIOError):  # the outer run's, still held
            os.close(lock_folder(outer, wait=False))
        os.close(lock_folder(inner, wait=False))  # the inner run's, released

    outer_main()
    with holding(outer):
        with pytest.raises(ValueError, match="^out: another run is writing to"):
            run_dir(outer, "exp")


def test_process_stat_reads_past_a_command_name_holding_a_parenthesis(tmp_path):
    """``/proc/PID/stat`` gives the command's name in parentheses, and a name may
    hold ``) `` itself (a program named so): the fields are those after the
    last one. A child that has ended and not been waited for is a zombie (Z),
    and it started after this process (start times are clock ticks since
    boot)."""
    import shutil

    program = tmp_path / "a) R 1 2"
    program.symlink_to(shutil.which("true"))
    child = subprocess.Popen([str(program)])
    try:
        os.waitid(os.P_PID, child.pid, os.WEXITED | os.WNOWAIT)  # ended, not reaped
        state, start = experiment._process_stat(child.pid)
        assert state == "Z"
        assert int(start) >= int(experiment._process_stat(os.getpid())[1])
    finally:
        child.wait()


_WATCHER = """
import os, sys, time
from tasks import experiment

owner, case = int(sys.argv[1]), sys.argv[2]
if case == "reused":  # from the second look on, another process has the owner's pid
    real, looks = experiment._process_stat, []

    def stat(pid):
        state, start = real(pid)
        looks.append(pid)
        return state, start if len(looks) == 1 else str(int(start) + 1)

    experiment._process_stat = stat
else:  # the owner's pid now belongs to another user's process
    kill = os.kill

    def refused(pid, sig):
        if pid == owner:
            raise PermissionError(1, "Operation not permitted")
        return kill(pid, sig)

    os.kill = refused
experiment.exit_with(owner, every=0.05)
time.sleep(5)  # exit_with ends the process with status 1 before this ends
"""


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
@pytest.mark.parametrize("case", ["reused", "another user"])
def test_a_worker_ends_when_its_owners_pid_is_another_process(tmp_path, case):
    """The owner's pid given to another process (another start time), or one
    this process may not signal (another user's), is the owner gone: the
    worker ends (status 1), rather than serving a pool no one reads for
    ever. The owner here is this test's process, alive, and the worker's
    parent."""

    script = tmp_path / "worker.py"
    script.write_text(_WATCHER)
    worker = subprocess.run(
        [sys.executable, str(script), str(os.getpid()), case],
        env=checkout_env(), timeout=60,
    )  # fmt: skip
    assert worker.returncode == 1


def test_each_weights_panel_plots_one_weight_against_one_parameter(
    tmp_path, monkeypatch
):
    """Panel (k, j) of weights.png: latent weight k + 1 against parameter j, the
    training instances' posterior means and the test instances' filtered
    belief means; with no latent feature, one panel that says so (and no
    legend, which matplotlib warns of when a panel has nothing to name)."""
    import matplotlib.pyplot as plt

    figures = []
    monkeypatch.setattr(
        experiment, "save_figure", lambda fig, path: figures.append(fig) or path
    )
    train_params = np.array([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0]])  # (B, p)
    train_w = np.array([[0.1, 0.2, 0.3], [-1.0, -2.0, -3.0]])  # (K', B)
    test_params, test_w = np.array([[4.0, 40.0]]), np.array([[0.4, -4.0]])
    experiment.weights_figure(
        tmp_path / "w.png", train_params, train_w, test_params, test_w,
        ["m1", "m2"], "weights",
    )  # fmt: skip
    axes = figures[0].axes
    assert len(axes) == 4  # rows: weights; columns: parameters
    second_weight_by_m1, first_weight_by_m2 = axes[2], axes[1]
    train, test = second_weight_by_m1.collections
    np.testing.assert_array_equal(train.get_offsets(), [[1, -1], [2, -2], [3, -3]])
    np.testing.assert_array_equal(test.get_offsets(), [[4, -4]])
    assert (second_weight_by_m1.get_xlabel(), second_weight_by_m1.get_ylabel()) == (
        "m1", "w2"
    )  # fmt: skip
    train, test = first_weight_by_m2.collections
    np.testing.assert_array_equal(
        train.get_offsets(), [[10, 0.1], [20, 0.2], [30, 0.3]]
    )
    np.testing.assert_array_equal(test.get_offsets(), [[40, 0.4]])
    assert (first_weight_by_m2.get_xlabel(), first_weight_by_m2.get_ylabel()) == (
        "m2", "w1"
    )  # fmt: skip
    with warnings.catch_warnings():  # no legend of an empty panel (matplotlib's
        warnings.simplefilter("error")  # "No artists with labels found" on stderr)
        experiment.weights_figure(
            tmp_path / "w.png", train_params, np.zeros((0, 3)), test_params,
            np.zeros((1, 0)), ["m1", "m2"], "weights",
        )  # fmt: skip
    assert [t.get_text() for t in figures[1].axes[0].texts] == [
        "no latent features were inferred"
    ]
    for fig in figures:
        plt.close(fig)


_ORPHANED_OWNER = """
import os, sys, time
from pathlib import Path

from tasks.experiment import pool_map

folder = Path(sys.argv[1])


def job(i):  # marks its worker, then works for 1.5 s (three of exit_with's polls)
    (folder / f"{os.getpid()}.mark").write_text("")
    time.sleep(1.5)
    return i


if __name__ == "__main__":
    try:
        result = repr(pool_map(job, [0, 1], workers=2, desc="", progress=False))
    except BaseException as err:
        result = f"failed: {err!r}"
    (folder / "result").write_text(result)
"""

_LAUNCHER = """
import subprocess, sys, time
from pathlib import Path

owner = subprocess.Popen([sys.executable, *sys.argv[1:]])
deadline = time.monotonic() + 60
while len(list(Path(sys.argv[2]).glob("*.mark"))) < 2 and time.monotonic() < deadline:
    time.sleep(0.02)
"""  # ends (not waiting for the owner) once both workers are in a job


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_pool_workers_outlive_the_owners_parent(tmp_path):
    """A run started from a shell that then ends (``nohup``, a closed terminal):
    the run's process lives on, and so must its pool's workers, which watch the
    run's process, not the process that started it."""

    (tmp_path / "owner.py").write_text(_ORPHANED_OWNER)
    subprocess.run(
        [sys.executable, "-c", _LAUNCHER, str(tmp_path / "owner.py"), str(tmp_path)],
        env=checkout_env(), timeout=60, check=True,
    )  # fmt: skip
    deadline = time.monotonic() + 60  # the owner is no child of ours to wait for
    while not (tmp_path / "result").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (tmp_path / "result").read_text() == "[0, 1]"


def test_the_common_flags_reach_the_config_and_a_bad_out_is_named_by_its_flag(
    tmp_path, monkeypatch, capsys
):
    """``--no-record`` and ``--no-progress`` turn off what the preset turns on,
    ``--new-features`` sets the fit's step; an ``--out`` that cannot be a run
    folder is a usage error that names the flag, as every other bad flag's is."""
    monkeypatch.chdir(tmp_path)  # the default --out, runs/cartpole_prediction, here
    config, _ = cartpole_prediction.parse_args([])
    assert config.record and config.progress
    config, _ = cartpole_prediction.parse_args(["--no-record", "--no-progress"])
    assert not config.record and not config.progress
    default = cartpole_prediction.PRESETS["quick"].fit
    config, _ = cartpole_prediction.parse_args(["--new-features", "multiple_try"])
    assert config.fit == dataclasses.replace(default, new_features="multiple_try")
    (tmp_path / "file").write_text("mine")
    with pytest.raises(SystemExit) as stopped:
        cartpole_prediction.parse_args(["--out", "file", "--no-record"])
    assert stopped.value.code == 2
    assert "error: --out (out): file exists and is not a folder" in (
        capsys.readouterr().err
    )


def test_a_second_stop_while_the_line_is_composed_is_ignored(
    tmp_path, monkeypatch, capsys
):
    """Ctrl-C pressed again, or SIGTERM sent, while the stop's line is being
    composed: still status 130 and the whole line, not a traceback; the two
    handlers are put back afterwards."""
    import signal

    out = tmp_path / "run"
    listing = experiment._listing
    calls = []

    def listing_under_a_second_stop(folder):
        calls.append(folder)
        if len(calls) == 2:  # the listing after the stop
            if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:  # ends pytest
                raise AssertionError("SIGTERM at its default while composing")
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the handlers, if any, run before this ends
        return listing(folder)

    def stopped_main(config, folder):
        write_json(out / "config.json", {"name": config.name})
        raise KeyboardInterrupt

    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    monkeypatch.setattr(experiment, "_listing", listing_under_a_second_stop)
    monkeypatch.setattr(cartpole_prediction, "main", stopped_main)
    args = ["--no-record", "--out", str(out)]
    assert _exit_status(cartpole_prediction, args) == 130
    assert len(calls) == 2
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
    assert capsys.readouterr().err == (
        "python -m tasks.cartpole_prediction: interrupted (Ctrl-C) before the run "
        f"ended: {out} holds the files it finished (config.json) and no "
        "metrics.json; the next run into it replaces them\n"
    )


def test_a_stop_without_out_names_the_default_run_folder(tmp_path, monkeypatch, capsys):
    """No ``--out``: the line names ``runs/<name>``, the folder the run writes."""

    def stopped_main(config, folder):
        raise KeyboardInterrupt

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cartpole_prediction, "main", stopped_main)
    assert _exit_status(cartpole_prediction, ["--no-record"]) == 130
    assert capsys.readouterr().err.endswith(
        "it had written nothing to runs/cartpole_prediction\n"
    )


# An experiment's process sent SIGTERM, by itself alone (`kill PID`, not the
# process group), at one of three moments of its pool's work (`MOMENT`): as it
# hands out its jobs, while they run (ten minutes each), and while a worker
# sends its result (10 MB: it blocks on the full pipe until the pool's manager
# thread reads it, and the manager waits a second before it does).
_TERMINATE_THE_POOLS_OWNER = """
import os, signal, sys, threading, time
from multiprocessing import connection
from tasks import experiment


# at the top level, where a worker started by forkserver or spawn finds it
def job(moment_and_x):
    if moment_and_x[0] == "sending":
        return b"x" * 10_000_000
    time.sleep(600)


def main(moment, owner):
    def terminate():
        os.kill(owner, signal.SIGTERM)

    class Jobs(list):  # the third job, the first time through
        def __iter__(self):
            for i, x in enumerate(list.__iter__(self)):
                if moment == "handing out" and i == 2 and not hasattr(self, "sent"):
                    self.sent = terminate()
                yield x

    in_order, recv = experiment._in_order, connection.Connection.recv

    def terminate_then_wait(*args):
        if moment == "running":
            terminate()
        return in_order(*args)

    def terminate_then_receive(self, sent=[]):
        if moment == "sending" and not sent and os.getpid() == owner and (
            threading.current_thread() is not threading.main_thread()
        ):
            sent.append(terminate())
            time.sleep(1)  # the run ends the workers, one of them halfway through
        return recv(self)

    experiment._in_order = terminate_then_wait
    connection.Connection.recv = terminate_then_receive
    with experiment.stops_reported("python -m job", "runs/none"):
        jobs = Jobs((moment, x) for x in range(4))
        experiment.pool_map(job, jobs, workers=2, desc="jobs", progress=False)


if __name__ == "__main__":
    main(sys.argv[1], os.getpid())
"""


def run_script(folder: Path, code: str, *args: str):
    """``subprocess.run`` of ``code`` saved as folder/script.py (so that pool
    workers started by forkserver, Python 3.14's default on Linux, or spawn,
    macOS's, can import its jobs; from ``-c`` they cannot), on this checkout's
    ``tasks`` (:func:`checkout_env`)."""
    (folder / "script.py").write_text(code)
    return subprocess.run(
        [sys.executable, str(folder / "script.py"), *args],
        env=checkout_env(), capture_output=True, text=True, cwd=folder, timeout=60,
    )  # fmt: skip


@pytest.mark.parametrize("moment", ["handing out", "running", "sending"])
def test_sigterm_to_the_run_alone_ends_its_running_jobs_with_it(tmp_path, moment):
    """A SIGTERM to an experiment's process alone (its pool's workers are not
    sent it) waited, before its stop line, until the workers had finished the
    jobs they were running, whose results it discards (a paper-preset trial
    takes minutes); so did one that came while the jobs were handed out. It
    ends them with the run. A worker ended while it sent a result left part of
    it in the pipe, and the run hung at exit for ever, its stop line printed.
    The timeout is a guard against those waits, not a timing check."""
    run = run_script(tmp_path, _TERMINATE_THE_POOLS_OWNER, moment)
    assert run.returncode == 143, run.stderr
    assert run.stderr == (
        "python -m job: terminated (SIGTERM) before the run ended: it had written "
        "nothing to runs/none\n"
    )


_ONE_JOB_FAILS_WHILE_OTHERS_RUN = """
import sys, threading, time
from concurrent.futures import Future
from tasks import experiment


def job(x):
    if x == 0:
        raise ValueError("job 0 failed")
    time.sleep(600)


if __name__ == "__main__":
    cancel = Future.cancel

    def cancel_and_say(self):  # what gh-107219 needs, however the race then goes
        if threading.current_thread() is threading.main_thread():
            print("a future was cancelled by the caller", file=sys.stderr)
        return cancel(self)

    Future.cancel = cancel_and_say
    try:
        experiment.pool_map(job, range(10), workers=2, desc="jobs", progress=False)
    except ValueError as error:
        print(error)
"""


def test_a_failed_job_ends_the_pools_running_jobs_and_nothing_else_is_printed(
    tmp_path,
):
    """A job's error is raised once the pool's other running jobs are ended,
    not finished (ten minutes each here; the timeout is a guard, not a timing
    check), and nothing else is printed: with more jobs than the pool takes at
    once, pool.map's results cancelled the jobs not yet taken as the error
    passed, and the pool's manager thread, failing them as the workers ended,
    printed its InvalidStateError traceback (CPython gh-107219) in about half
    the runs. A future cancelled by the caller, the race's first half, is told
    on stderr too, so the check does not depend on how the race goes."""
    run = run_script(tmp_path, _ONE_JOB_FAILS_WHILE_OTHERS_RUN)
    assert (run.returncode, run.stdout, run.stderr) == (0, "job 0 failed\n", "")
