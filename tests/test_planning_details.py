"""Sarsa and planning details the tabular and corridor tests cannot see (found by
a mutation review): per-feature step sizes, replacing traces with negative
features in both update paths, the episode count and start rows of `plan`,
the reward's argument order, terminal against truncated at the step limit,
exploration in planning, and wrapped open-loop errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hipmdp.data import Transitions, wrap_angle
from hipmdp.fourier import FourierBasis
from hipmdp.planning import (
    LearnedModel,
    PlanningTask,
    SimulatedEpisodes,
    StepwiseModel,
    open_loop_errors,
    plan,
    run_sarsa_episodes,
)
from hipmdp.sarsa import (
    SarsaConfig,
    SarsaState,
    init_state,
    sarsa_update,
    sarsa_update_batch,
)
from tests.test_planning import CORRIDOR_TASK as TASK
from tests.test_planning import Corridor as CorridorModel
from tests.test_planning import PlainModel


class Corridor(CorridorModel):
    """test_planning's corridor, remembering what it was asked."""

    def __init__(self):
        self.seen = []

    def predict(self, states, actions):
        self.seen.append((states.copy(), actions.copy()))
        return super().predict(states, actions)


def test_step_sizes_are_per_feature():  # S04
    cfg = SarsaConfig(alpha=0.5, lam=0.5, gamma=0.9)
    st = SarsaState(np.zeros((2, 3)), np.zeros((2, 3)))
    alphas = np.array([0.5, 0.1, 0.02])
    phi = np.array([1.0, -0.5, 0.25])
    out = sarsa_update(st, phi, 1, 2.0, None, None, alphas, cfg)
    np.testing.assert_allclose(out.state.weights[1], 2.0 * alphas * phi)


@pytest.mark.parametrize("n", [1, 2])
def test_replacing_trace_keeps_the_larger_magnitude_with_its_sign(n):  # S02 S05 S06
    cfg = SarsaConfig(alpha=0.1, lam=1.0, gamma=1.0, traces="replacing")
    e = np.array([[0.5, -0.1, 0.2], [0.0, 0.0, 0.0]])
    phi = np.array([-0.8, 0.3, -0.1])
    st = SarsaState(np.zeros((2, 3)), np.tile(e, (n, 1, 1)))
    out = sarsa_update_batch(
        st,
        np.tile(phi, (n, 1)),
        np.zeros(n, int),
        np.zeros(n),
        np.tile(phi, (n, 1)),
        np.zeros(n, int),
        np.ones(n, bool),
        np.ones(n, bool),
        np.full(3, 0.1),
        cfg,
    )
    for j in range(n):
        np.testing.assert_allclose(out.state.traces[j, 0], [-0.8, 0.3, 0.2])


def test_plan_runs_exactly_n_episodes_from_every_start_row():  # P05 P04
    basis = FourierBasis(2, np.array([0.0]), np.array([1.0]))
    model = Corridor()
    starts = np.array([[0.0], [0.5], [0.9]])
    out = plan(
        init_state(2, basis.n_features),
        basis,
        SarsaConfig(alpha=0.1),
        model,
        dataclasses.replace(TASK, max_steps=1),
        starts,
        30,
        rng=np.random.default_rng(0),
        n_parallel=4,
    )
    assert out.steps.shape == (30,)  # 30 is not a multiple of 4
    seen = np.concatenate([s[:, 0] for s, _ in model.seen])
    assert set(seen.tolist()) == {0.0, 0.5, 0.9}


def test_reward_gets_state_action_next_state_in_order():  # P03
    task = PlanningTask(lambda s, a, s2: s2[:, 0] - s[:, 0], TASK.terminal, 3)
    ep = SimulatedEpisodes(Corridor(), task, np.array([[0.2]]))
    r = ep.step(np.array([1]))
    assert r.rewards[0] == pytest.approx(0.1)


def test_terminal_on_the_last_allowed_step_is_not_truncated():  # P01
    task = dataclasses.replace(TASK, max_steps=3)
    ep = SimulatedEpisodes(Corridor(), task, np.array([[0.75]]))
    for _ in range(3):
        r = ep.step(np.array([1]))
    assert r.terminal[0] and not r.truncated[0]


