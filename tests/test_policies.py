"""A policy as your own method (tasks/methods.py): the example agent against the
built-in agent's episode loop, the checks on what a policy returns, and a policy
added to a swing-up run leaving every other number as it was."""

from __future__ import annotations

import dataclasses
import hashlib
import re

import numpy as np
import pytest

from hipmdp.data import Transitions
from tasks import methods
from tasks.acrobot import AcrobotParams
from tasks.agents import ACROBOT, run_episode
from tasks.methods import Added, MethodSpec, SarsaPolicy, method_seed
from tasks.transfer import TransferConfig, _policy_episode

SARSA = "sarsa=tasks.methods:SarsaPolicy"


def added(method, name="mine", seed=0) -> Added:
    return Added(MethodSpec(name, "m", "A"), method, seed)


def test_the_example_policy_acts_and_learns_as_the_built_in_agent():
    """SarsaPolicy's agent in the trials' episode loop against
    ``tasks.agents.run_episode`` (the built-in agent, learning): the same
    environment seed and exploration seed give the same states, rewards and
    weights, through an episode that ends at the goal and one cut by the step
    limit."""
    params = AcrobotParams(link_mass_1=1.1, link_mass_2=0.9)
    envs = [
        ACROBOT.make_env(params, seed=np.random.default_rng(3), max_steps=max_steps)
        for max_steps in (2000, 2000)
    ]
    policy = added(SarsaPolicy())
    agent = SarsaPolicy().agent(rng=np.random.default_rng(4))
    basis, rng = ACROBOT.basis(), np.random.default_rng(4)
    state = agent.state  # the same fresh weights
    terminal = []
    for _ in range(2):
        states, rewards = _policy_episode(envs[0], agent, policy, ACROBOT.n_actions)
        episode = run_episode(envs[1], basis, ACROBOT.sarsa, state, rng=rng)
        state = episode.state
        np.testing.assert_array_equal(np.array(states), episode.states)
        np.testing.assert_array_equal(rewards, episode.rewards)
        np.testing.assert_array_equal(agent.state.weights, state.weights)
        terminal.append(episode.terminal)
    # the second episode again, cut short: the step limit's last update
    cut = [
        ACROBOT.make_env(params, seed=np.random.default_rng(5), max_steps=30)
        for _ in range(2)
    ]
    states, rewards = _policy_episode(cut[0], agent, policy, ACROBOT.n_actions)
    episode = run_episode(cut[1], basis, ACROBOT.sarsa, state, rng=rng)
    np.testing.assert_array_equal(np.array(states), episode.states)
    np.testing.assert_array_equal(agent.state.weights, episode.state.weights)
    assert terminal[0] and len(rewards) == 30 and not episode.terminal


class Acts:
    """A policy whose agent returns ``action`` (or what ``agent`` says)."""

    def __init__(self, action=0, agent=None):
        self.action, self.made = action, agent

    def fit(self, batch, *, rng):
        pass

    def agent(self, *, rng):
        return self if self.made is None else self.made

    def act(self, state):
        state[:] = np.nan  # scribbles, as a careless policy might
        return self.action

    def observe(self, state, action, reward, next_state, terminal):
        state[:] = np.nan
        next_state[:] = np.nan


class BothKinds(Acts):
    def adapt(self, train, *, rng):
        return self


class AgentWithoutRng(Acts):
    def agent(self):
        return self


class NoObserve:
    def act(self, state):
        return 0


class FailsLater(Acts):
    """Acts once (as fit_all tries it), then raises; with ``where="agent"``, its
    second agent raises instead."""

    calls = 0
    where = "act"

    def fit(self, batch, *, rng):
        FailsLater.calls = 0  # a run starts counting afresh

    def agent(self, *, rng):
        FailsLater.calls += self.where == "agent"
        if FailsLater.calls > 1:
            raise RuntimeError("second agent")
        return self

    def act(self, state):
        FailsLater.calls += self.where == "act"
        if FailsLater.calls > 1:
            raise RuntimeError("second act")
        return 0


class FailsInItsSecondAgent(FailsLater):
    where = "agent"


