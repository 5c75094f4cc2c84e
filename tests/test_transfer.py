"""The transfer trial's protocol (tasks/transfer.py) on tiny trials: where
planning starts, which streams a trial draws, what an added method and a
policy are given, and what the recording shows at each step."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
import pytest

from hipmdp.data import Transitions
from tasks import acrobot, methods, transfer
from tasks.acrobot import AcrobotParams
from tasks.agents import ACROBOT
from tasks.methods import Added, MethodSpec
from tasks.transfer import TransferConfig, TrialJob, run_trial, set_models, trial_label

PARAMS = AcrobotParams(link_mass_1=0.9, link_mass_2=1.1)
#: real episodes of 5 steps (no random start swings up that fast), little planning
TINY = TransferConfig(
    n_episodes=3, max_steps=5, planning_max_steps=3, n_start_states=4,
    initial_planning_episodes=1, planning_episodes=1,
)  # fmt: skip


def batch():
    """A small batch shaped as the acrobot's: 4-D states, actions 0, 1, 2."""
    rng = np.random.default_rng(0)
    s = rng.normal(size=(20, 4))
    return Transitions(
        s, rng.integers(3, size=20), s + 0.01, np.zeros(20, int), rewards=-np.ones(20)
    )


def spy_on_plan(monkeypatch) -> list:
    """Record each planning's start states and its rng's state as it begins."""
    real, calls = transfer.plan, []

    def spying(state, basis, sarsa, model, task, starts, n_episodes, *, rng):
        calls.append((np.array(starts), rng.bit_generator.state["state"]))
        return real(state, basis, sarsa, model, task, starts, n_episodes, rng=rng)

    monkeypatch.setattr(transfer, "plan", spying)
    return calls


def test_planning_starts_from_reset_states_and_each_real_episodes_first(monkeypatch):
    """The start states: n_start_states reset states, then the first state of
    every real episode so far, in order."""
    calls = spy_on_plan(monkeypatch)
    set_models(ACROBOT, TINY, None, None)
    result = run_trial(TrialJob("true", 0, 0, PARAMS, (5, (0, 0)), True))
    assert [len(starts) for starts, _ in calls] == [4, 5, 6]  # none after the last
    firsts = np.array([trace.states[0] for trace in result.traces])
    for e, (starts, _) in enumerate(calls):
        np.testing.assert_array_equal(starts[4:], firsts[:e])
    assert len({tuple(s) for s in calls[0][0]} | {tuple(s) for s in firsts}) == 7


def test_the_environment_starts_and_agent_draw_from_three_streams(monkeypatch):
    """The real environment's seed, the planning starts' environment's seed and
    the agent's stream are three different children of the trial's seed."""
    calls = spy_on_plan(monkeypatch)
    seeds = []

    def make_env(params, *, seed, **kwargs):
        if isinstance(seed, np.random.Generator):  # not the simulator model's
            seeds.append(seed.bit_generator.state["state"])
        return acrobot.swingup(params, seed=seed, **kwargs)

    domain = dataclasses.replace(ACROBOT, make_env=make_env)
    set_models(domain, dataclasses.replace(TINY, n_episodes=1), None, None)
    run_trial(TrialJob("true", 0, 0, PARAMS, (5, (0, 0)), False))
    agent = calls[0][1]  # before its first draw
    assert len(seeds) == 2
    assert len({str(s) for s in (*seeds, agent)}) == 3


