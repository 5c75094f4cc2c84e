"""The identification check on a finished (tiny) swing-up run."""

from __future__ import annotations

import dataclasses
import importlib
import json
import re
import shutil

import numpy as np
import pytest

import hipmdp
from tasks import acrobot_identified
from tasks.acrobot_swingup import main as swingup_main
from tasks.acrobot_swingup import run_streams
from tasks.agents import ACROBOT
from tasks.prediction import gather_split
from tests.test_acrobot_swingup import TINY


@pytest.fixture(scope="module")
def run(tiny_swingup_run):
    out = tiny_swingup_run
    return out, acrobot_identified.main(
        out, trials=1, episodes=2, identify=30, workers=1, progress=False
    )


def test_writes_every_variant_on_the_same_trials(run):
    out, results = run
    data = json.loads((out / "identified.json").read_text())
    n = len(TINY.test_masses) * 1
    for v in acrobot_identified.VARIANTS:
        returns = np.array(data["returns"][v])
        assert returns.shape == (n, 2)
        np.testing.assert_array_equal(returns, results.returns[v])
        assert np.all((-TINY.transfer.max_steps <= returns) & (returns <= -1))
    assert set(data["paired_difference_to_true"]) == set(
        acrobot_identified.VARIANTS
    ) - {"true"}
    between_filters = data["paired_difference_model_error_minus_paper_filter"]
    assert set(between_filters) == {"hipmdp", "identified"}
    for v, d in between_filters.items():
        diff = results.returns[v] - results.returns[f"{v}_paper_filter"]
        assert d["all_episodes"]["mean"] == pytest.approx(diff.mean())
    for v in acrobot_identified.VARIANTS:
        returns = np.array(data["returns"][v])
        np.testing.assert_array_equal(data["median"][v], np.median(returns, axis=0))
        np.testing.assert_array_equal(
            data["step_limit_rate"][v],
            np.mean(returns == -TINY.transfer.max_steps, axis=0),
        )


class _Hip:
    """A stand-in fitted HiP-MDP: its prior is "prior", and ``update`` returns
    what it was given, ``model_error`` included."""

    n_features = 3

    def prior(self):
        return "prior"

    def update(self, belief, data, *, model_error=True):
        return (belief, data, model_error)


def test_identified_model_starts_from_the_given_belief_and_filters_as_asked():
    model = acrobot_identified._Identified(_Hip(), "filtered")
    assert model.prior() == "filtered" and model.n_features == 3
    assert model.update("b", "d") == ("b", "d", True)
    paper = acrobot_identified._Identified(_Hip(), None, model_error=False)
    assert paper.prior() == "prior"
    assert paper.update("b", "d") == ("b", "d", False)


_BAD_OPTIONS = [
    ({"seed": -1}, "seed: expected >= 0"),
    ({"workers": 0}, "workers: expected >= 1"),
    ({"out": "."}, "out: . is a folder"),
]


@pytest.mark.parametrize(
    "check, bad, match",
    [
        (check, bad, match)
        for check, options in (
            ("identified", {"seed", "workers", "out"}),
            ("energy", {"seed", "workers", "out"}),
            ("horizon", {"seed", "out"}),
            ("batch_errors", {"out"}),
        )
        for bad, match in _BAD_OPTIONS
        if set(bad) <= options
    ],
)
def test_checks_refuse_bad_options_before_any_work(run, monkeypatch, check, bad, match):
    """Each check on a run refuses a bad seed, worker count or --out before it
    reads the run."""
    module = importlib.import_module(f"tasks.acrobot_{check}")

    def read_run(*args, **kwargs):
        raise AssertionError("the run was read before the options were checked")

    monkeypatch.setattr(module, "read_run", read_run)
    with pytest.raises(ValueError, match=match):
        module.main(run[0], **bad)


@pytest.mark.parametrize("check", ["identified", "energy", "horizon", "batch_errors"])
def test_checks_refuse_to_write_over_the_runs_own_files(run, monkeypatch, check):
    """``--out RUN/config.json`` replaced the run's config with the check's JSON."""
    module = importlib.import_module(f"tasks.acrobot_{check}")

    def read_run(*args, **kwargs):
        raise AssertionError("the run was read before the options were checked")

    monkeypatch.setattr(module, "read_run", read_run)
    for name in ("config.json", "hipmdp_model.npz"):
        with pytest.raises(ValueError, match=f"out: .*{name} is one of the run"):
            module.main(run[0], out=run[0] / name)


@pytest.mark.parametrize("check", ["identified", "energy", "horizon"])
def test_checks_refuse_the_runs_own_seed(run, monkeypatch, check):
    """SeedSequence(seed).spawn gave a check the run's own streams when --seed
    was the run's: the identification data of test setting 0 came from the bits
    that chose the fit's hyperparameter subsample."""
    module = importlib.import_module(f"tasks.acrobot_{check}")
    seed = json.loads((run[0] / "config.json").read_text())["seed"]

    def average_model(*args, **kwargs):
        raise AssertionError("the work began before the seed was checked")

    monkeypatch.setattr(module, "average_model", average_model)
    with pytest.raises(ValueError, match=f"seed: {seed} is the run's own seed"):
        module.main(run[0], seed=seed, out=run[0].parent / "never.json")
    assert not (run[0].parent / "never.json").exists()