@pytest.mark.parametrize("max_steps", [1, 200])
def test_planning_explores_at_rate_epsilon(max_steps):  # P12 (first a), P06 (a')
    basis = FourierBasis(1, np.array([0.0]), np.array([1.0]))
    st = SarsaState(np.array([[1.0, 0.0], [0.0, 0.0]]), np.zeros((2, 2)))  # greedy: 0
    model = Corridor()
    plan(
        st,
        basis,
        SarsaConfig(alpha=1e-9, epsilon=1.0),
        model,
        dataclasses.replace(TASK, max_steps=max_steps),
        np.zeros((1, 1)),
        200 if max_steps == 1 else 10,
        rng=np.random.default_rng(0),
    )
    acts = np.concatenate([a for _, a in model.seen])
    # ε = 1: every action uniform over two (the greedy one is 0), so the mean is
    # 0.5 with standard deviation 0.5/√n; within 4 of them
    assert len(acts) >= 150 and abs(acts.mean() - 0.5) < 4 * 0.5 / np.sqrt(len(acts))


def test_open_loop_errors_wrap_across_pi():  # P11
    s = np.array([[3.1], [3.12]])  # recorded: stays below pi
    data = Transitions(s[:1], np.array([0]), s[1:], np.array([0]), angle_dims=(0,))
    model = StepwiseModel(lambda x, a: wrap_angle(x + 0.25))
    err = open_loop_errors(model, data, [1])[1]
    np.testing.assert_allclose(err, [[0.23]], atol=1e-12)  # model crosses pi


def test_models_refuse_float_actions():  # P-int
    """A float action was cast to an integer: 0.5 became action 0."""
    states, actions = np.zeros((2, 2)), np.array([0.5, 1.0])
    for model in (LearnedModel(PlainModel()), StepwiseModel(lambda s, a: s)):
        with pytest.raises(ValueError, match=r"actions: expected integer shape \(2,\)"):
            model.predict(states, actions)


def test_learned_model_checks_the_last_angle_index_against_d():  # P-angle bound
    """angle_dims = (D,) on a model that does not know D: the first index out of
    range, a ValueError naming angle_dims (not numpy's IndexError)."""
    with pytest.raises(ValueError, match=r"angle_dims: expected indices in \[0, 2\)"):
        LearnedModel(PlainModel(), None, (2,)).predict(np.zeros((1, 2)), [0])
    got = LearnedModel(PlainModel(), None, (1,)).predict(np.zeros((1, 2)), [0])
    np.testing.assert_array_equal(got, [[0.5, 0.5]])


def test_learned_model_refuses_a_mean_that_would_broadcast():  # P-mean shape
    class OneColumn(PlainModel):
        def predict(self, states, actions):
            return np.ones((len(states), 1)), np.ones((len(states), 1))

    with pytest.raises(ValueError, match=r"expected a mean of shape \(3, 2\), got"):
        LearnedModel(OneColumn()).predict(np.zeros((3, 2)), np.zeros(3, dtype=int))


def test_stepwise_model_refuses_a_row_shaped_next_state():  # P-step shape
    """A (1, D) next state has D values but is not a state of shape (D,)."""
    with pytest.raises(ValueError, match=r"got shape \(1, 2\) for row 0"):
        StepwiseModel(lambda s, a: s[None]).predict(np.ones((1, 2)), np.array([0]))


def test_simulated_episodes_refuse_non_finite_start_states():
    """The message named the (correct) shape, not the value or where it was."""
    for bad, match in (
        ([[np.nan]], r"expected finite values, got nan at index \(0, 0\)"),
        ([[0.0], [np.inf]], r"expected finite values, got inf at index \(1, 0\)"),
    ):
        with pytest.raises(ValueError, match="start_states: " + match):
            SimulatedEpisodes(Corridor(), TASK, np.array(bad))
    with pytest.raises(ValueError, match=r"start_states: expected shape \(N >= 1, D"):
        SimulatedEpisodes(Corridor(), TASK, np.zeros(2))


def test_reached_says_whether_a_terminal_state_was_reached_so_far():
    ep = SimulatedEpisodes(Corridor(), TASK, np.array([[0.75], [0.0]]))
    for _ in range(2):
        ep.step(np.array([1, 1]))
        np.testing.assert_array_equal(ep.reached, [False, False])  # still running
    ep.step(np.array([1, 1]))
    np.testing.assert_array_equal(ep.reached, [True, False])