def test_the_value_function_passes_from_each_planning_to_the_next_real_episode(
    monkeypatch,
):
    """One value function runs through the trial: each real episode starts from
    the value function the planning before it left, and each planning from the
    one the real episode before it left (what the agent learnt acting on the
    instance is kept); each planning runs its configured number of episodes
    (initial, after the first real episode, after the others)."""
    calls, episodes = [], []
    real_plan, real_episode = transfer.plan, transfer.run_episode

    def planning(state, *args, rng):
        result = real_plan(state, *args, rng=rng)
        calls.append((state, args[-1], result.state))  # args[-1]: n_episodes
        return result

    def acting(env, basis, sarsa, state, *, rng):
        episode = real_episode(env, basis, sarsa, state, rng=rng)
        episodes.append((state, episode.state))
        return episode

    monkeypatch.setattr(transfer, "plan", planning)
    monkeypatch.setattr(transfer, "run_episode", acting)
    config = dataclasses.replace(
        TINY, initial_planning_episodes=2, first_planning_episodes=3
    )
    set_models(ACROBOT, config, CountingHipMDP(), None)
    run_trial(TrialJob("hipmdp", 0, 0, PARAMS, (5, (0, 0)), False))
    assert [n for _, n, _ in calls] == [2, 3, 1]  # none after the last episode
    for e, (before, after) in enumerate(episodes):
        assert before is calls[e][2]
        assert not np.array_equal(after.weights, before.weights)  # it learnt
        if e + 1 < len(calls):
            assert calls[e + 1][0] is after


class Remembers:
    """A model that counts its adapt calls on itself and records, on the class,
    what each call saw: that count, the number of transitions and their ids."""

    seen: list = []

    def fit(self, batch, *, rng):
        self.calls = 0

    def adapt(self, train, *, rng):
        Remembers.seen.append((self.calls, len(train), np.unique(train.instances)))
        self.calls += 1
        return self

    def predict(self, states, actions):
        return np.zeros(states.shape), np.ones(states.shape)


def test_an_added_model_adapts_per_trial_on_a_fresh_copy_to_one_instance():
    """Each trial adapts a fresh copy of the fitted method (what adapt keeps on
    the object does not reach the next trial), to all the trial's real
    transitions so far as one instance, id 0."""
    loaded = [(MethodSpec("r", "m", "A"), Remembers())]
    set_models(ACROBOT, TINY, None, None, added=methods.fit_all(loaded, batch(), 0))
    for trial in (0, 1):
        Remembers.seen = []
        result = run_trial(TrialJob("r", 0, trial, PARAMS, (5, (0, trial)), False))
        sizes = np.cumsum([0, *result.steps[:-1]])
        assert [(c, n) for c, n, _ in Remembers.seen] == list(enumerate(sizes))
        assert all(set(ids) <= {0} for *_, ids in Remembers.seen)


class FailsAfterAnEpisode(Remembers):
    """Adapts to no transitions (a trial's first planning), and raises on any."""

    def adapt(self, train, *, rng):
        if len(train):
            raise KeyError("no adapt on real transitions")
        return self


def test_an_error_in_adapt_during_a_trial_names_the_setting_and_trial():
    # not through fit_all, whose try adapts to batch transitions
    added = Added(MethodSpec("late", "m", "A"), FailsAfterAnEpisode(), 0)
    set_models(ACROBOT, TINY, None, None, added=(added,))
    with pytest.raises(KeyError, match="no adapt on real") as err:
        run_trial(TrialJob("late", 2, 1, PARAMS, (5, (2, 1)), False))
    note = "".join(err.value.__notes__)
    assert "in method late: adapt" in note
    assert "after 1 real episodes; setting 2, trial 1" in note


class Belief(NamedTuple):
    mean: np.ndarray
    cov: np.ndarray


class CountingHipMDP:
    """A stand-in HiP-MDP whose belief counts the transitions it has filtered
    (mean (n,), variance 1 / (1 + n)) and whose prediction is Δs = 0.001 n in
    every dimension."""

    def prior(self):
        return Belief(np.zeros(1), np.eye(1))

    def update(self, belief, data):
        n = belief.mean[0] + len(data)
        return Belief(np.array([n]), np.eye(1) / (1.0 + n))

    def predict(self, states, actions, belief):
        mean = np.full(np.shape(states), 1e-3 * belief.mean[0])
        return mean, np.ones_like(mean)