@pytest.mark.parametrize(
    "check, options",
    [
        ("identified", []),
        ("energy", ["--last", "1"]),  # the tiny run plans 1 initial episode
        ("horizon", []),
        ("batch_errors", []),
    ],
)
def test_an_error_refitting_the_average_model_is_not_a_usage_error(
    run, monkeypatch, check, options
):
    """The average model is refitted after the inputs are checked: an error there
    is a failure of the work, shown whole, not reported as bad input (exit 2)."""
    module = importlib.import_module(f"tasks.acrobot_{check}")

    def failing(*args, **kwargs):
        raise ValueError("a failure refitting the average model")

    monkeypatch.setattr(module, "average_model", failing)
    with pytest.raises(ValueError, match="a failure refitting the average model"):
        module.cli([str(run[0]), *options])


@pytest.mark.parametrize(
    "damage, match",
    [
        (lambda c: c.pop("average_n_max"), "average_n_max: missing"),
        (lambda c: c.update(average_n_max=0), "average_n_max: expected >= 1, got 0"),
        (lambda c: c["fit"].update(n_support=0), "fit: FitConfig.n_support"),
        (lambda c: c.update(seed=-1), "seed: expected >= 0, got -1"),
        # the reviewer's cases: a TypeError, a KeyError, a message of AcrobotParams
        (
            lambda c: c["transfer"].update(episodes=3),
            "transfer: unknown TransferConfig fields ['episodes']",
        ),
        (lambda c: c.pop("test_masses"), "test_masses: missing"),
        (
            lambda c: c.update(test_masses=[[0.9]]),
            r"test_masses[0]: expected a pair [m1, m2] of masses > 0 (kg), got [0.9]",
        ),
        (lambda c: c.update(test_masses=[[0.9, True]]), "test_masses[0]: expected"),
        (lambda c: c.update(test_masses=[]), "test_masses: expected a list"),
        (lambda c: c["fit"].update(sweeps=3), "fit: unknown FitConfig fields"),
        (lambda c: c.update(fit=[1]), "fit: expected an object of FitConfig fields"),
        (lambda c: c["transfer"].update(n_episodes=0), "transfer: n_episodes: "),
        (lambda c: c.update(n_trials="3"), "n_trials: expected an integer >= 1"),
        (lambda c: c.update(n_trials=0), "n_trials: expected >= 1, got 0"),
        (lambda c: c.update(test_masses=[[0.9, 0]]), "test_masses[0]: expected"),
        # json writes and reads float("inf") as Infinity
        (lambda c: c.update(test_masses=[[float("inf"), 1]]), "test_masses[0]: "),
        (lambda c: c.update(book_inertia=1), "book_inertia: expected true or false"),
    ],
)
def test_a_damaged_run_config_is_a_usage_error_naming_the_file(
    run, tmp_path, capsys, damage, match
):
    """What the average model is refitted from is checked as the run is read,
    before the work: a usage error (exit 2) naming config.json."""
    copy = tmp_path / "run"
    shutil.copytree(run[0], copy)
    config = json.loads((copy / "config.json").read_text())
    damage(config)
    (copy / "config.json").write_text(json.dumps(config))
    with pytest.raises(SystemExit) as stopped:
        acrobot_identified.cli([str(copy)])
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert "config.json: not a swing-up run's config" in err and match in err


@pytest.mark.parametrize(
    "text, match",
    [
        ('[{"seed": 0}]', r"expected a JSON object \({...}\) at the top level, got an"),
        ('{"seed": 0, "fit": {"n_supp', r"not a JSON file \(Unterminated string"),
        ("", r"not a JSON file \(Expecting value"),
    ],
)
def test_a_config_json_that_is_no_json_object_is_refused_naming_it(
    run, tmp_path, capsys, text, match
):
    """A top-level list gave AttributeError, a cut-short file a JSON error
    without the file's path: each reader of a run's config names the file."""
    from tasks import acrobot_refit, compare_runs

    copy = tmp_path / "run"
    shutil.copytree(run[0], copy)
    (copy / "config.json").write_text(text)
    for cli in (
        lambda: acrobot_identified.cli([str(copy)]),
        lambda: acrobot_refit.cli([str(copy), str(tmp_path / "refit")]),
        lambda: compare_runs.cli([str(run[0]), str(copy)]),
    ):
        with pytest.raises(SystemExit) as stopped:
            cli()
        assert stopped.value.code == 2
        err = capsys.readouterr().err
        assert re.search(f"{re.escape(str(copy / 'config.json'))}: {match}", err)
    assert not (tmp_path / "refit").exists()


def test_a_model_and_batch_of_different_runs_are_refused_naming_both_files(
    run, tmp_path, capsys
):
    """A batch.npz copied from another run (here: one value changed, so the
    instance ids and the number of transitions still agree, as between runs of
    two seeds) is refused before any work, naming both files; a model fitted
    before models recorded their data's digest is checked on the ids and the
    number alone, as it was."""
    copy = tmp_path / "run"
    shutil.copytree(run[0], copy)
    batch = hipmdp.Transitions.load(copy / "batch.npz")
    table = hipmdp.data.ParameterTable.load(copy / "batch.npz")
    states = batch.states.copy()
    states[7, 0] += 1e-9
    dataclasses.replace(batch, states=states).save(copy / "batch.npz", table=table)
    with pytest.raises(SystemExit) as stopped:
        acrobot_identified.cli([str(copy)])
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert f"{copy / 'hipmdp_model.npz'} was not fitted on {copy / 'batch.npz'}" in err
    assert "SHA-256" in err
    batch.take(np.arange(len(batch) - 1)).save(copy / "batch.npz", table=table)
    with pytest.raises(ValueError, match=f"fitted on {len(batch)} transitions"):
        acrobot_identified.read_run(copy)
    fewer = batch.select(instances=batch.instance_ids[1:])
    fewer.save(copy / "batch.npz", table=table)
    with pytest.raises(ValueError, match="training instances .* are not the batch's"):
        acrobot_identified.read_run(copy)

    # a model written before the digest: the changed batch is read as before
    dataclasses.replace(batch, states=states).save(copy / "batch.npz", table=table)
    hip = hipmdp.load(copy / "hipmdp_model.npz")
    info = {k: v for k, v in hip.info.items() if k != "data_sha256"}
    dataclasses.replace(hip, info=info).save(copy / "hipmdp_model.npz")
    np.testing.assert_array_equal(
        acrobot_identified.read_run(copy).batch.states, states
    )