def test_episodes_that_do_not_learn_leave_the_weights():  # learn=False
    basis = FourierBasis(2, np.array([0.0]), np.array([1.0]))
    weights = np.random.default_rng(0).normal(size=(2, basis.n_features))
    episodes = SimulatedEpisodes(Corridor(), TASK, np.zeros((3, 1)))
    out = run_sarsa_episodes(
        SarsaState(weights, np.ones_like(weights)),
        basis,
        SarsaConfig(alpha=0.1, epsilon=0.5),
        episodes,
        rng=np.random.default_rng(1),
        learn=False,
    )
    assert not episodes.active.any() and episodes.steps.min() > 1
    np.testing.assert_array_equal(out.weights, weights)
    np.testing.assert_array_equal(out.traces, 0.0)


def test_plan_checks_n_parallel_and_the_agents_features():
    """n_parallel = 0 ran groups of no episodes forever; weights for another
    basis failed in a matrix product that named neither."""
    basis = FourierBasis(1, np.zeros(1), np.ones(1))
    args = (SarsaConfig(), Corridor(), TASK, np.zeros((1, 1)), 1)
    with pytest.raises(ValueError, match="n_parallel: expected >= 1, got 0"):
        plan(init_state(2, basis.n_features), basis, *args,
             rng=np.random.default_rng(0), n_parallel=0)  # fmt: skip
    with pytest.raises(ValueError, match=r"state.weights: expected 2 features"):
        plan(init_state(2, 3), basis, *args, rng=np.random.default_rng(0))


def test_plan_returns_each_episodes_return():
    """Reward -1 per step in the corridor: each return is minus its length."""
    basis = FourierBasis(2, np.array([0.0]), np.array([1.0]))
    out = plan(init_state(2, basis.n_features), basis, SarsaConfig(alpha=0.1),
               Corridor(), TASK, np.array([[0.0], [0.5]]), 7,
               rng=np.random.default_rng(0), n_parallel=3)  # fmt: skip
    assert out.returns.dtype == float and out.steps.min() >= 5
    np.testing.assert_array_equal(out.returns, -out.steps)


def test_open_loop_errors_take_episodes_whose_angles_were_wrapped_between_rows():
    """A next state recorded unwrapped (3.3) followed by the same state wrapped
    (3.3 - 2π) is one episode in time order, not a gap."""
    s = np.array([[3.0, 0.0], [3.3 - 2 * np.pi, 0.1], [3.6 - 2 * np.pi, 0.2]])
    nxt = np.array([[3.3, 0.1], [3.6 - 2 * np.pi, 0.2], [3.9 - 2 * np.pi, 0.3]])
    data = Transitions(s, np.zeros(3, int), nxt, np.zeros(3, int), angle_dims=(0,))
    model = StepwiseModel(lambda x, a: np.array([wrap_angle(x[0] + 0.3), x[1] + 0.1]))
    errs = open_loop_errors(model, data, [1, 3])
    np.testing.assert_allclose(errs[1], 0.0, atol=1e-12)
    np.testing.assert_allclose(errs[3], 0.0, atol=1e-12)


def test_lockstep_step_sizes_are_per_feature_too():
    """Two identical terminal episodes from θ = 0: the mean step is δ α ⊙ φ with
    δ = r, so each feature moves by its own α_i (as the single update does)."""
    cfg = SarsaConfig(alpha=0.5, lam=0.5, gamma=0.9)
    alphas = np.array([0.5, 0.1, 0.02])
    phi = np.array([1.0, -0.5, 0.25])
    out = sarsa_update_batch(
        SarsaState(np.zeros((2, 3)), np.zeros((2, 2, 3))),
        np.tile(phi, (2, 1)),
        np.ones(2, int),
        np.full(2, 2.0),
        np.tile(phi, (2, 1)),
        np.zeros(2, int),
        np.ones(2, bool),
        np.ones(2, bool),
        alphas,
        cfg,
    )
    np.testing.assert_allclose(out.state.weights[1], 2.0 * alphas * phi)
    np.testing.assert_array_equal(out.state.weights[0], 0.0)