class Counts(Acts):
    """Its agent is itself, and counts what it observes."""

    observed = 0

    def observe(self, state, action, reward, next_state, terminal):
        self.observed += 1


class Draws(Acts):
    """Keeps the first draw of each agent's rng, on the class (trials run on
    copies of the object)."""

    drawn: list = []

    def agent(self, *, rng):
        Draws.drawn.append(rng.random())
        return self


def batch():
    """A small batch shaped as the acrobot's: 4-D states, actions 0, 1, 2."""
    rng = np.random.default_rng(0)
    s = rng.normal(size=(20, 4))
    return Transitions(
        s, rng.integers(3, size=20), s + 0.01, np.zeros(20, int), rewards=-np.ones(20)
    )


@pytest.mark.parametrize(
    "policy, match",
    [
        (Acts(3), "mine: act must return an action index 0..2, got 3"),
        (Acts(-1), "mine: act must return an action index 0..2, got -1"),
        (Acts(True), "mine: act must return an action index 0..2, got True"),
        (Acts(1.0), "mine: act must return an action index \\(an integer\\), got 1.0"),
        (Acts(None), "an action index \\(an integer\\), got None \\(NoneType\\)"),
        (Acts(agent=NoObserve()), "mine: agent must return .* NoObserve has no obs"),
    ],
)
def test_bad_agents_are_refused_before_any_run_naming_the_method(policy, match):
    with pytest.raises(ValueError, match=match):
        methods.fit_all([(MethodSpec("mine", "m", "A"), policy)], batch(), 0, 3)


def test_a_good_agent_passes_and_its_action_may_be_a_numpy_integer():
    loaded = [(MethodSpec("p", "m", "A"), Acts(np.int64(2)))]
    (fitted,) = methods.fit_all(loaded, batch(), 0, n_actions=3)
    assert fitted.is_policy
    assert fitted.act(Acts(np.int64(2)), np.zeros(4), 3) == 2
    with pytest.raises(ValueError, match="index 0..1, got np.int64\\(2\\)"):
        methods.fit_all(loaded, batch(), 0, n_actions=2)


def test_policies_are_loaded_by_the_swing_up_alone():
    with pytest.raises(ValueError, match="sarsa=tasks.methods:SarsaPolicy is a pol"):
        methods.load_all([SARSA])
    ((spec, policy),) = methods.load_all([SARSA], policies=True)
    assert spec.name == "sarsa" and methods.is_policy(policy)
    with pytest.raises(ValueError, match="BothKinds has both adapt and agent"):
        methods.load_all(["x=tests.test_policies:BothKinds"], policies=True)
    with pytest.raises(ValueError, match="NoObserve has no fit and no adapt or agent"):
        methods.load_all(["x=tests.test_policies:NoObserve"], policies=True)
    # the trials call agent(rng=rng)
    with pytest.raises(ValueError, match="AgentWithoutRng.agent\\(\\) cannot take"):
        methods.load_all(["x=tests.test_policies:AgentWithoutRng"], policies=True)