def test_rejects_a_folder_that_is_not_a_run_and_unknown_variants(tmp_path, run):
    with pytest.raises(FileNotFoundError, match="has no config.json"):
        acrobot_identified.main(tmp_path)
    file = tmp_path / "file"  # named as no run, not as an --out it was not given
    file.write_text("")
    with pytest.raises(FileNotFoundError, match="file has no config.json"):
        acrobot_identified.main(file)
    # a folder with a run's config and model but no batch data: named before the
    # options are checked (the batch is what the model is matched against)
    partial = tmp_path / "partial"
    partial.mkdir()
    for name in ("config.json", "hipmdp_model.npz"):
        shutil.copy(run[0] / name, partial / name)
    with pytest.raises(FileNotFoundError, match="partial has no batch.npz; is it a"):
        acrobot_identified.main(partial, variants=("oracle",))
    with pytest.raises(ValueError, match="variants: expected some of"):
        acrobot_identified.main(run[0], variants=("oracle",))
    # a repeated variant ran its trials twice and counted them as twice the trials
    with pytest.raises(ValueError, match="variants: expected .* each once"):
        acrobot_identified.main(run[0], variants=("hipmdp", "hipmdp", "average"))
    with pytest.raises(ValueError, match="variants: expected some of"):
        acrobot_identified.main(run[0], variants=())


@pytest.fixture
def planned(run, monkeypatch):
    """The run's models, installed for ``_job`` with ``init(config)``, and the
    ``n_episodes`` of every ``plan`` call the trials make."""
    from hipmdp import baselines
    from tasks import transfer

    out, _ = run
    hip = hipmdp.load(out / "hipmdp_model.npz")
    batch = hipmdp.Transitions.load(out / "batch.npz")
    average = baselines.batch_only(batch, rng=np.random.default_rng(0), n_max=100)
    calls: list[int] = []
    real_plan = transfer.plan

    def counting_plan(*args, **kwargs):
        calls.append(args[6])  # n_episodes
        return real_plan(*args, **kwargs)

    monkeypatch.setattr(transfer, "plan", counting_plan)

    def init(config):
        acrobot_identified._init(config, hip, average, {"model": [], "paper": []})
        calls.clear()

    return init, calls


def test_model_free_variant_plans_nothing(planned):
    init, calls = planned
    seed = (7, ())
    for variant in ("model_free", "true"):
        init(TINY.transfer)
        v, *_, returns = acrobot_identified._job(
            (variant, 0, 0, TINY.params(*TINY.test_masses[0]), seed)
        )
        assert v == variant and len(returns) == TINY.transfer.n_episodes
        if variant == "model_free":
            assert calls and set(calls) == {0}
        else:
            assert sum(calls) > 0


def test_true_first_plans_on_the_simulator_until_the_first_update(run):
    from hipmdp.planning import LearnedModel
    from tasks.acrobot_swingup import setting_params
    from tasks.agents import ACROBOT, SimulatorModel

    out, _ = run
    hip = hipmdp.load(out / "hipmdp_model.npz")
    batch = hipmdp.Transitions.load(out / "batch.npz")
    params = setting_params(*TINY.test_masses[0])
    model = acrobot_identified._TrueFirst(hip, params)
    S, A = batch.states[:20], batch.actions[:20]
    first = LearnedModel(model, model.prior(), ACROBOT.angle_dims).predict(S, A)
    np.testing.assert_allclose(
        first, SimulatorModel(ACROBOT, params).predict(S, A), atol=1e-12
    )
    data = batch.take(np.arange(30))
    after = LearnedModel(model, model.update(model.prior(), data), ACROBOT.angle_dims)
    plain = LearnedModel(hip, hip.update(hip.prior(), data), ACROBOT.angle_dims)
    np.testing.assert_array_equal(after.predict(S, A), plain.predict(S, A))
    assert not np.allclose(after.predict(S, A), first)


def test_first_planning_changes_only_the_planning_after_the_first_episode(planned):

    init, calls = planned
    # 1 initial planning episode, 3 real episodes, 1 planning episode after each
    # but the last (no episode follows it)
    base = dataclasses.replace(TINY.transfer, n_episodes=3)
    assert base.initial_planning_episodes == base.planning_episodes == 1
    for first, expected in ((None, [1, 1, 1]), (3, [1, 3, 1])):
        init(dataclasses.replace(base, first_planning_episodes=first))
        acrobot_identified._job(
            ("hipmdp", 0, 0, TINY.params(*TINY.test_masses[0]), (7, ()))
        )
        assert calls == expected
    with pytest.raises(ValueError, match="first_planning_episodes: expected >= 0"):
        dataclasses.replace(base, first_planning_episodes=-1)


