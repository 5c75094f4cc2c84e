"""Agents on live MuJoCo instances: Sarsa(λ) learns both tasks, the true-simulator
model steps exactly as the environment, and planning on it helps a fresh agent."""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest
from scipy import stats

from hipmdp.data import ParameterTable, Transitions
from hipmdp.planning import plan
from hipmdp.sarsa import SarsaState, epsilon_greedy, init_state, sarsa_update
from tasks import acrobot, cartpole
from tasks.agents import (
    ACROBOT,
    CARTPOLE,
    EnergyConserving,
    SimulatorModel,
    learn,
    run_episode,
)
from tasks.batch import gather_batch


class Recording:
    """Wraps a model and keeps every (states, actions, next_states) call."""

    def __init__(self, model):
        self.model, self.calls = model, []

    def predict(self, states, actions):
        out = self.model.predict(states, actions)
        self.calls.append((states.copy(), actions.copy(), out.copy()))
        return out


def test_sarsa_balances_the_nominal_cartpole() -> None:
    """The issue's threshold: ≥ 195 mean steps over the last 10 of ≤ 300 episodes
    (here 50), domain defaults, one fixed seed."""
    env = cartpole.balance(seed=0)
    result = learn(env, CARTPOLE, 50, rng=np.random.default_rng(0))
    assert result.steps[-10:].mean() >= 195.0
    assert result.steps.max() <= cartpole.DEFAULT_MAX_STEPS


def test_sarsa_swings_up_the_nominal_acrobot() -> None:
    """The issue's threshold: a mean of ≤ 200 steps to goal over the last 10 of 50
    episodes, order-5 basis and domain defaults, one fixed seed."""
    env = acrobot.swingup(seed=0)
    result = learn(env, ACROBOT, 50, rng=np.random.default_rng(0))
    assert result.steps[0] > 200  # the untrained agent does not swing up quickly
    assert result.steps[-10:].mean() <= 200.0
    # every episode under the limit ended at the goal, so its return is -steps
    np.testing.assert_array_equal(result.returns, -result.steps)


@pytest.mark.parametrize(
    ("domain", "params"),
    [
        (CARTPOLE, None),
        (CARTPOLE, cartpole.CartpoleParams(pole_mass=0.3, pole_half_length=0.4)),
        (ACROBOT, None),
        (ACROBOT, acrobot.AcrobotParams(link_mass_1=1.3, link_mass_2=0.7)),
    ],
    ids=["cartpole", "cartpole-heavy-short", "acrobot", "acrobot-1.3-0.7"],
)
def test_simulator_model_steps_exactly_as_the_environment(domain, params) -> None:
    rng = np.random.default_rng(1)
    env = domain.make_env(params, seed=1)
    model = SimulatorModel(domain, params)
    time_step = env.reset()
    states, actions, next_states = [], [], []
    while not time_step.last() and len(actions) < 60:
        a = int(rng.integers(domain.n_actions))
        states.append(time_step.observation["state"])
        time_step = env.step(a)
        actions.append(a)
        next_states.append(time_step.observation["state"])
    states, actions = np.array(states), np.array(actions)
    got = model.predict(states, actions)
    # The environment's qpos keeps unwrapped angles, the model starts from wrapped
    # ones: the trigonometry differs by round-off only.
    np.testing.assert_allclose(got, np.array(next_states), rtol=0, atol=1e-12)
    if params is not None:  # the instance matters: the nominal model differs
        nominal = SimulatorModel(domain).predict(states, actions)
        assert np.abs(nominal - got).max() > 1e-4
    # a batch is the same as its rows one at a time
    for n in (0, len(actions) - 1):
        np.testing.assert_array_equal(got[n], model.step(states[n], int(actions[n])))