def test_a_recorded_episode_shows_the_belief_and_prediction_of_each_step():
    """Step t's recorded prediction is the model's with the belief filtered on
    the t transitions before it (the episode's and all earlier ones), and the
    recorded belief after t transitions is that belief: its mean and its
    standard deviation (the recording draws ±2σ), not its variance."""
    set_models(ACROBOT, TINY, CountingHipMDP(), None)
    result = run_trial(TrialJob("hipmdp", 0, 0, PARAMS, (5, (0, 0)), True))
    before = 0
    for trace in result.traces:
        steps = len(trace.predicted)
        counts = before + np.arange(steps + 1)
        np.testing.assert_array_equal(trace.belief_mean[:, 0], counts)
        np.testing.assert_allclose(trace.belief_std[:, 0], 1 / np.sqrt(1 + counts))
        velocities = trace.predicted[:, 2:] - trace.states[:-1, 2:]
        expected = np.repeat(1e-3 * counts[:-1, None], 2, axis=1)
        np.testing.assert_allclose(velocities, expected, atol=1e-12)
        before += steps
    np.testing.assert_array_equal(result.weight_means[:, 0], [0, 5, 10, 15])


class Watching:
    """A policy's agent that records every act and observe call."""

    def __init__(self):
        self.calls = []

    def act(self, state):
        self.calls.append(("act", state))
        return 1

    def observe(self, state, action, reward, next_state, terminal):
        self.calls.append(("observe", state, next_state, terminal))


def test_a_policy_sees_each_state_as_it_acts_and_each_transition_it_made():
    """In a policy's episode, act gets s_t and observe (s_t, a_t, r, s_t+1,
    terminal), terminal False at the step limit."""
    env = acrobot.swingup(PARAMS, seed=np.random.default_rng(0), max_steps=4)
    agent = Watching()
    added = Added(MethodSpec("w", "m", "A"), None, 0)
    states, rewards = transfer._policy_episode(env, agent, added, 3)
    assert len(states) == 5 and len(rewards) == 4
    for t in range(4):
        (act, s), (observe, s_obs, s_next, terminal) = agent.calls[2 * t : 2 * t + 2]
        assert (act, observe, terminal) == ("act", "observe", False)
        np.testing.assert_array_equal(s, states[t])
        np.testing.assert_array_equal(s_obs, states[t])
        np.testing.assert_array_equal(s_next, states[t + 1])


@pytest.mark.parametrize(
    "field", ["n_episodes", "n_start_states", "max_steps", "planning_max_steps"]
)
def test_a_size_of_zero_is_refused_on_construction(field):
    """Each of these must be at least 1 (no start states leaves planning
    nowhere to begin; no steps, no episode): refused as the config is made,
    naming the field, not minutes into a run."""
    with pytest.raises(ValueError, match=f"^{field}: expected >= 1"):
        dataclasses.replace(TINY, **{field: 0})


def test_only_the_hipmdp_has_weight_means():
    """A trial's weight_means is the HiP-MDP's belief mean before and after each
    real episode, shape (E + 1, K); the other methods have no belief: None, not
    an empty array."""
    set_models(ACROBOT, dataclasses.replace(TINY, n_episodes=1), CountingHipMDP(), None)
    true = run_trial(TrialJob("true", 0, 0, PARAMS, (5, (0, 0)), False))
    hip = run_trial(TrialJob("hipmdp", 0, 0, PARAMS, (5, (0, 0)), False))
    assert true.weight_means is None
    assert hip.weight_means.shape == (2, 1)


def test_an_unknown_method_is_refused_naming_the_known_ones():
    """A misspelt method must not run as some other method's trial."""
    set_models(ACROBOT, TINY, CountingHipMDP(), None)
    with pytest.raises(ValueError, match=r"^method: expected one of \('true', "):
        run_trial(TrialJob("HiP-MDP", 0, 0, PARAMS, (5, (0, 0)), False))


def test_a_trial_label_names_method_setting_and_trial_from_0():
    job = TrialJob("NAME", 3, 0, PARAMS, (5, (3, 0)), False)
    assert trial_label(job) == "NAME, setting 3, trial 0"