def test_planning_sizes_reach_every_variant_and_bad_ones_fail_early(
    run, tmp_path, monkeypatch
):
    out, _ = run
    seen, real_pool_map = {}, acrobot_identified.pool_map

    def pool_map(fn, jobs, *, initargs, **kwargs):  # the protocol the trials get
        seen["protocol"] = initargs[0]
        return real_pool_map(fn, jobs, initargs=initargs, **kwargs)

    monkeypatch.setattr(acrobot_identified, "pool_map", pool_map)
    for initial, first in ((None, None), (4, None), (0, 7)):
        acrobot_identified.main(
            out, variants=("true", "hipmdp"), trials=1, episodes=1, identify=30,
            workers=1, initial_planning=initial, first_planning=first, progress=False,
            out=tmp_path / "sizes.json",
        )  # fmt: skip
        protocol = seen["protocol"]
        run_initial = TINY.transfer.initial_planning_episodes
        assert protocol.initial_planning_episodes == (
            run_initial if initial is None else initial
        )
        assert protocol.first_planning_episodes == first
        written = json.loads((tmp_path / "sizes.json").read_text())
        assert written["initial_planning_episodes"] == (
            protocol.initial_planning_episodes
        )
    seen.clear()
    for name in ("initial_planning", "first_planning"):
        with pytest.raises(ValueError, match=f"{name}: expected >= 0"):
            acrobot_identified.main(out, variants=("true",), **{name: -1})
    assert not seen  # rejected before any trial


def test_replan_variant_plans_again_from_a_fresh_value_function(planned, monkeypatch):
    from hipmdp.sarsa import init_state
    from tasks import transfer
    from tasks.agents import ACROBOT

    init, calls = planned
    counting_plan, weights = transfer.plan, []

    def recording_plan(*args, **kwargs):
        weights.append(args[0].weights.copy())  # the value function planning starts at
        return counting_plan(*args, **kwargs)

    monkeypatch.setattr(transfer, "plan", recording_plan)
    fresh = init_state(
        ACROBOT.n_actions, ACROBOT.basis().n_features, ACROBOT.initial_value
    ).weights
    # 2 initial episodes, 3 real ones with 1 planning episode after each but the
    # last
    base = dataclasses.replace(TINY.transfer, initial_planning_episodes=2, n_episodes=3)
    for variant, first in (
        ("hipmdp", None),
        ("hipmdp_replan", None),
        ("hipmdp_replan", 3),
    ):
        init(dataclasses.replace(base, first_planning_episodes=first))
        weights.clear()
        acrobot_identified._job(
            (variant, 0, 0, TINY.params(*TINY.test_masses[0]), (7, ()))
        )
        replan = variant == "hipmdp_replan"
        # the replanning takes the initial planning's size unless --first-planning
        assert calls == [2, (first or 2) if replan else 1, 1]
        np.testing.assert_array_equal(weights[0], fresh)
        assert np.array_equal(weights[1], fresh) == replan
        assert not np.array_equal(weights[2], fresh)
    with pytest.raises(ValueError, match="replan_after_first: expected True or False"):
        dataclasses.replace(base, replan_after_first=1)


class Captured(Exception):
    """Raised by a test's stand-in once it has recorded what it was given, so
    that nothing after it runs."""


def test_run_seeds_replay_the_runs_own_trials(run, tmp_path, monkeypatch):
    from types import SimpleNamespace

    from tasks import acrobot_swingup

    # TINY's 60-step episodes all end at the limit, so their returns cannot tell
    # one trial from another: a run of 2 trials of 500-step episodes can
    long = dataclasses.replace(
        TINY, n_trials=2, record=False,
        transfer=dataclasses.replace(TINY.transfer, max_steps=500),
    )  # fmt: skip
    out = swingup_main(long, out=tmp_path / "long").out
    with np.load(out / "trials.npz") as z:
        methods, returns = list(z["methods"]), z["returns"]
    variants = ("true", "average", "hipmdp")
    for run_seeds in (True, False):
        replay = acrobot_identified.main(
            out, variants=variants, trials=long.n_trials,
            episodes=long.transfer.n_episodes, identify=30, run_seeds=run_seeds,
            workers=1, progress=False, out=tmp_path / "replay.json",
        )  # fmt: skip
        same = []
        for v in variants:  # (setting, trial) rows in the run's order
            ran = returns[methods.index(v)].reshape(-1, long.transfer.n_episodes)
            same.append(np.array_equal(replay.returns[v], ran))
        # the returns differ between trials, so other seeds give other returns
        assert all(same) if run_seeds else not any(same)
        expected = "the run's" if run_seeds else "spawned from seed"
        assert replay.summary["trial_seeds"] == expected
    assert len(np.unique(returns)) > 3

    # the seeds themselves, on a copy of the run with 2 settings x 3 trials: the
    # first 2 trials of each are the run's, whose transfer would spawn them so
    big = tmp_path / "big"
    shutil.copytree(run[0], big)
    config = json.loads((big / "config.json").read_text())
    config.update(test_masses=[[0.9, 1.1], [1.3, 0.7]], n_trials=3, seed=5)
    (big / "config.json").write_text(json.dumps(config))
    seen: dict[str, list] = {}

    def capture(name, key):
        def pool_map(fn, jobs, **kwargs):  # record the jobs, run none
            seen[name] = [key(j) for j in jobs]
            raise Captured

        return pool_map

    monkeypatch.setattr(acrobot_swingup, "pool_map", capture("run", lambda j: j))
    swingup = SimpleNamespace(
        test_masses=config["test_masses"], n_trials=3, record=False, workers=1,
        progress=False, transfer=None, params=acrobot_swingup.setting_params,
        methods=(),
    )  # fmt: skip
    with pytest.raises(Captured):
        acrobot_swingup.run_transfer(swingup, None, None, run_streams(5).trials)
    ran = {(j.setting, j.trial): j.seed for j in seen["run"]}
    for run_seeds in (True, False):
        monkeypatch.setattr(
            acrobot_identified, "pool_map", capture("check", lambda j: j[1:])
        )
        with pytest.raises(Captured):
            acrobot_identified.main(
                big, variants=("true",), trials=2, run_seeds=run_seeds,
                out=tmp_path / "x.json",
            )  # fmt: skip
        checked = {(i, t): seed for (i, t, _, seed) in seen["check"]}
        assert sorted(checked) == [(i, t) for i in range(2) for t in range(2)]
        same = [checked[k] == ran[k] for k in checked]
        assert all(same) if run_seeds else not any(same)
    with pytest.raises(ValueError, match="trials: expected at most the run's 3"):
        acrobot_identified.main(big, variants=("true",), trials=4, run_seeds=True)