def _episode_by_hand(env, basis, config, weights, rng):
    """Sarsa(λ) on a live environment from ``sarsa_update`` alone: a' is drawn
    once per step, used in the update and then acted on; the last step
    bootstraps unless the episode ended in a terminal state (dm_env discount 0)."""
    state = SarsaState(weights, np.zeros_like(weights))
    alphas = config.alpha * basis.step_scale
    time_step = env.reset()
    phi = basis(time_step.observation["state"])
    a = epsilon_greedy(state.weights @ phi, config.epsilon, rng=rng)
    actions = []
    while True:
        time_step = env.step(a)
        actions.append(a)
        phi2 = basis(time_step.observation["state"])
        a2 = epsilon_greedy(state.weights @ phi2, config.epsilon, rng=rng)
        ends = time_step.last()
        bootstrap = not (ends and time_step.discount == 0.0)
        state = sarsa_update(state, phi, a, float(time_step.reward),
                             phi2 if bootstrap else None, a2, alphas,
                             config).state  # fmt: skip
        if ends:
            return state.weights, actions, not bootstrap
        phi, a = phi2, a2


@pytest.mark.parametrize(
    ("max_steps", "terminal"),
    [(5, False), (1000, True)],  # cut at the step limit / the pole falls
    ids=["step-limit", "terminal"],
)
def test_run_episode_is_sarsa_by_hand(max_steps, terminal) -> None:
    """An exploring agent (ε = 0.5) on the cart-pole: run_episode's weights,
    actions and end equal the hand-written loop's, for an episode cut at the step
    limit (which bootstraps) and one that ends with the pole down (which does
    not). Random weights: the values at s' matter, so a missing or extra
    bootstrap shows."""
    basis = CARTPOLE.basis()
    config = dataclasses.replace(CARTPOLE.sarsa, epsilon=0.5)
    weights = np.random.default_rng(0).normal(size=(2, basis.n_features))
    out = run_episode(
        CARTPOLE.make_env(None, seed=4, max_steps=max_steps), basis, config,
        SarsaState(weights, np.zeros_like(weights)), rng=np.random.default_rng(5),
    )  # fmt: skip
    expect, actions, ended_terminal = _episode_by_hand(
        CARTPOLE.make_env(None, seed=4, max_steps=max_steps), basis, config,
        weights, np.random.default_rng(5),
    )  # fmt: skip
    assert ended_terminal == terminal == out.terminal
    assert len(actions) == (max_steps if not terminal else len(out.actions)) > 1
    np.testing.assert_array_equal(out.actions, actions)
    np.testing.assert_allclose(out.state.weights, expect, rtol=0, atol=1e-12)


def test_planner_model_calls_match_the_simulator_step_for_step() -> None:
    """Plan one episode on the true model from a real initial state, then replay the
    planner's actions on the real environment: every predicted state equals the
    environment's, and the episode ends at the same step for the same reason."""
    basis = ACROBOT.basis()
    s0 = acrobot.swingup(seed=3).reset().observation["state"]
    model = Recording(SimulatorModel(ACROBOT))
    task = ACROBOT.planning_task(None, 500)
    out = plan(init_state(3, basis.n_features), basis, ACROBOT.sarsa, model, task,
               s0[None], 1, rng=np.random.default_rng(3))  # fmt: skip
    assert len(model.calls) == out.steps[0] > 1
    env = acrobot.swingup(seed=3, max_steps=500)
    time_step = env.reset()
    np.testing.assert_array_equal(time_step.observation["state"], s0)
    for t, (s, a, s2) in enumerate(model.calls):
        assert s.shape == (1, 4) and a.shape == (1,)
        np.testing.assert_allclose(s[0], time_step.observation["state"], atol=1e-9)
        time_step = env.step(int(a[0]))
        np.testing.assert_allclose(s2[0], time_step.observation["state"], atol=1e-9)
        assert time_step.last() == (t == len(model.calls) - 1)
    assert bool(out.reached[0]) == (time_step.discount == 0.0)