@pytest.mark.parametrize("n_parallel", [1, 2])
def test_planning_episodes_start_with_no_eligibility_traces(n_parallel):
    """An agent handed over with the traces of its last real episode (as
    tasks.agents.run_episode returns it) plans exactly as one without: traces
    belong to one episode (Sutton & Barto §7.5)."""
    basis = FourierBasis(2, np.array([0.0]), np.array([1.0]))
    rng = np.random.default_rng(0)
    weights = rng.normal(size=(2, basis.n_features))
    stale = rng.normal(size=weights.shape)
    out = {}
    for name, traces in (("stale", stale), ("none", np.zeros_like(weights))):
        out[name] = plan(
            SarsaState(weights, traces),
            basis,
            SarsaConfig(alpha=0.1, epsilon=0.2),
            Corridor(),
            dataclasses.replace(TASK, max_steps=6),
            np.array([[0.0], [0.5]]),
            4,
            rng=np.random.default_rng(1),
            n_parallel=n_parallel,
        ).state.weights
    assert not np.array_equal(out["none"], weights)  # it did learn
    np.testing.assert_array_equal(out["stale"], out["none"])


def test_an_episode_that_ended_does_not_shift_the_others_actions():
    """Episode 0 reaches the goal after 3 steps; then episode 1 must get its own
    action (0: back by 0.1), not the first entry of the actions."""
    model = Corridor()
    ep = SimulatedEpisodes(model, TASK, np.array([[0.75], [0.0]]))
    for _ in range(3):
        ep.step(np.array([1, 1]))
    assert not ep.active[0] and ep.active[1]
    ep.step(np.array([1, 0]))
    np.testing.assert_allclose(ep.states[:, 0], [1.05, 0.2])
    np.testing.assert_array_equal(model.seen[-1][1], [0])


@pytest.mark.parametrize("n_parallel", [1, 4])
def test_plan_draws_each_episodes_start_row_uniformly(n_parallel):
    """300 one-step episodes from 3 rows: each row starts Binomial(300, 1/3)
    episodes, mean 100, sd sqrt(300 · 1/3 · 2/3) ≈ 8.2, so ±4 sd is ±33. Rows
    drawn once and reused (for every group) would give 300 or multiples of 75."""
    basis = FourierBasis(1, np.array([0.0]), np.array([1.0]))
    model = Corridor()
    plan(
        init_state(2, basis.n_features),
        basis,
        SarsaConfig(alpha=0.1),
        model,
        dataclasses.replace(TASK, max_steps=1),
        np.array([[0.0], [0.5], [0.9]]),
        300,
        rng=np.random.default_rng(0),
        n_parallel=n_parallel,
    )
    seen = np.concatenate([s[:, 0] for s, _ in model.seen])
    assert seen.shape == (300,)
    for row in (0.0, 0.5, 0.9):
        assert abs(np.sum(seen == row) - 100) < 33


def test_plan_with_no_episodes_runs_nothing_and_returns_the_weights():
    """n_episodes = 0 is allowed (a protocol without planning): no model call, θ
    as given, traces zero as after any planning (PlanResult's contract: the stale
    traces of a real episode were handed back), and empty statistics."""
    basis = FourierBasis(2, np.array([0.0]), np.array([1.0]))
    weights = np.random.default_rng(0).normal(size=(2, basis.n_features))
    model = Corridor()
    out = plan(
        SarsaState(weights, np.ones_like(weights)),
        basis,
        SarsaConfig(alpha=0.1),
        model,
        TASK,
        np.zeros((1, 1)),
        0,
        rng=np.random.default_rng(1),
    )
    assert model.seen == []
    np.testing.assert_array_equal(out.state.weights, weights)
    np.testing.assert_array_equal(out.state.traces, np.zeros_like(weights))
    assert out.steps.shape == out.returns.shape == out.reached.shape == (0,)
    assert (out.steps.dtype, out.returns.dtype, out.reached.dtype) == (
        np.int64,
        np.float64,
        bool,
    )


@pytest.mark.parametrize("skip", [1.0, -1.0], ids=["ahead", "behind"])
def test_open_loop_errors_refuse_a_gap_in_either_direction(skip):
    """0 → 1, then a transition starting at 1 + skip: not one episode in time
    order, whether the next start lies ahead of the last next state or behind."""
    s = np.array([[0.0], [1.0 + skip]])
    data = Transitions(s, np.zeros(2, int), s + 1.0, np.zeros(2, int))
    model = StepwiseModel(lambda x, a: x + 1.0)
    with pytest.raises(ValueError, match="data: expected transitions in time order"):
        open_loop_errors(model, data, [1])