def test_out_writes_the_named_file_and_leaves_the_default_alone(run, tmp_path):
    out, results = run
    before = (out / "identified.json").read_text()
    other = acrobot_identified.main(
        out, variants=("true", "average"), trials=1, episodes=1, identify=30,
        workers=1, progress=False, out=tmp_path / "two.json",
    )  # fmt: skip
    assert other.out == tmp_path / "two.json"
    assert set(json.loads(other.out.read_text())["returns"]) == {"true", "average"}
    assert (out / "identified.json").read_text() == before


def test_load_run_refits_the_average_model_with_the_runs_kernels(run, tmp_path):
    # a run fitted with FitConfig(periodic=True) gets a periodic average model;
    # a config written before the field existed loads as the plain kernel
    copy = tmp_path / "run"
    shutil.copytree(run[0], copy)
    config = json.loads((copy / "config.json").read_text())
    for value, want in ((True, (0, 1)), (False, ()), (None, ())):
        if value is None:
            config["fit"].pop("periodic")
        else:
            config["fit"]["periodic"] = value
        (copy / "config.json").write_text(json.dumps(config))
        average = acrobot_identified.load_run(copy).average
        assert average.hyper.periodic == want


def test_energy_variants_plan_on_the_conserving_model_of_their_method(
    planned, monkeypatch
):
    from hipmdp.planning import LearnedModel
    from tasks import transfer
    from tasks.acrobot import AcrobotParams
    from tasks.acrobot_swingup import setting_params
    from tasks.agents import EnergyConserving, SimulatorModel

    init, _ = planned
    seen = []
    counting_plan = transfer.plan  # the fixture's: counts, then plans

    def model_plan(*args, **kwargs):
        seen.append(args[3])
        return counting_plan(*args, **kwargs)

    monkeypatch.setattr(transfer, "plan", model_plan)
    masses = TINY.test_masses[0]
    for variant, inner, params in (
        ("hipmdp_energy", "hipmdp", setting_params(*masses)),
        ("average_energy_nominal", "average", AcrobotParams()),
        ("true", None, None),
    ):
        init(TINY.transfer)
        seen.clear()
        acrobot_identified._job((variant, 0, 0, setting_params(*masses), (7, ())))
        # the initial planning and one after each real episode but the last
        assert len(seen) == TINY.transfer.n_episodes
        for model in seen:
            if inner is None:  # the simulator is never wrapped
                assert isinstance(model, SimulatorModel)
                continue
            assert isinstance(model, EnergyConserving)
            assert model._params == params
            assert isinstance(model._model, LearnedModel)
            hip_like = model._model.belief is not None
            assert hip_like == (inner == "hipmdp")
        if inner == "hipmdp":  # the belief was filtered between episodes
            assert seen[0]._model.belief is not seen[-1]._model.belief


def test_the_planning_wrapper_skips_the_simulator_and_spares_the_recording(run):
    """``_planning_model`` wraps the learned models only; a recorded trial with a
    wrapper installed traces the learned model's own one-step predictions."""
    from hipmdp import baselines
    from hipmdp.planning import LearnedModel
    from tasks import transfer
    from tasks.acrobot_swingup import setting_params
    from tasks.agents import ACROBOT, EnergyConserving

    out, _ = run
    hip = hipmdp.load(out / "hipmdp_model.npz")
    batch = hipmdp.Transitions.load(out / "batch.npz")
    average = baselines.batch_only(batch, rng=np.random.default_rng(0), n_max=100)
    wrapped = []

    def wrapper(model, params):
        wrapped.append(model)
        return EnergyConserving(model, params)

    transfer.set_models(ACROBOT, TINY.transfer, hip, average, wrapper)
    params = setting_params(*TINY.test_masses[0])
    for method in transfer.METHODS:
        job = transfer.TrialJob(method, 0, 0, params, (7, ()), False)
        model = object()
        got = transfer._planning_model(model, job)
        assert (got is model) == (method == "true")
    wrapped.clear()
    result = transfer.run_trial(
        transfer.TrialJob("hipmdp", 0, 0, params, (7, ()), True)
    )
    assert len(wrapped) == TINY.transfer.n_episodes  # as many plannings
    # the trace holds no actions: the first prediction must be the prior-mean
    # model's for one of them, and the energy-conserving one's for none
    trace = result.traces[0]
    first = LearnedModel(hip, hip.prior(), ACROBOT.angle_dims)
    s0 = np.repeat(trace.states[:1], 3, axis=0)
    actions = np.arange(3)
    raw = first.predict(s0, actions)
    conserving = EnergyConserving(first, params).predict(s0, actions)
    assert np.any(np.all(np.isclose(raw, trace.predicted[0], atol=1e-12), axis=1))
    assert not np.any(np.all(np.isclose(conserving, trace.predicted[0]), axis=1))