def test_planning_on_the_true_simulator_improves_the_first_real_episode() -> None:
    """Fresh agents on six seeds: the first real episode's steps to goal with 10
    planning episodes on the true model from the real initial state, against the
    same agent (same environment seed and exploration stream) without planning.
    Paired: the one-sided 99% Student-t bound on the mean difference (with −
    without, 5 degrees of freedom) must be below 0."""
    basis = ACROBOT.basis()
    model = SimulatorModel(ACROBOT)
    task = ACROBOT.planning_task(None, ACROBOT.max_steps)
    without, with_planning = [], []
    for seed in range(6):
        fresh = init_state(3, basis.n_features)
        env = acrobot.swingup(seed=seed)
        episode = run_episode(env, basis, ACROBOT.sarsa, fresh,
                              rng=np.random.default_rng(seed))  # fmt: skip
        without.append(len(episode.actions))
        s0 = acrobot.swingup(seed=seed).reset().observation["state"]
        planned = plan(fresh, basis, ACROBOT.sarsa, model, task, s0[None], 10,
                       rng=np.random.default_rng(100 + seed)).state  # fmt: skip
        env = acrobot.swingup(seed=seed)
        episode = run_episode(env, basis, ACROBOT.sarsa, planned,
                              rng=np.random.default_rng(seed))  # fmt: skip
        with_planning.append(len(episode.actions))
    diff = np.array(with_planning, float) - np.array(without, float)
    upper = diff.mean() + stats.t.ppf(0.99, df=len(diff) - 1) * stats.sem(diff)
    assert upper < 0, (with_planning, without)


def test_gather_batch_returns_consistent_transitions() -> None:
    def gather(workers):
        return gather_batch(
            "cartpole", [cartpole.CartpoleParams(pole_mass=0.3)] * 2,
            repetitions=2, episodes=3, max_steps=40,
            seed=np.random.SeedSequence(5), workers=workers,
        )  # fmt: skip

    data = gather(workers=1)
    assert isinstance(data, Transitions)
    assert data.dones.sum() == 2 * 2 * 3  # instances x repetitions x episodes
    np.testing.assert_array_equal(data.instance_ids, [0, 1])
    assert data.angle_dims == cartpole.ANGLE_DIMS and data.dt == 0.02
    # within an episode each next state is the following state
    inside = ~data.dones[:-1]
    np.testing.assert_array_equal(
        data.next_states[:-1][inside], data.states[1:][inside]
    )
    # reward 1 until failure; episode lengths within the limit
    ends = np.flatnonzero(data.dones)
    lengths = np.diff(np.concatenate([[-1], ends]))
    assert lengths.max() <= 40
    failed = cartpole.failed(data.next_states)
    np.testing.assert_array_equal(data.rewards, np.where(failed, 0.0, 1.0))
    # the same seed gives the same data, whatever the number of processes
    again = gather(workers=2)
    np.testing.assert_array_equal(again.states, data.states)


