"""Planning on models (numpy only): the learned-model adapter, lockstep simulated
episodes, and Dyna planning against a sequential Sarsa(λ) reference."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hipmdp.data import Transitions, wrap_angle
from hipmdp.fourier import FourierBasis
from hipmdp.planning import (
    DynamicsModel,
    LearnedModel,
    PlanningTask,
    SimulatedEpisodes,
    StepwiseModel,
    open_loop_errors,
    plan,
)
from hipmdp.sarsa import SarsaConfig, SarsaState, init_state, sarsa_update


class Corridor:
    """x ∈ [0, 1]: action 1 moves +0.1, action 0 moves −0.1 (floored at 0)."""

    def predict(self, states, actions):
        step = np.where(actions == 1, 0.1, -0.1)[:, None]
        return np.maximum(states + step, 0.0)


CORRIDOR_TASK = PlanningTask(
    reward=lambda s, a, s2: np.full(s.shape[0], -1.0),
    terminal=lambda s2: s2[:, 0] >= 1.0 - 1e-9,
    max_steps=60,
)


class BeliefModel:
    """A stand-in learned model: E[Δ] = belief · a (per dimension), var = 1."""

    def predict(self, states, actions, belief):
        mean = np.outer(actions, belief) + 0.0 * states
        return mean, np.ones_like(mean)


class Broken:
    """A model whose every prediction is NaN."""

    def predict(self, states, actions):
        return states * np.nan


class PlainModel:
    def predict(self, states, actions):
        return np.full_like(states, 0.5), np.ones_like(states)


def test_learned_model_adds_mean_delta_and_wraps_angles() -> None:
    states = np.array([[3.0, 1.0, 0.0], [-3.0, 2.0, 1.0]])
    actions = np.array([1, 2])
    belief = np.array([0.4, 5.0, -0.25])
    model = LearnedModel(BeliefModel(), belief, angle_dims=(0,))
    assert isinstance(model, DynamicsModel)
    got = model.predict(states, actions)
    raw = states + np.outer(actions, belief)
    np.testing.assert_allclose(got[:, 1:], raw[:, 1:])
    np.testing.assert_allclose(got[:, 0], wrap_angle(raw[:, 0]))
    assert got[0, 0] == pytest.approx(3.4 - 2 * np.pi)  # wrapped past π
    # without a belief the model is called as predict(states, actions)
    got = LearnedModel(PlainModel()).predict(states, actions)
    np.testing.assert_allclose(got, states + 0.5)


def test_learned_model_gives_the_model_copies_of_its_inputs() -> None:
    """A model that writes into its arguments (s -= 1, then Δ = 0) moved the
    planner's states, so that planning used s' = s - 1 while the prediction
    tables, which pass copies, scored Δ = 0."""

    class Scribbles(PlainModel):
        def predict(self, states, actions):
            states -= 1.0
            actions[:] = 0
            return np.zeros_like(states), np.ones_like(states)

    states, actions = np.ones((2, 3)), np.array([1, 2])
    got = LearnedModel(Scribbles()).predict(states, actions)
    np.testing.assert_array_equal(got, 1.0)
    np.testing.assert_array_equal(states, 1.0)
    np.testing.assert_array_equal(actions, [1, 2])


def test_learned_model_prefers_a_mean_only_path() -> None:
    class MeanOnly(PlainModel):
        def predict_mean(self, states, actions):
            return np.full_like(states, -1.0)

    got = LearnedModel(MeanOnly()).predict(np.zeros((2, 3)), np.array([0, 1]))
    np.testing.assert_array_equal(got, -1.0)


def test_learned_model_builds_a_mean_predictor_once() -> None:
    built = []

    class WithPredictor(PlainModel):
        def mean_predictor(self, *belief):
            built.append(belief)
            return lambda states, actions: states + actions[:, None]

    model = LearnedModel(WithPredictor())
    for _ in range(3):
        got = model.predict(np.zeros((2, 3)), np.array([0, 1]))
    np.testing.assert_array_equal(got, [[0, 0, 0], [1, 1, 1]])
    LearnedModel(WithPredictor(), belief="b")
    assert built == [(), ("b",)]  # built at construction, with the belief if any


def test_learned_model_checks_angles_and_belief_when_built() -> None:
    """Bad angle_dims used to fail at the first predict (or never: () left a
    fitted model's angles unwrapped); a missing belief, with a TypeError."""

    class Fitted(PlainModel):
        state_dim = 3
        info = {"angle_dims": [0, 1]}

        def mean_predictor(self, belief):
            return lambda states, actions: states

    assert LearnedModel(Fitted(), "b", [np.int64(0), 1]).angle_dims == (0, 1)
    assert LearnedModel(Fitted(), "b").angle_dims == (0, 1)  # the recorded ones
    for dims, match in [
        ((), r"angle_dims: \(\) differs from the fitted model's \(0, 1\)"),
        ((1, 0), r"differs"),
        ((0, 3), r"angle_dims: expected distinct indices in \[0, 3\)"),
        ((0, 0), "distinct"),
        ((True,), "expected integer indices"),
        (0, "angle_dims: expected a sequence"),
    ]:
        with pytest.raises(ValueError, match=match):
            LearnedModel(Fitted(), "b", dims)
    with pytest.raises(ValueError, match="belief: the model's mean_predictor needs"):
        LearnedModel(Fitted(), None, (0, 1))

    class Average(PlainModel):
        def mean_predictor(self):
            return lambda states, actions: states

    with pytest.raises(ValueError, match="belief: the model's mean_predictor takes"):
        LearnedModel(Average(), "b")
    assert LearnedModel(Average(), None, (5,)).angle_dims == (5,)  # no state_dim
    assert LearnedModel(Average()).angle_dims == ()  # none recorded: none
    # a model whose record is wrong is named, not the angle_dims nobody passed
    for recorded, match in [
        ([0, 3], r"expected distinct indices in \[0, 3\), got \(0, 3\)"),
        (1, r"expected a sequence of indices, got 1"),  # was a TypeError if given
    ]:
        bad = Fitted()
        bad.info = {"angle_dims": recorded}
        for given in ((), ((0, 1),)):
            with pytest.raises(ValueError, match=r"^model: info\['angle_dims'\], "
                               r"the angles it records .*: " + match):  # fmt: skip
                LearnedModel(bad, "b", *given)
    # a model and belief passed the other way round failed at the first predict
    with pytest.raises(ValueError, match="model: expected a model of Δs with predict"):
        LearnedModel("b", Fitted())


def test_learned_model_checks_angles_against_what_knows_the_state_dimension():
    """With no state_dim on the model, angle_dims = (5,) was taken and failed
    with an IndexError when predict wrapped the angles; a numpy-integer
    state_dim was not used for the check."""
    states, actions = np.zeros((2, 3)), np.array([0, 1])
    unknown = LearnedModel(PlainModel(), None, (1, 5))  # D is not known yet
    with pytest.raises(
        ValueError, match=r"angle_dims: expected indices in \[0, 3\) \(the states'"
    ):
        unknown.predict(states, actions)

    class NumpyDim(PlainModel):
        state_dim = np.int64(3)

    class Means:
        """A mean predictor that knows D, as a KernelMeans does."""

        state_dim = 3

        def __call__(self, states, actions):
            return np.zeros_like(states)

    class WithMeans(PlainModel):
        def mean_predictor(self):
            return Means()

    for model in (NumpyDim(), WithMeans()):
        with pytest.raises(ValueError, match=r"angle_dims: .* in \[0, 3\), got \(5,\)"):
            LearnedModel(model, None, (5,))
        got = LearnedModel(model, None, (2,)).predict(states + 4.0, actions)
        assert np.all(got[:, :2] > np.pi) and np.all(np.abs(got[:, 2]) <= np.pi)


def test_learned_model_rejects_bad_shapes() -> None:
    model = LearnedModel(PlainModel())
    with pytest.raises(ValueError, match="actions"):
        model.predict(np.zeros((3, 2)), np.zeros(2, dtype=int))
    with pytest.raises(ValueError, match="states"):
        model.predict(np.zeros(3), np.zeros(3, dtype=int))


def test_stepwise_model_applies_step_row_by_row() -> None:
    model = StepwiseModel(lambda s, a: s * (a + 1))
    got = model.predict(np.ones((3, 2)), np.array([0, 1, 2]))
    np.testing.assert_array_equal(got, [[1, 1], [2, 2], [3, 3]])


def test_stepwise_model_requires_one_finite_next_state_per_row() -> None:
    """A scalar or a (1,) return filled every dimension of the row; a wrong
    length failed with numpy's broadcast error, naming no row."""
    states, actions = np.ones((3, 2)), np.array([0, 1, 2])
    for step, got in [
        (lambda s, a: 5.0, r"\(\)"),
        (lambda s, a: s[:1], r"\(1,\)"),
        (lambda s, a: np.append(s, a), r"\(3,\)"),
        (lambda s, a: s if a < 2 else s[:1], r"\(1,\) for row 2 \(action 2\)"),
    ]:
        with pytest.raises(
            ValueError,
            match=r"step: expected a next state of shape \(D,\) = \(2,\), "
            rf"got shape {got}",
        ):
            StepwiseModel(step).predict(states, actions)
    gym = StepwiseModel(lambda s, a: (s, -1.0, False))  # gym's (state, reward, done)
    with pytest.raises(ValueError, match="step: expected the next state alone, got a"):
        gym.predict(states, actions)
    as_tuple = StepwiseModel(lambda s, a: (s[0] + a, s[1]))  # a state, as numbers
    np.testing.assert_array_equal(as_tuple.predict(states, actions)[:, 0], [1, 2, 3])
    model = StepwiseModel(lambda s, a: s / (a - 1))  # action 1 divides by zero
    with np.errstate(divide="ignore"):
        with pytest.raises(ValueError, match=r"finite next state.* row 1 \(action 1\)"):
            model.predict(states, actions)


def test_simulated_episodes_end_at_terminal_or_step_limit() -> None:
    task = PlanningTask(CORRIDOR_TASK.reward, CORRIDOR_TASK.terminal, max_steps=5)
    episodes = SimulatedEpisodes(Corridor(), task, np.array([[0.75], [0.0], [0.4]]))
    actions = np.ones(3, dtype=int)
    results = [episodes.step(actions) for _ in range(5)]
    # episode 0 reaches x = 1.05 ≥ 1 after 3 steps; the others run into the limit
    np.testing.assert_array_equal(episodes.steps, [3, 5, 5])
    np.testing.assert_array_equal(episodes.reached, [True, False, False])
    np.testing.assert_array_equal(episodes.returns, [-3.0, -5.0, -5.0])
    assert results[2].terminal.tolist() == [True, False, False]
    assert results[4].truncated.tolist() == [False, True, True]
    assert not episodes.active.any()
    # an ended episode's state stays put and earns nothing
    assert results[3].rewards[0] == 0.0
    np.testing.assert_allclose(episodes.states[:, 0], [1.05, 0.5, 0.9])


@pytest.mark.parametrize("max_steps", [60, 4])
def test_plan_with_one_episode_at_a_time_is_sequential_sarsa(max_steps) -> None:
    """With random (tie-free) weights and ε = 0 the actions are deterministic, so
    plan() must equal a hand-written loop of sarsa_update on the model. With
    max_steps = 4 no episode reaches the goal (8 steps away at best): each is cut
    at the limit, where the update still bootstraps (only a terminal state does
    not)."""
    rng = np.random.default_rng(0)
    basis = FourierBasis(3, np.array([0.0]), np.array([1.0]))
    config = SarsaConfig(alpha=0.05, lam=0.9, gamma=1.0, epsilon=0.0)
    start = SarsaState(rng.normal(size=(2, 4)), np.zeros((2, 4)))
    task = dataclasses.replace(CORRIDOR_TASK, max_steps=max_steps)
    out = plan(start, basis, config, Corridor(), task, np.array([[0.2]]), 3,
               rng=np.random.default_rng(1))  # fmt: skip

    weights, model, alphas = start.weights, Corridor(), config.alpha * basis.step_scale
    steps = []
    for _ in range(3):
        state = SarsaState(weights, np.zeros_like(weights))
        s = np.array([[0.2]])
        a = int(np.argmax(state.weights @ basis(s[0])))
        for t in range(1, max_steps + 1):  # noqa: B007 (t: the episode's length)
            s2 = model.predict(s, np.array([a]))
            terminal = bool(s2[0, 0] >= 1.0 - 1e-9)
            a2 = int(np.argmax(state.weights @ basis(s2[0])))
            state = sarsa_update(state, basis(s[0]), a, -1.0,
                                 None if terminal else basis(s2[0]), a2, alphas,
                                 config).state  # fmt: skip
            s, a = s2, a2
            if terminal:
                break
        steps.append(t)
        weights = state.weights
    np.testing.assert_allclose(out.state.weights, weights, atol=1e-12)
    np.testing.assert_array_equal(out.steps, steps)
    np.testing.assert_array_equal(out.state.traces, 0.0)
    if max_steps == 4:
        assert np.all(out.steps == 4) and not out.reached.any()


@pytest.mark.parametrize("n_parallel", [1, 4])
def test_planning_learns_the_corridor(n_parallel: int) -> None:
    """Optimistic zero values, ε = 0: after planning, a greedy rollout on the model
    takes the shortest path (10 steps from x = 0)."""
    basis = FourierBasis(4, np.array([0.0]), np.array([1.0]))
    config = SarsaConfig(alpha=0.1, lam=0.9, gamma=1.0, epsilon=0.0)
    out = plan(init_state(2, basis.n_features), basis, config, Corridor(),
               CORRIDOR_TASK, np.zeros((1, 1)), 40, rng=np.random.default_rng(2),
               n_parallel=n_parallel)  # fmt: skip
    assert out.steps.shape == (40,) and out.reached[-4:].all()
    assert out.steps[0] > 10
    episodes = SimulatedEpisodes(Corridor(), CORRIDOR_TASK, np.zeros((1, 1)))
    while episodes.active.any():
        episodes.step(np.argmax(basis(episodes.states) @ out.state.weights.T, axis=1))
    assert episodes.steps[0] == 10 and episodes.reached[0]


def test_plan_rejects_bad_input() -> None:
    basis = FourierBasis(1, np.zeros(2), np.ones(2))
    state = init_state(2, basis.n_features)
    config = SarsaConfig()
    for starts in (np.zeros((1, 3)), np.zeros((0, 2))):  # (0, 2): numpy's "high <= 0"
        with pytest.raises(ValueError, match=r"start_states: expected shape \(M >= 1"):
            plan(state, basis, config, Corridor(), CORRIDOR_TASK, starts, 1,
                 rng=np.random.default_rng(0))  # fmt: skip
    with pytest.raises(ValueError, match="n_episodes"):
        plan(state, basis, config, Corridor(), CORRIDOR_TASK, np.zeros((1, 2)), -1,
             rng=np.random.default_rng(0))  # fmt: skip
    for n in (2.5, True):  # 2.5 ran two episodes, True one, before failing or not
        with pytest.raises(ValueError, match="n_episodes: expected an integer"):
            plan(state, basis, config, Corridor(), CORRIDOR_TASK, np.zeros((1, 2)), n,
                 rng=np.random.default_rng(0))  # fmt: skip
    with pytest.raises(ValueError, match="n_parallel: expected an integer"):
        plan(state, basis, config, Corridor(), CORRIDOR_TASK, np.zeros((1, 2)), 1,
             rng=np.random.default_rng(0), n_parallel=1.0)  # fmt: skip
    for steps in (0, 2.5):
        with pytest.raises(ValueError, match="max_steps"):
            PlanningTask(CORRIDOR_TASK.reward, CORRIDOR_TASK.terminal, steps)


def test_simulated_episodes_take_exactly_one_integer_action_per_episode() -> None:
    """Three actions for two episodes used the first two silently; one failed
    with an IndexError; float actions reached the model."""
    episodes = SimulatedEpisodes(Corridor(), CORRIDOR_TASK, np.zeros((2, 1)))
    for actions in ([1, 1, 0], [1], [[1, 1]], [1.0, 1.0], [True, False]):
        with pytest.raises(ValueError, match=r"actions: expected integers of shape"):
            episodes.step(np.array(actions))
    np.testing.assert_array_equal(episodes.steps, [0, 0])  # no step was taken
    episodes.step([1, 0])  # a list of integers is fine


@pytest.mark.parametrize(
    ("task", "match"),
    [
        (dataclasses.replace(CORRIDOR_TASK, reward=lambda s, a, s2: -1.0),
         r"task.reward: expected finite numbers of shape \(2,\)"),
        (dataclasses.replace(CORRIDOR_TASK, reward=lambda s, a, s2: s[:, 0] * np.nan),
         r"task.reward: expected finite numbers"),
        (dataclasses.replace(CORRIDOR_TASK, terminal=lambda s2: s2[:, 0] * 0 + 0.5),
         r"task.terminal: expected booleans \(or 0/1\) of shape \(2,\)"),
        (dataclasses.replace(CORRIDOR_TASK, terminal=lambda s2: False),
         r"task.terminal: expected booleans \(or 0/1\) of shape \(2,\)"),
        # an integer other than 0/1 (a step count?) was taken as reached
        (dataclasses.replace(CORRIDOR_TASK, terminal=lambda s2: np.full(2, 2)),
         r"task.terminal: expected booleans \(or 0/1\) of shape \(2,\).*got int64"),
    ],
)  # fmt: skip
def test_a_tasks_answer_must_be_one_per_active_episode(task, match) -> None:
    """A scalar reward was spread over every episode; a terminal of 0.5 counted
    as reached; a NaN reward entered the returns."""
    episodes = SimulatedEpisodes(Corridor(), task, np.zeros((2, 1)))
    with pytest.raises(ValueError, match=match):
        episodes.step(np.array([1, 0]))


def test_a_terminal_of_0_1_integers_is_taken_as_booleans() -> None:
    """As `Transitions` takes 0/1 dones (it was refused as not booleans)."""
    ints = dataclasses.replace(
        CORRIDOR_TASK, terminal=lambda s2: CORRIDOR_TASK.terminal(s2).astype(int)
    )
    runs = [
        SimulatedEpisodes(Corridor(), t, np.zeros((2, 1)))
        for t in (CORRIDOR_TASK, ints)
    ]
    for _ in range(12):  # the end is 10 steps away
        a, b = (r.step(np.array([1, 1])) for r in runs)
        np.testing.assert_array_equal(a.terminal, b.terminal)
    assert runs[1].reached.any()  # the corridor's end was reached, and counted


def test_non_finite_model_output_is_an_error() -> None:
    episodes = SimulatedEpisodes(Broken(), CORRIDOR_TASK, np.zeros((2, 1)))
    with pytest.raises(ValueError, match="model.predict"):
        episodes.step(np.zeros(2, dtype=int))


def _drift_episodes(lengths, rng):
    """Episodes of s' = s + u[a] (2 dims, the first an angle), in time order."""
    u = np.array([[0.9, 0.1], [-0.4, 0.3]])
    parts = []
    for i, n in enumerate(lengths):
        actions = rng.integers(0, 2, size=n)
        states = np.zeros((n + 1, 2))
        states[0] = rng.normal(size=2)
        for t, a in enumerate(actions):
            states[t + 1] = states[t] + u[a]
        states[:, 0] = wrap_angle(states[:, 0])
        dones = np.zeros(n, dtype=bool)
        dones[-1] = True
        parts.append(
            Transitions(
                states[:-1],
                actions,
                states[1:],
                np.full(n, i),
                dones=dones,
                angle_dims=(0,),
            )  # fmt: skip
        )
    return Transitions.concatenate(parts), u


def test_open_loop_errors_compound_a_bias_and_respect_episodes() -> None:
    data, u = _drift_episodes([7, 3, 12], np.random.default_rng(0))
    bias = np.array([0.05, -0.02])

    def step(s, a, c):
        nxt = s + u[a] + c
        return np.array([wrap_angle(nxt[0]), nxt[1]])

    exact = StepwiseModel(lambda s, a: step(s, a, 0.0))
    biased = StepwiseModel(lambda s, a: step(s, a, bias))
    horizons = (1, 3, 8)
    for k, err in open_loop_errors(exact, data, horizons).items():
        # windows never cross an episode end: episodes of 7, 3, 12 transitions
        assert len(err) == sum(max(0, n - k + 1) for n in (7, 3, 12))
        np.testing.assert_allclose(err, 0.0, atol=1e-12)
    for k, err in open_loop_errors(biased, data, horizons).items():
        np.testing.assert_allclose(err, np.tile(k * bias, (len(err), 1)), atol=1e-12)


@pytest.mark.parametrize(
    ("predict", "shape"),
    [
        (lambda s, a: s[:, 0], r"\(4,\)"),  # broadcast to (4, 4)
        (lambda s, a: s[:, :0], r"\(4, 0\)"),  # an empty error array
        (lambda s, a: s[:1], r"\(1, 1\)"),  # broadcast over the four starts
    ],
    ids=["(n,)", "(n, 0)", "(1, D)"],
)
def test_open_loop_errors_reject_a_model_output_of_the_wrong_shape(predict, shape):
    """A (n,) prediction for n one-dimensional states broadcast to errors of
    shape (n, n); (n, 0) gave an empty array; neither was an error."""

    class Model:
        def predict(self, states, actions):
            return predict(states, actions)

    s = np.arange(5.0)[:, None]
    data = Transitions(s[:-1], np.zeros(4, int), s[1:], np.zeros(4, int))
    match = r"model.predict: expected next states of shape \(4, 1\), got shape "
    with pytest.raises(ValueError, match=match + shape):
        open_loop_errors(Model(), data, [1])


def test_open_loop_errors_reject_a_non_finite_model_output() -> None:
    s = np.arange(3.0)[:, None]
    data = Transitions(s[:-1], np.zeros(2, int), s[1:], np.zeros(2, int))
    with pytest.raises(ValueError, match="model.predict: expected finite next states"):
        open_loop_errors(Broken(), data, [1])


def test_open_loop_errors_reject_bad_input() -> None:
    data, u = _drift_episodes([5], np.random.default_rng(1))
    model = StepwiseModel(lambda s, a: s + u[a])
    with pytest.raises(ValueError, match="horizons"):
        open_loop_errors(model, data, [0])
    # int(k) made 1.5 a 1, True a 1 and "12" the horizons 1 and 2
    for horizons, match in [
        ([1.5], r"horizons\[0\]: expected an integer >= 1, got 1.5 \(float\)"),
        ([1, True], r"horizons\[1\]: expected an integer >= 1, got True \(bool\)"),
        ("12", r"horizons\[0\]: expected an integer >= 1, got '1' \(str\)"),
        ([2, 0], r"horizons\[1\]: expected >= 1, got 0"),
        ([], "horizons: expected at least one"),
        (3, "horizons: expected a sequence"),
    ]:
        with pytest.raises(ValueError, match=match):
            open_loop_errors(model, data, horizons)
    assert list(open_loop_errors(model, data, (np.int64(2),))) == [2]
    shuffled = data.take(np.array([0, 2, 1, 3, 4]))
    with pytest.raises(ValueError, match="time order"):
        open_loop_errors(model, shuffled, [1])


def test_plan_names_an_argument_of_the_wrong_kind() -> None:
    """Arguments in another order, an int seed or a bare model of Δs failed as
    AttributeErrors or TypeErrors inside the planning loop."""
    basis = FourierBasis(1, np.zeros(1), np.ones(1))
    state, config = init_state(2, basis.n_features), SarsaConfig()
    s0 = np.zeros((1, 1))

    def call(*args, rng=None):
        rng = np.random.default_rng(0) if rng is None else rng
        return plan(*args, s0, 1, rng=rng)

    for args, match in [
        ((basis, state, config, Corridor(), CORRIDOR_TASK), "state: expected a Sarsa"),
        ((state, basis, Corridor(), config, CORRIDOR_TASK), "config: expected a Sarsa"),
        ((state.weights, basis, config, Corridor(), CORRIDOR_TASK), "state: expected"),
        ((state, basis, config, Corridor(), CORRIDOR_TASK.reward), "task: expected"),
        ((state, basis, config, object(), CORRIDOR_TASK), "model: expected a Dyn"),
        ((state, basis, config, BeliefModel(), CORRIDOR_TASK), "LearnedModel"),
    ]:
        with pytest.raises(ValueError, match=match):
            call(*args)
    with pytest.raises(ValueError, match="rng: expected a numpy Generator"):
        call(state, basis, config, Corridor(), CORRIDOR_TASK, rng=0)


def test_plan_refuses_an_agent_with_another_number_of_actions_than_the_model():
    """An agent with fewer actions than the model planned without a word, never
    trying the others."""

    class ThreeActions(PlainModel):
        n_actions = 3

    basis = FourierBasis(1, np.zeros(1), np.ones(1))
    for model in (ThreeActions(), LearnedModel(ThreeActions())):
        with pytest.raises(ValueError, match="agent has 2 actions, the model 3"):
            plan(init_state(2, basis.n_features), basis, SarsaConfig(), model,
                 CORRIDOR_TASK, np.zeros((1, 1)), 1,
                 rng=np.random.default_rng(0))  # fmt: skip


def test_plan_refuses_a_basis_over_another_state_dimension_than_the_models():
    """A 3-D basis with a 2-D model blamed the (right) start states."""

    class TwoDims(PlainModel):
        state_dim = 2

    basis = FourierBasis(1, np.zeros(3), np.ones(3))
    for model in (TwoDims(), LearnedModel(TwoDims())):
        with pytest.raises(ValueError, match="basis: expected a basis over the "
                           "model's 2 state dimensions, got one over 3"):  # fmt: skip
            plan(init_state(2, basis.n_features), basis, SarsaConfig(), model,
                 CORRIDOR_TASK, np.zeros((1, 2)), 1,
                 rng=np.random.default_rng(0))  # fmt: skip


@pytest.mark.parametrize(
    "reward, terminal, match",
    [
        (lambda s2: s2[:, 0], CORRIDOR_TASK.terminal, "task.reward: expected a func"),
        (lambda s, a: s[:, 0], CORRIDOR_TASK.terminal, "task.reward: expected a func"),
        (-1.0, CORRIDOR_TASK.terminal, r"task.reward: expected a function"),
        (CORRIDOR_TASK.reward, lambda s, a, s2: s2[:, 0] > 1, "task.terminal: exp"),
        (CORRIDOR_TASK.reward, None, "task.terminal: expected a function"),
    ],
)
def test_planning_task_checks_its_functions_signatures(reward, terminal, match):
    with pytest.raises(ValueError, match=match):
        PlanningTask(reward, terminal, 10)
    PlanningTask(lambda *args: args[0][:, 0], lambda s2, extra=0: s2[:, 0] > 1, 10)