def test_recording_a_trial_does_not_change_its_results(run):
    """A recorded trial also filters step by step, for the trace; the belief it
    goes on with must be the unrecorded trial's, bit for bit, or the chaotic
    agent turns the round-off into other returns."""
    from tasks import transfer
    from tasks.acrobot_swingup import setting_params
    from tasks.agents import ACROBOT

    out, _ = run
    hip = hipmdp.load(out / "hipmdp_model.npz")
    transfer.set_models(ACROBOT, TINY.transfer, hip, None)
    params = setting_params(*TINY.test_masses[0])
    recorded, plain = (
        transfer.run_trial(transfer.TrialJob("hipmdp", 0, 0, params, (7, ()), rec))
        for rec in (True, False)
    )
    assert recorded.traces and plain.traces is None
    np.testing.assert_array_equal(recorded.weight_means, plain.weight_means)
    np.testing.assert_array_equal(recorded.returns, plain.returns)
    # the trace ends where step-by-step filtering ends: at the batched belief up
    # to round-off
    np.testing.assert_allclose(
        recorded.traces[0].belief_mean[-1], recorded.weight_means[1], rtol=1e-9
    )


def test_the_checks_build_the_runs_own_instances(run, tmp_path, monkeypatch):
    """A run made with --book-inertia is checked on instances with the book's
    inertias, by each check that builds instances."""
    from tasks import acrobot_energy, acrobot_horizon

    book = tmp_path / "book"
    shutil.copytree(run[0], book)
    config = json.loads((book / "config.json").read_text())
    config["book_inertia"] = True
    (book / "config.json").write_text(json.dumps(config))
    seen: dict[str, list] = {}

    def capture(name, instances):
        seen[name] = list(instances)
        raise Captured

    monkeypatch.setattr(
        acrobot_identified,
        "pool_map",
        lambda fn, jobs, **kw: capture("identified", [j[3] for j in jobs]),
    )
    monkeypatch.setattr(
        acrobot_energy,
        "pool_map",
        lambda fn, jobs, initargs, **kw: capture("energy", initargs[0]),
    )
    monkeypatch.setattr(
        acrobot_horizon,
        "gather_split",
        lambda domain, params, *a, **kw: capture("horizon", [params]),
    )
    options = dict(progress=False, out=tmp_path / "check.json")
    with pytest.raises(Captured):
        acrobot_identified.main(book, variants=("true",), workers=1, **options)
    with pytest.raises(Captured):
        acrobot_energy.main(
            book, models=("true", "prior"), last=1, workers=1, **options
        )
    with pytest.raises(Captured):
        acrobot_horizon.main(book, **options)
    assert set(seen) == {"identified", "energy", "horizon"}
    for name, instances in seen.items():
        assert instances, name
        for params in instances:
            assert params.inertias == pytest.approx((1.0, 1.0)), name


def test_the_identified_variants_get_beliefs_filtered_on_their_instance(
    run, monkeypatch, tmp_path
):
    """The beliefs handed to the trials, rebuilt from --seed: each setting's
    own `identify` transitions, filtered with the model's error ("model") and
    with the paper's σ² ("paper"); neither is the prior. (The returns cannot
    show a swap: the tiny run's are all at the step limit.)"""
    out, _ = run
    handed = {}
    real_init = acrobot_identified._init

    def init(config, hip, average, beliefs):
        handed.update(hip=hip, beliefs=beliefs)
        real_init(config, hip, average, beliefs)

    monkeypatch.setattr(acrobot_identified, "_init", init)
    acrobot_identified.main(
        out, variants=("identified", "identified_paper_filter"), trials=1,
        episodes=1, identify=30, seed=5, workers=1, progress=False,
        out=tmp_path / "identified.json",
    )  # fmt: skip
    hip, beliefs = handed["hip"], handed["beliefs"]
    config = json.loads((out / "config.json").read_text())
    instances = acrobot_identified.run_test_instances(config)
    _, ss_identify = np.random.SeedSequence(5).spawn(2)
    assert len(beliefs["model"]) == len(beliefs["paper"]) == len(instances)
    for i, (s, params) in enumerate(
        zip(ss_identify.spawn(len(instances)), instances, strict=True)
    ):
        train = gather_split(ACROBOT, params, 30, 0, rng=np.random.default_rng(s)).train
        assert len(train) == 30 and set(train.instances) == {0}
        for key, model_error in (("model", True), ("paper", False)):
            want = hip.update(hip.prior(), train, model_error=model_error)
            np.testing.assert_array_equal(beliefs[key][i].mean, want.mean)
            assert not np.allclose(beliefs[key][i].mean, hip.prior().mean)
        assert not np.allclose(beliefs["model"][i].mean, beliefs["paper"][i].mean)