def test_each_instance_and_repetition_is_one_job_with_its_own_seed(
    monkeypatch, tmp_path
):
    """gather_and_save runs config.batch_repetitions agents per instance, each
    learning config.batch_episodes episodes of at most config.batch_max_steps,
    job (b, r) seeded with child b * repetitions + r of the seed (its entropy
    and spawn key), the jobs' transitions kept in job order; an instance that
    diverges stops the batch, naming it, rather than being left out of it."""
    from types import SimpleNamespace

    from tasks import batch
    from tasks.collect import Divergence

    real, calls, parts = batch.collect_sarsa, [], []

    def spying(domain, instances, *, episodes_per_instance, rng, **kwargs):
        seed_seq = rng.bit_generator.seed_seq
        calls.append((episodes_per_instance, kwargs["max_steps"], seed_seq.entropy,
                      seed_seq.spawn_key))  # fmt: skip
        out = real(
            domain, instances, episodes_per_instance=episodes_per_instance,
            rng=rng, **kwargs,
        )  # fmt: skip
        parts.append(out.transitions)
        return out

    monkeypatch.setattr(batch, "collect_sarsa", spying)
    config = SimpleNamespace(
        batch_repetitions=2, batch_episodes=3, batch_max_steps=20, workers=1
    )
    params = [cartpole.CartpoleParams(pole_mass=0.3)] * 2
    data = batch.gather_and_save(
        "cartpole", params, tmp_path / "batch.npz", config=config,
        seed=np.random.SeedSequence(5, spawn_key=(7,)), progress=False,
    )  # fmt: skip
    assert calls == [(3, 20, 5, (7, k)) for k in range(4)]
    np.testing.assert_array_equal(
        data.states, np.concatenate([p.states for p in parts])
    )
    assert data.dones.sum() == 2 * 2 * 3
    assert np.diff(np.flatnonzero(data.dones), prepend=-1).max() <= 20
    saved = Transitions.load(tmp_path / "batch.npz")
    np.testing.assert_array_equal(saved.states, data.states)
    table = ParameterTable.load(tmp_path / "batch.npz")
    np.testing.assert_array_equal(table.instances, [0, 1])

    def diverging(domain, instances, **kwargs):
        out = real(domain, instances, **kwargs)
        if kwargs["instance_ids"] == [1]:
            out = out._replace(diverged=(Divergence(1, -1, -1, "MuJoCo warning"),))
        return out

    monkeypatch.setattr(batch, "collect_sarsa", diverging)
    with pytest.raises(RuntimeError, match="cartpole instance 1 diverged"):
        batch.gather_batch(
            "cartpole", params, repetitions=1, episodes=1, max_steps=5,
            seed=np.random.SeedSequence(5),
        )  # fmt: skip


def test_parameter_table_rows_are_the_instances_in_order():
    """Row b of the parameter table (saved beside the batch) is instance b's
    parameters (the data's id b)."""
    from tasks.batch import parameter_table

    light, heavy = (cartpole.CartpoleParams(pole_mass=m) for m in (0.3, 0.5))
    table = parameter_table([light, light, heavy])
    np.testing.assert_array_equal(table.instances, [0, 1, 2])
    column = table.values[:, list(table.names).index("pole_mass")]
    np.testing.assert_array_equal(column, [0.3, 0.3, 0.5])


def test_the_domains_defaults_are_the_module_docstrings_table():
    """Order, α, λ, γ, ε and q₀ of each domain as tasks/agents.py's table gives
    them; the normalisation boxes as it names them, symmetric about 0."""
    from tasks import agents

    rows = {
        line.split()[0]: line.split()
        for line in agents.__doc__.splitlines()
        if line.split()[:1] in (["cartpole"], ["acrobot"])
    }
    for name, domain in agents.DOMAINS.items():
        row = rows[name]
        sarsa = domain.sarsa
        assert domain.order == int(row[1]), name
        assert (sarsa.alpha, sarsa.lam, sarsa.gamma, sarsa.epsilon) == tuple(
            map(float, row[-5:-1])
        ), name
        assert domain.initial_value == float(row[-1]), name
        np.testing.assert_array_equal(domain.low, -np.array(domain.high))
    np.testing.assert_allclose(CARTPOLE.high, (2.4, np.deg2rad(12), 2.5, 3.5))
    np.testing.assert_allclose(ACROBOT.high, (np.pi, np.pi, 4 * np.pi, 9 * np.pi))