def test_the_cart_pole_refuses_a_policy_before_any_work(tmp_path):
    from tasks.cartpole_prediction import main
    from tests.test_cartpole_prediction import TINY

    with pytest.raises(ValueError, match="only tasks.acrobot_swingup runs policies"):
        main(dataclasses.replace(TINY, methods=(SARSA,)), out=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_the_swing_up_command_line_takes_a_policy_and_refuses_a_bad_class(
    capsys, tmp_path
):
    """A class that is neither a model nor a policy is a usage error (exit
    status 2) naming --method, before the run gathers any data."""
    from tasks.acrobot_swingup import parse_args

    assert parse_args(["--method", SARSA])[0].methods == (SARSA,)
    for bad, match in [
        ("x=tests.test_policies:BothKinds", "BothKinds has both adapt and agent"),
        ("x=tests.test_policies:NoObserve", "NoObserve has no fit and no adapt or"),
    ]:
        with pytest.raises(SystemExit) as exit_:
            parse_args(["--method", bad, "--out", str(tmp_path / "x")])
        assert exit_.value.code == 2
        assert re.search(
            f"error: --method \\(methods\\): .*{match}", capsys.readouterr().err
        )


def test_an_agent_gets_its_keys_stream_and_copies_of_the_states():
    """``Added.agent``'s rng: the one of (seed, name, key); act and observe see
    copies, so the scribbling policy leaves the caller's states as they were."""
    policy, Draws.drawn = Draws(), []
    agent = added(policy, "a", 7).agent((4, 2, 1))
    expected = np.random.default_rng(method_seed(7, "a", 1, 4, 2, 1)).random()
    assert Draws.drawn == [expected]
    s = np.arange(4.0)
    added(policy).act(agent, s, 3)
    added(policy).observe(agent, s, 0, -1.0, s, False)
    np.testing.assert_array_equal(s, np.arange(4.0))


@pytest.mark.parametrize(
    "cls, where", [("FailsLater", "act"), ("FailsInItsSecondAgent", "agent")]
)
def test_a_policy_that_breaks_in_a_trial_says_where(tmp_path, cls, where):
    from tasks.acrobot_swingup import main as swingup
    from tests.test_acrobot_swingup import TINY as SWINGUP

    config = dataclasses.replace(
        SWINGUP,
        record=False,
        workers=1,
        methods=(f"late=tests.test_policies:{cls}",),
    )
    with pytest.raises(RuntimeError, match=f"second {where}") as err:
        swingup(config, tmp_path)
    note = "".join(err.value.__notes__)
    assert f"in method late: {where}" in note and "setting 0, trial 0" in note


class FailsAtTheEnd(Acts):
    def end_episode(self):
        raise RuntimeError("end_episode failed")


def test_the_try_ends_its_episode_so_a_broken_end_episode_fails_early():
    """fit_all's try calls end_episode, as every real episode's end will: a
    policy whose end_episode breaks is refused before the run's long stages."""
    with pytest.raises(RuntimeError, match="end_episode failed") as err:
        methods.fit_all([(MethodSpec("e", "m", "A"), FailsAtTheEnd())], batch(), 0, 3)
    assert "in method e: end_episode" in "".join(err.value.__notes__)


class Records(Acts):
    """Keeps the calls its agents get, on the class (the try runs on a copy)."""

    calls: list = []

    def act(self, state):
        Records.calls.append("act")
        return 0

    def observe(self, state, action, reward, next_state, terminal):
        Records.calls.append("observe")

    def end_episode(self):
        Records.calls.append("end_episode")


def test_the_try_steps_once_or_on_an_empty_batch_only_ends_the_episode():
    """fit_all's try of a policy: act, observe and end_episode on the first
    batch transition; with no batch transition to act on, end_episode alone."""
    for data, expected in [
        (batch(), ["act", "observe", "end_episode"]),
        (batch().take(np.arange(0)), ["end_episode"]),
    ]:
        Records.calls = []
        methods.fit_all([(MethodSpec("r", "m", "A"), Records())], data, 0, 3)
        assert Records.calls == expected


class Observes(Draws):
    """Keeps the first draw of its agent's rng and what the agent observes."""

    seen: list = []

    def observe(self, state, action, reward, next_state, terminal):
        Observes.seen.append((state, action, reward, next_state, terminal))


def test_the_try_agent_has_its_stream_and_observes_the_first_batch_transition():
    """fit_all's try of a policy: the agent's rng is that of key (2, 2)
    (method_seed's docstring), and it observes the batch's first transition as
    it was, not at the goal (terminal False)."""
    data = batch()
    Draws.drawn, Observes.seen = [], []
    methods.fit_all([(MethodSpec("o", "m", "A"), Observes())], data, 7, 3)
    assert Draws.drawn == [np.random.default_rng(method_seed(7, "o", 1, 2, 2)).random()]
    ((state, action, reward, next_state, terminal),) = Observes.seen
    np.testing.assert_array_equal(state, data.states[0])
    np.testing.assert_array_equal(next_state, data.next_states[0])
    assert (action, reward, terminal) == (data.actions[0], -1.0, False)


def test_the_example_policy_starts_from_the_domains_initial_values():
    """A fresh agent's action values are the domain's q₀ (tasks/agents.py's
    table): 0 on the acrobot, 100 on the cart-pole, one row per action."""
    for domain, n_actions, q0 in (("acrobot", 3, 0.0), ("cartpole", 2, 100.0)):
        agent = SarsaPolicy(domain).agent(rng=np.random.default_rng(0))
        weights = agent.state.weights
        assert weights.shape == (n_actions, agent.basis.n_features), domain
        np.testing.assert_array_equal(agent.basis(np.zeros(4)) @ weights.T, q0)


def test_the_example_policy_refuses_an_unknown_domain():
    with pytest.raises(
        ValueError, match="domain: expected one of .*, got 'no_such_domain'"
    ):
        SarsaPolicy("no_such_domain")


def test_the_try_leaves_the_fitted_object_as_fit_left_it():
    policy = Counts()
    (fitted,) = methods.fit_all([(MethodSpec("c", "m", "A"), policy)], batch(), 0, 3)
    assert fitted.method is policy and policy.observed == 0
    with pytest.raises(ValueError, match="n_actions: needed to try the policy c"):
        methods.fit_all([(MethodSpec("c", "m", "A"), policy)], batch(), 0)


def test_each_trial_gets_its_own_agent_stream():
    """run_trial gives a policy's agent the stream of (run seed, name, setting,
    trial): the same for the same trial, another for another."""
    from tasks.transfer import TrialJob, run_trial, set_models

    config = TransferConfig(n_episodes=1, max_steps=5, planning_max_steps=5)
    loaded = [(MethodSpec("d", "m", "A"), Draws())]
    set_models(
        ACROBOT, config, None, None, added=methods.fit_all(loaded, batch(), 7, 3)
    )
    params = AcrobotParams(link_mass_1=0.9, link_mass_2=1.1)
    Draws.drawn = []
    for i, t in [(0, 0), (1, 2), (0, 0), (2, 1)]:
        run_trial(TrialJob("d", i, t, params, (5, (i, t)), False))
    expected = [
        np.random.default_rng(method_seed(7, "d", 1, 4, i, t)).random()
        for i, t in [(0, 0), (1, 2), (0, 0), (2, 1)]
    ]
    assert Draws.drawn == expected and len(set(expected)) == 3


class ModelDraws:
    """A model-based method that records the first draw of every rng it is
    given, fit's and each adapt's, on the class (trials run on copies)."""

    drawn: dict = {}

    def fit(self, batch, *, rng):
        ModelDraws.drawn.setdefault("fit", []).append(rng.random())

    def adapt(self, train, *, rng):
        ModelDraws.drawn.setdefault(len(train), []).append(rng.random())
        return self

    def predict(self, states, actions):
        return np.zeros(states.shape), np.ones(states.shape)


def test_a_models_fit_and_each_trials_adapt_get_their_own_streams():
    """fit gets (seed, name, 0), fit_all's tries (seed, name, 1, 2) and (seed,
    name, 1, 2, 1); a transfer trial's adapt after e real episodes of trial t on
    setting i gets (seed, name, 1, 3, i, t, e), as method_seed says: the same
    for the same trial, another for another (an unseeded or constant stream
    would pass the other tests: their methods draw nothing)."""
    from tasks.transfer import TrialJob, run_trial, set_models

    config = TransferConfig(
        n_episodes=2, max_steps=5, planning_max_steps=5,
        initial_planning_episodes=1, planning_episodes=1,
    )  # fmt: skip
    ModelDraws.drawn = {}
    loaded = [(MethodSpec("m", "x", "A"), ModelDraws())]
    set_models(
        ACROBOT, config, None, None,
        added=methods.fit_all(loaded, batch(), 7, 3, transfer=True),
    )  # fmt: skip
    fit = np.random.default_rng(method_seed(7, "m", 0)).random()
    assert ModelDraws.drawn["fit"] == [fit]
    # fit_all's two tries (TRIAL_SIZE transitions, then none): keys (2,), (2, 1)
    for n_seen, key in [(methods.TRIAL_SIZE, (2,)), (0, (2, 1))]:
        tried = np.random.default_rng(method_seed(7, "m", 1, *key)).random()
        assert ModelDraws.drawn[n_seen] == [tried], key
    ModelDraws.drawn = {}
    params = AcrobotParams(link_mass_1=0.9, link_mass_2=1.1)
    trials = [(0, 0), (1, 2), (0, 0)]
    for i, t in trials:
        run_trial(TrialJob("m", i, t, params, (5, (i, t)), False))
    # before the first episode (no transitions), after it (its 5)
    for e, n_seen in enumerate((0, 5)):
        expected = [
            np.random.default_rng(method_seed(7, "m", 1, 3, i, t, e)).random()
            for i, t in trials
        ]
        assert ModelDraws.drawn[n_seen] == expected, e
        assert expected[0] == expected[2] != expected[1]


def test_a_swing_up_run_takes_a_policy_and_nothing_else_changes(tiny_swingup, tmp_path):
    """A tiny swing-up run without added methods (one process) and with a policy
    and a model (two worker processes): every other method's numbers, traced
    states and predictions the same; the policy in every control table and pair,
    in no prediction table; its episodes start where the true model's do."""
    from tasks.recording import rrd_contents
    from tests._seed_spread import assert_reads_the_run
    from tests._swingup import traced_main
    from tests.test_acrobot_swingup import TINY as SWINGUP
    from tests.test_methods import LINEAR, without

    assert SWINGUP.workers == 1  # the session's run (conftest.py): one process
    config = dataclasses.replace(SWINGUP, workers=2, methods=(SARSA, LINEAR))
    added = traced_main(config, tmp_path / "added")
    plain, run = tiny_swingup.results, added.results
    traced = [
        {(r.method, r.setting, r.trial): r for r in x.trials}
        for x in (tiny_swingup, added)
    ]
    a, b = plain.metrics, run.metrics
    assert "methods" not in a["environment"]
    assert set(b["environment"]["methods"]) == {"sarsa", "linear"}
    for m in (a, b):
        del m["seconds"], m["environment"]
    pairs = {
        "hipmdp - sarsa", "sarsa - average", "sarsa - true",
        "hipmdp - linear", "linear - average", "linear - true",
    }  # fmt: skip
    assert without(b, {"sarsa", "linear", *pairs}) == a
    for key in ("returns", "median_returns", "step_limit_rate", "margin_to_target"):
        assert set(b[key]) - set(a[key]) == {"sarsa", "linear"}, key
    for key in ("mse", "approximation_floor", "coverage", "loglik_difference"):
        assert "sarsa" not in b[key] and "sarsa" not in str(b[key]), key
    assert set(b["paired_difference"]) - set(a["paired_difference"]) == pairs
    assert {m for m, _, _ in traced[0]} == {"true", "average", "hipmdp"}
    for key, result in traced[0].items():
        other = traced[1][key]
        np.testing.assert_array_equal(result.returns, other.returns)
        for x, y in zip(result.traces or [], other.traces or [], strict=True):
            np.testing.assert_array_equal(x.states, y.states)
            np.testing.assert_array_equal(x.predicted, y.predicted)
    n = len(SWINGUP.test_masses)
    for i in range(n):
        for t in range(SWINGUP.n_trials):
            policy = traced[1][("sarsa", i, t)]
            assert policy.weight_means is None
            np.testing.assert_array_equal(policy.steps, -policy.returns)
    (trace_true, trace_policy) = (
        traced[1][(m, 0, 0)].traces for m in ("true", "sarsa")
    )
    assert len(trace_policy) == SWINGUP.transfer.n_episodes
    for x, y in zip(trace_true, trace_policy, strict=True):
        np.testing.assert_array_equal(x.states[0], y.states[0])  # paired starts
        assert y.predicted is None
    trials = np.load(run.out / "trials.npz")
    assert trials["methods"].tolist() == [
        "true",
        "average",
        "hipmdp",
        "sarsa",
        "linear",
    ]
    report = (run.out / "report.md").read_text()
    assert "sarsa (`tasks.methods:SarsaPolicy`, a policy, so not in the" in report
    assert "| hipmdp - sarsa |" in report
    entities = set(rrd_contents(run.out / "acrobot.rrd"))
    assert {"/rollout/sarsa/real", "/returns/sarsa"} <= entities
    assert "/rollout/sarsa/predicted" not in entities
    assert "/rollout/linear/predicted" in entities
    spread = assert_reads_the_run(run.out, tmp_path, "acrobot_swingup")
    labels = {n["label"] for n in spread["numbers"]}
    assert {"episodes to near-optimal, sarsa", "return, sarsa - true (trials)"} <= (
        labels
    )


def test_same_seed_same_policy_trial():
    """One policy trial run twice from the same job: the same returns and
    states."""
    from tasks.transfer import TrialJob, run_trial, set_models

    config = TransferConfig(n_episodes=2, max_steps=40, planning_max_steps=10)
    (policy,) = methods.fit_all(
        methods.load_all([SARSA], policies=True), batch(), 0, ACROBOT.n_actions
    )
    set_models(ACROBOT, config, None, None, added=(policy,))
    job = TrialJob(
        "sarsa",
        1,
        2,
        AcrobotParams(link_mass_1=0.9, link_mass_2=1.1),
        (5, (0, 1)),
        True,
    )
    first, second = run_trial(job), run_trial(job)
    np.testing.assert_array_equal(first.returns, second.returns)
    for x, y in zip(first.traces, second.traces, strict=True):
        np.testing.assert_array_equal(x.states, y.states)
    assert not np.array_equal(first.traces[0].states, first.traces[1].states)


def test_readmes_example_policy_runs_as_written(tmp_path, monkeypatch):
    """README's `pump.py`, saved where its command puts it, in a tiny swing-up
    run; the command parses as written."""
    import shlex

    from tasks.acrobot_swingup import main as swingup
    from tasks.acrobot_swingup import parse_args
    from tests.test_acrobot_swingup import TINY as SWINGUP
    from tests.test_docs import ROOT, python_block

    readme = ROOT / "README.md"
    code = python_block(readme, "#### A policy instead of a model")
    (tmp_path / "pump.py").write_text(code)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    command = next(
        line for line in readme.read_text().splitlines()
        if line.startswith("python -m tasks.acrobot_swingup") and "pump:" in line
    )  # fmt: skip
    config, out = parse_args(shlex.split(command)[3:])
    assert config.methods == ("pump=pump:Pump",) and str(out) == "runs/acro_pump"
    config = dataclasses.replace(SWINGUP, methods=config.methods, record=False)
    run = swingup(config, out=tmp_path / "run")
    assert set(run.metrics["returns"]) == {"true", "average", "hipmdp", "pump"}
    assert "pump" not in run.metrics["mse"]
    assert run.metrics["environment"]["methods"]["pump"] == {
        "module": "pump",
        "class": "pump.Pump",
        "file": str(tmp_path / "pump.py"),
        "sha256": hashlib.sha256(code.encode()).hexdigest(),
        "version": None,  # a file in the working directory, not a package
    }


def test_the_example_policies_pickle_for_worker_processes():
    """What --workers > 1 needs under spawn or forkserver (``must_pickle``):
    a fitted SarsaPolicy, and an agent mid-trial, survive a pickle round trip
    and act the same after it."""
    import pickle

    (policy,) = methods.fit_all(
        methods.load_all([SARSA], policies=True), batch(), 0, 3, pickled=True
    )
    agent = policy.agent((4, 0, 0))
    s = np.array([0.1, -0.2, 0.3, 0.4])
    policy.observe(agent, s, policy.act(agent, s, 3), -1.0, s + 0.1, False)
    twin = pickle.loads(pickle.dumps(agent))
    np.testing.assert_array_equal(twin.state.weights, agent.state.weights)
    for x in (agent, twin):
        policy.observe(x, s + 0.1, policy.act(x, s + 0.1, 3), -1.0, s, False)
    np.testing.assert_array_equal(twin.state.weights, agent.state.weights)
    assert methods.must_pickle(1) is False


class Unpicklable(Acts):
    def fit(self, batch, *, rng):
        self.hook = lambda: None  # a closure: deepcopy copies it, pickle cannot


def test_a_method_that_will_not_pickle_is_refused_when_workers_need_it():
    loaded = [(MethodSpec("u", "m", "A"), Unpicklable())]
    methods.fit_all(loaded, batch(), 0, 3)  # in one process: fine
    with pytest.raises(Exception, match="lambda") as err:
        methods.fit_all(loaded, batch(), 0, 3, pickled=True)
    assert "in method u: pickle.dumps of the fitted object" in "".join(
        err.value.__notes__
    )


class Outer:
    class Inner(Acts):
        pass


def test_provenance_says_nothing_of_a_source_file_that_is_gone(tmp_path, monkeypatch):
    """A class whose module's file is no longer there (deleted or moved after
    the import): no file, hash or version, and no error (provenance is
    bookkeeping and must not stop a run whose method loaded)."""
    import sys
    import types

    module = types.ModuleType("gone_method")
    module.__file__ = str(tmp_path / "gone_method.py")  # never written
    monkeypatch.setitem(sys.modules, "gone_method", module)
    gone = type("Gone", (Acts,), {"__module__": "gone_method"})()
    (entry,) = methods.provenance(
        [(MethodSpec("g", "gone_method", "G"), gone)]
    ).values()
    assert entry == {
        "module": "gone_method", "class": "gone_method.Gone", "file": None,
        "sha256": None, "version": None,
    }  # fmt: skip


def test_a_relative_installed_location_is_not_read_against_the_cwd(
    tmp_path, monkeypatch
):
    """_version_holding: a distribution whose files locate as relative paths
    (some editable installs) would claim any file of that name in the working
    directory; the same file located absolutely is the distribution's."""
    from pathlib import Path

    (tmp_path / "mine.py").write_text("")
    monkeypatch.chdir(tmp_path)

    class Dist:
        version, files = "1.0", ["mine.py"]

        def __init__(self, root):
            self.root = root

        def locate_file(self, name):
            return Path(self.root) / name

    distributions = {"mine": ["mine"]}
    monkeypatch.setattr(
        methods.metadata, "packages_distributions", lambda: distributions
    )
    for root, expected in [("", None), (tmp_path, "1.0")]:
        monkeypatch.setattr(
            methods.metadata, "distribution", lambda _, root=root: Dist(root)
        )
        assert methods._version_holding(str(tmp_path / "mine.py"), "mine") == expected


def test_provenance_names_the_class_its_file_and_nothing_it_cannot_tell():
    import numpy

    (entry,) = methods.provenance(
        [(MethodSpec("s", "tasks.methods", "X"), SarsaPolicy())]
    ).values()
    assert entry["class"] == "tasks.methods.SarsaPolicy"
    assert entry["file"] == str(methods.Path(methods.__file__).resolve())
    assert (
        entry["sha256"]
        == hashlib.sha256(methods.Path(methods.__file__).read_bytes()).hexdigest()
    )
    dynamic = type("Dynamic", (Acts,), {"__module__": "not_a_module"})()
    (entry,) = methods.provenance([(MethodSpec("d", "x", "Y"), dynamic)]).values()
    assert entry == {
        "module": "x", "class": "not_a_module.Dynamic", "file": None,
        "sha256": None, "version": None,
    }  # fmt: skip
    # a class nested in another is named by its qualified name, as it is found
    (entry,) = methods.provenance([(MethodSpec("n", "x", "Y"), Outer.Inner())]).values()
    assert entry["class"] == f"{__name__}.Outer.Inner"
    # a class of an installed package's submodule: that package's version
    (entry,) = methods.provenance(
        [(MethodSpec("g", "numpy", "random.default_rng"), np.random.default_rng(0))]
    ).values()
    assert entry["version"] == numpy.__version__ and entry["sha256"] is not None
    # an installed package's own file gets its version; another file, none
    assert methods._version_holding(numpy.__file__, "numpy") == numpy.__version__
    assert methods._version_holding(__file__, "numpy") is None