@pytest.mark.parametrize("check", ["identified", "energy", "horizon", "refit"])
def test_the_checks_command_lines_take_no_progress(monkeypatch, check):
    """``--no-progress`` reaches ``main`` (the run checks had no way to hide their
    bars, unlike the experiments)."""
    module = importlib.import_module(f"tasks.acrobot_{check}")
    seen = []

    class Stop(Exception):
        pass

    def main(*args, progress=True, **kwargs):
        seen.append(progress)
        raise Stop

    monkeypatch.setattr(module, "main", main)
    argv = ["RUN"] + (["OUT"] if check == "refit" else [])
    for extra, progress in (([], True), (["--no-progress"], False)):
        with pytest.raises(Stop):
            module.cli(argv + extra)
        assert seen.pop() is progress


def test_each_variant_trial_gets_its_model_filter_belief_and_method(monkeypatch):
    """``_job`` on test setting 1 hands the trial: the identified variants that
    setting's own filtered belief ("model" or "paper", not another setting's),
    every HiP-MDP variant the filter it names, ``model_free`` the true model's
    method with no planning at all, and the energy variants their instance's or
    the nominal acrobot's constraint. (The tiny run's returns, all at the step
    limit, cannot show a swap.)"""
    from types import SimpleNamespace

    from tasks import transfer
    from tasks.acrobot import AcrobotParams
    from tasks.acrobot_swingup import setting_params

    beliefs = {"model": ["model 0", "model 1"], "paper": ["paper 0", "paper 1"]}
    monkeypatch.setattr(acrobot_identified, "_STATE", {})  # the stand-ins stay here
    acrobot_identified._init(TINY.transfer, _Hip(), "the average", beliefs)
    installed, ran = [], []

    def set_models(domain, config, model, average, wrapper):
        installed.append((config, model, wrapper))

    def run_trial(job):
        ran.append(job)
        return SimpleNamespace(returns=np.array([-1.0]))

    monkeypatch.setattr(transfer, "set_models", set_models)
    monkeypatch.setattr(transfer, "run_trial", run_trial)
    params = setting_params(1.3, 0.7)
    # variant: the trial's method, its prior belief, whether it filters with the
    # model's error (None: not the HiP-MDP's filter), its energy constraint
    for variant, method, prior, model_error, energy in (
        ("hipmdp", "hipmdp", "prior", True, None),
        ("hipmdp_paper_filter", "hipmdp", "prior", False, None),
        ("identified", "hipmdp", "model 1", True, None),
        ("identified_paper_filter", "hipmdp", "paper 1", False, None),
        ("hipmdp_energy", "hipmdp", "prior", True, params),
        ("hipmdp_energy_nominal", "hipmdp", "prior", True, AcrobotParams()),
        ("average_energy_nominal", "average", None, None, AcrobotParams()),
        ("average", "average", None, None, None),
        ("true", "true", None, None, None),
        ("model_free", "true", None, None, None),
    ):
        acrobot_identified._job((variant, 1, 0, params, (7, ())))
        (config, model, wrapper), job = installed.pop(), ran.pop()
        assert (job.method, job.setting, job.params) == (method, 1, params), variant
        if model_error is not None:
            assert model.prior() == prior, variant
            assert model.update("b", "d") == ("b", "d", model_error), variant
        planned = config.initial_planning_episodes, config.planning_episodes
        assert planned == ((0, 0) if variant == "model_free" else (1, 1)), variant
        if energy is None:
            assert wrapper is None, variant
        else:
            assert wrapper("inner", params)._params == energy, variant


@pytest.fixture
def written(run, tmp_path, monkeypatch):
    """``main`` on a copy of the run with 2 test settings, 3 trials of 3 episodes
    each, whose trials return the hand-made ``_HIPMDP`` (rows in (setting, trial)
    order), ``_HIPMDP + _PAPER_GAIN`` for the paper's filter and -10 for ``true``;
    and the seed each (variant, setting, trial) was given."""
    copy = tmp_path / "two"
    shutil.copytree(run[0], copy)
    config = json.loads((copy / "config.json").read_text())
    config.update(test_masses=[[0.9, 1.1], [1.3, 0.7]], n_trials=3)
    (copy / "config.json").write_text(json.dumps(config))
    seeds = {}

    def job(args):
        variant, setting, trial, _, seed = args
        seeds[variant, setting, trial] = seed
        returns = {
            "true": np.full(3, -10.0),
            "hipmdp": _HIPMDP[3 * setting + trial],
            "hipmdp_paper_filter": _HIPMDP[3 * setting + trial] + _PAPER_GAIN,
        }[variant]
        # as a trial does, one return per episode of the protocol it was given
        n_episodes = acrobot_identified._STATE["config"].n_episodes
        return variant, setting, trial, returns[:n_episodes]

    monkeypatch.setattr(acrobot_identified, "_job", job)
    results = acrobot_identified.main(
        copy, variants=("true", "hipmdp", "hipmdp_paper_filter"), trials=3,
        episodes=3, identify=40, seed=config["seed"] + 1, workers=1,
        progress=False, out=tmp_path / "identified.json",
    )  # fmt: skip
    return results, json.loads(results.out.read_text()), seeds, config