def test_an_episode_that_does_not_learn_leaves_the_weights_and_learn_needs_one():
    basis = CARTPOLE.basis()
    config = dataclasses.replace(CARTPOLE.sarsa, epsilon=0.5)
    weights = np.random.default_rng(0).normal(size=(2, basis.n_features))
    out = run_episode(
        CARTPOLE.make_env(None, seed=4, max_steps=5), basis, config,
        SarsaState(weights, np.zeros_like(weights)), rng=np.random.default_rng(5),
        learn=False,
    )  # fmt: skip
    assert len(out.actions) == 5
    np.testing.assert_array_equal(out.state.weights, weights)
    with pytest.raises(ValueError, match="n_episodes: expected >= 1, got 0"):
        learn(CARTPOLE.make_env(None, seed=4), CARTPOLE, 0, rng=np.random.default_rng())
    # 2.5 was a TypeError from range(), True one episode
    for bad in (2.5, True):
        with pytest.raises(ValueError, match="n_episodes: expected an integer"):
            learn(
                CARTPOLE.make_env(None, seed=4),
                CARTPOLE,
                bad,
                rng=np.random.default_rng(),
            )


def test_learn_takes_its_config_and_starting_agent():
    """``config`` overrides the domain's hyperparameters and ``state`` is where
    the agent starts: learn is then run_episode after run_episode with them."""
    exploring = dataclasses.replace(CARTPOLE.sarsa, epsilon=0.5, alpha=0.01)
    start = init_state(2, CARTPOLE.basis().n_features, 7.0)
    result = learn(
        CARTPOLE.make_env(None, seed=4, max_steps=10), CARTPOLE, 2,
        rng=np.random.default_rng(0), config=exploring, state=start,
    )  # fmt: skip
    env = CARTPOLE.make_env(None, seed=4, max_steps=10)
    rng, state = np.random.default_rng(0), start
    for _ in range(2):
        state = run_episode(env, CARTPOLE.basis(), exploring, state, rng=rng).state
    np.testing.assert_array_equal(result.state.weights, state.weights)


def _cartpole_learning(limit=25):
    """A fresh agent's first episodes on the cart-pole: the first two end with
    the pole down (23 and 9 steps), the others at the step limit of 25."""
    env = CARTPOLE.make_env(None, seed=1, max_steps=limit)
    return learn(env, CARTPOLE, 6, rng=np.random.default_rng(0))


def test_learns_returns_are_each_episodes_rewards():
    """The cart-pole pays 1 per step and 0 for the step that drops the pole: an
    episode's return is its steps, less 1 if it ended with the pole down (on the
    acrobot, -1 per step, the return is -steps whatever the end, so it cannot
    tell a return from a step count)."""
    result = _cartpole_learning()
    fell = result.steps < 25
    assert fell.any() and not fell.all()
    np.testing.assert_array_equal(result.returns, result.steps - fell)


def test_the_cartpole_planning_task_pays_and_ends_as_the_environment():
    """On the real transitions of episodes that drop the pole and episodes cut
    at the step limit: the planning task's reward is the environment's, and it
    is terminal exactly at the last step of the episodes that dropped the pole."""
    result = _cartpole_learning()
    t = result.transitions
    task = CARTPOLE.planning_task(None, 25)
    np.testing.assert_array_equal(task.reward(t.states, t.actions, t.next_states),
                                  t.rewards)  # fmt: skip
    ends = np.flatnonzero(t.dones)
    fell = ends[result.steps < 25]
    assert len(fell) == 2 and 0.0 in t.rewards
    np.testing.assert_array_equal(np.flatnonzero(task.terminal(t.next_states)), fell)


def test_the_acrobot_planning_task_ends_at_its_instances_goal():
    """The goal is the tip above ``l₁``, with the instance's links: at θ₁ = π/2,
    θ₂ = 2π/3 the tip is ``-l₂ cos(7π/6) = 0.866 l₂`` above the shoulder, below
    the nominal ``l₁ = 1`` but above it with ``l₂ = 1.5`` (1.30). Every step
    costs 1."""
    state = np.array([[np.pi / 2, 2 * np.pi / 3, 0.0, 0.0]])
    long_arm = acrobot.AcrobotParams(link_length_2=1.5)
    for params, reached in ((None, False), (long_arm, True)):
        task = ACROBOT.planning_task(params, 500)
        np.testing.assert_array_equal(task.terminal(state), [reached])
        np.testing.assert_array_equal(task.reward(state, np.zeros(1, int), state), [-1])