# TINY's step limit is 60: an episode returning -60 ran to it
_HIPMDP = np.array(
    [
        [-60.0, -20.0, -12.0],
        [-20.0, -20.0, -12.0],
        [-20.0, -30.0, -12.0],
        [-60.0, -30.0, -12.0],
        [-20.0, -40.0, -12.0],
        [-20.0, -40.0, -12.0],
    ]
)
_PAPER_GAIN = np.array([0.0, 6.0, 3.0])  # the paper's filter, 3 better per episode


def test_the_summary_is_of_each_episode_over_the_trials(written):
    """The written means, medians, step-limit shares and paired differences of
    hand-made returns, worked out by hand (episode columns of ``_HIPMDP``:
    -60 -60 -20 -20 -20 -20, -20 -20 -30 -30 -40 -40, six times -12)."""
    results, data, _, config = written
    np.testing.assert_array_equal(data["returns"]["hipmdp"], _HIPMDP)
    np.testing.assert_array_equal(results.returns["hipmdp"], _HIPMDP)
    curve = data["curves"]["hipmdp"]
    np.testing.assert_allclose(curve["mean"], [-200 / 6, -30, -12])
    assert curve["n"] == 6
    assert np.all(np.array(curve["low"][:2]) < curve["mean"][:2])
    assert np.all(np.array(curve["high"][:2]) > curve["mean"][:2])
    np.testing.assert_array_equal(data["median"]["hipmdp"], [-20, -30, -12])
    np.testing.assert_allclose(data["step_limit_rate"]["hipmdp"], [2 / 6, 0, 0])
    np.testing.assert_array_equal(data["step_limit_rate"]["true"], [0, 0, 0])
    # hipmdp - true: the mean of _HIPMDP (its row sums -92 -52 -62 -102 -72 -72,
    # total -452 over 18 returns) + 10; its per-episode means + 10
    to_true = data["paired_difference_to_true"]["hipmdp"]
    assert to_true["all_episodes"]["mean"] == pytest.approx(-452 / 18 + 10)
    assert to_true["all_episodes"]["n"] == 6
    np.testing.assert_allclose(to_true["per_episode"]["mean"], [-200 / 6 + 10, -20, -2])
    between = data["paired_difference_model_error_minus_paper_filter"]["hipmdp"]
    assert between["all_episodes"]["mean"] == pytest.approx(-3)
    assert data["trials_per_setting"] == 3
    assert data["identify_transitions"] == 40
    assert data["seed"] == config["seed"] + 1
    assert data["first_planning_episodes"] is None
    assert data["initial_planning_episodes"] == TINY.transfer.initial_planning_episodes


def test_every_variant_runs_on_the_same_seeds_and_each_trial_on_its_own(written):
    """Paired comparisons rest on each (setting, trial) having one seed for all
    variants, and different trials different ones."""
    _, _, seeds, _ = written
    pairs = [(i, t) for i in range(2) for t in range(3)]
    for i, t in pairs:
        assert len({seeds[v, i, t] for v in ("true", "hipmdp")}) == 1
    assert len({seeds["true", i, t] for i, t in pairs}) == len(pairs)


def test_the_command_line_prints_each_episodes_standard_error(monkeypatch, capsys):
    """Episode 1 returns -10 and -30: mean -20, sample standard deviation
    (ddof=1) √200, standard error √200/√2 = 10; episode 2 likewise -30 ± 10."""
    returns = {"true": np.array([[-10.0, -20.0], [-30.0, -40.0]])}
    summary = {"median": {"true": [-20.0, -30.0]}, "step_limit_rate": {}}

    def main(*args, **kwargs):
        return acrobot_identified.Results("out.json", returns, summary)

    monkeypatch.setattr(acrobot_identified, "main", main)
    assert acrobot_identified.cli(["RUN"]) == 0
    assert "true: -20.0 ± 10.0, -30.0 ± 10.0   (mean ± s.e." in capsys.readouterr().out
    # one trial has no standard error ("± 0.0" read as certainty)
    returns["true"] = returns["true"][:1]
    assert acrobot_identified.cli(["RUN"]) == 0
    assert "true: -10.0, -20.0   (per episode, one trial: no standard error)" in (
        capsys.readouterr().out
    )


def test_a_model_is_matched_to_its_batch_whatever_the_order_of_its_columns(run):
    """The model's training instances are its columns, in any order: a model
    whose columns run in another order than the batch's ids was fitted on it."""
    from types import SimpleNamespace

    batch = hipmdp.Transitions.load(run[0] / "batch.npz")
    assert len(batch.instance_ids) > 1
    hip = SimpleNamespace(instance_ids=batch.instance_ids[::-1].copy(), info={})
    acrobot_identified.check_model_data(hip, batch, "model.npz", "batch.npz")


def test_true_first_predicts_wrapped_angle_changes():
    """The true simulator's Δ stands in for the HiP-MDP's, which predicts angle
    changes wrapped to [-π, π]: a swing across ±π changes an angle by a little,
    not by about 2π."""
    from tasks.acrobot_swingup import setting_params

    model = acrobot_identified._TrueFirst(_Hip(), setting_params(0.9, 1.1))
    states = np.array([[np.pi - 1e-3, np.pi - 1e-3, 5.0, 5.0]])
    delta = model.mean_predictor(model.prior())(states, np.array([1]))
    dims = list(ACROBOT.angle_dims)
    assert np.all(np.abs(delta[:, dims]) <= np.pi)  # unwrapped: about 1 - 2π