def test_the_energy_conserving_model_predicts_the_given_actions():
    """It rescales the wrapped model's prediction for the same states and
    actions. (The energy check in test_acrobot_energy cannot tell: a prediction
    for any action can be rescaled to the given torque's work.)"""
    inner = Recording(SimulatorModel(ACROBOT))
    states = np.random.default_rng(0).uniform(-1, 1, (4, 4))
    actions = np.array([0, 1, 2, 2])
    EnergyConserving(inner, acrobot.AcrobotParams()).predict(states, actions)
    ((seen_states, seen_actions, _),) = inner.calls
    np.testing.assert_array_equal(seen_states, states)
    np.testing.assert_array_equal(seen_actions, actions)


def test_the_simulator_model_refuses_states_of_another_dimension():
    with pytest.raises(ValueError, match=r"states: expected shape \(N, 4\), got"):
        SimulatorModel(ACROBOT).predict(np.zeros((2, 3)), np.zeros(2, int))


@pytest.mark.parametrize("actions", [np.zeros(3, int), np.zeros((2, 1), int)])
def test_the_simulator_model_refuses_actions_not_one_per_state(actions):
    """Three actions for two states would step the first two and ignore the
    third; a column of actions would be read row by row."""
    with pytest.raises(ValueError, match=r"actions: expected shape \(2,\), got"):
        SimulatorModel(ACROBOT).predict(np.zeros((2, 4)), actions)


def test_a_greedy_agent_acts_on_the_state_it_is_in():
    """ε = 0 and fixed weights: every action is ``argmax_a θ φ(s_t)`` of the state
    it is taken in, not of the one before. Consecutive states are close, so a
    one-step lag only shows where the greedy action switches: these random
    weights (on the cart-pole) make it switch often."""
    basis = CARTPOLE.basis()
    config = dataclasses.replace(CARTPOLE.sarsa, epsilon=0.0)
    weights = np.random.default_rng(3).normal(size=(2, basis.n_features))
    out = run_episode(
        CARTPOLE.make_env(None, seed=2), basis, config,
        SarsaState(weights, np.zeros_like(weights)), rng=np.random.default_rng(1),
        learn=False,
    )  # fmt: skip
    greedy = [int(np.argmax(weights @ basis(s))) for s in out.states[:-1]]
    np.testing.assert_array_equal(out.actions, greedy)
    assert np.count_nonzero(np.diff(greedy)) > 10  # the policy does switch


def test_an_episode_starts_with_no_eligibility_traces():
    """Traces belong to one episode (Sutton & Barto §7.5): an agent handed over
    with traces left from an earlier episode learns exactly as one without."""
    basis = CARTPOLE.basis()
    config = dataclasses.replace(CARTPOLE.sarsa, epsilon=0.5)
    rng = np.random.default_rng(0)
    weights = rng.normal(size=(2, basis.n_features))
    stale = rng.normal(size=weights.shape)
    out = {}
    for name, traces in (("stale", stale), ("none", np.zeros_like(weights))):
        out[name] = run_episode(
            CARTPOLE.make_env(None, seed=4, max_steps=5), basis, config,
            SarsaState(weights, traces), rng=np.random.default_rng(5),
        ).state.weights  # fmt: skip
    assert not np.array_equal(out["none"], weights)  # it did learn
    np.testing.assert_array_equal(out["stale"], out["none"])


@pytest.mark.parametrize("domain", [CARTPOLE, ACROBOT], ids=lambda d: d.name)
def test_the_domains_step_limit_is_its_tasks(domain):
    """collect_sarsa's default limit is ``domain.max_steps``, collect's the
    environment's own: the two gatherers must stop episodes at the same step."""
    default = inspect.signature(domain.make_env).parameters["max_steps"].default
    assert domain.max_steps == default
    assert domain.make_env(None, seed=0).task.max_steps == default
