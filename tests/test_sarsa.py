"""Sarsa(λ): the update against a plain tabular reference, the lockstep batch update
against the single one, ε-greedy statistics, and learning on a small corridor."""

from __future__ import annotations

import numpy as np
import pytest

from hipmdp.fourier import FourierBasis
from hipmdp.sarsa import (
    SarsaConfig,
    SarsaState,
    epsilon_greedy,
    epsilon_greedy_batch,
    init_state,
    q_values,
    reset_traces,
    sarsa_update,
    sarsa_update_batch,
)


def tabular_sarsa_lambda(episode, n_states, n_actions, alpha, gamma, lam, kind):
    """Textbook tabular Sarsa(λ) (Sutton & Barto 1998, Fig. 7.11) with dicts.

    ``episode``: list of (s, a, r, s', a', terminal) with integer states."""
    Q = {(s, a): 0.0 for s in range(n_states) for a in range(n_actions)}
    e = dict.fromkeys(Q, 0.0)
    for s, a, r, s2, a2, terminal in episode:
        delta = r + (0.0 if terminal else gamma * Q[(s2, a2)]) - Q[(s, a)]
        for key in e:
            e[key] *= gamma * lam
        e[(s, a)] = e[(s, a)] + 1.0 if kind == "accumulating" else 1.0
        for key in Q:
            Q[key] += alpha * delta * e[key]
    return np.array([[Q[(s, a)] for s in range(n_states)] for a in range(n_actions)])


@pytest.mark.parametrize("kind", ["accumulating", "replacing"])
def test_one_hot_features_reproduce_tabular_sarsa_lambda(kind: str) -> None:
    rng = np.random.default_rng(0)
    n_states, n_actions = 5, 2
    config = SarsaConfig(alpha=0.3, lam=0.8, gamma=0.9, traces=kind)
    # a random walk that revisits states, so accumulating and replacing differ
    s = rng.integers(n_states, size=30)
    a = rng.integers(n_actions, size=30)
    r = rng.normal(size=29)
    episode = [(s[t], a[t], r[t], s[t + 1], a[t + 1], t == 28) for t in range(29)]
    state = init_state(n_actions, n_states)
    eye = np.eye(n_states)
    for st, at, rt, s2, a2, terminal in episode:
        state = sarsa_update(
            state, eye[st], at, rt, None if terminal else eye[s2], a2,
            np.full(n_states, config.alpha), config,
        ).state  # fmt: skip
    expected = tabular_sarsa_lambda(
        episode, n_states, n_actions, config.alpha, config.gamma, config.lam, kind
    )
    np.testing.assert_allclose(state.weights, expected, atol=1e-12)


def test_replacing_traces_are_bounded_by_one_for_real_features() -> None:
    rng = np.random.default_rng(1)
    config = SarsaConfig(alpha=0.01, lam=1.0, gamma=1.0, traces="replacing")
    state = init_state(2, 8)
    for _ in range(50):
        phi = rng.uniform(-1, 1, size=8)
        state = sarsa_update(
            state, phi, 0, -1.0, phi, 0, np.full(8, 0.01), config
        ).state
        assert np.all(np.abs(state.traces) <= 1.0)
    assert np.all(state.traces[1] == 0.0)  # the untaken action has no trace


@pytest.mark.parametrize("kind", ["accumulating", "replacing"])
def test_batch_update_with_one_episode_equals_single_update(kind: str) -> None:
    rng = np.random.default_rng(2)
    config = SarsaConfig(alpha=0.05, lam=0.9, gamma=0.95, traces=kind)
    single = SarsaState(rng.normal(size=(3, 6)), rng.uniform(-1, 1, size=(3, 6)))
    batch = SarsaState(single.weights.copy(), single.traces[None].copy())
    alphas = config.alpha * rng.uniform(0.2, 1.0, size=6)
    for t in range(20):
        phi, phi2 = rng.uniform(-1, 1, size=(2, 6))
        a, a2 = rng.integers(3, size=2)
        r, terminal = rng.normal(), t == 19
        one = sarsa_update(single, phi, a, r, None if terminal else phi2, a2,
                           alphas, config)  # fmt: skip
        many = sarsa_update_batch(
            batch, phi[None], np.array([a]), np.array([r]), phi2[None],
            np.array([a2]), np.array([terminal]), np.array([True]), alphas, config,
        )  # fmt: skip
        np.testing.assert_allclose(many.state.weights, one.state.weights, atol=1e-12)
        np.testing.assert_allclose(many.state.traces[0], one.state.traces, atol=1e-12)
        assert many.td_error[0] == pytest.approx(one.td_error, abs=1e-12)
        single, batch = one.state, many.state


def test_batch_update_of_identical_episodes_equals_single_update() -> None:
    """N copies of one episode: the mean step is the single step (general path)."""
    rng = np.random.default_rng(6)
    config = SarsaConfig(alpha=0.05, lam=0.9, gamma=0.95)
    weights, trace = rng.normal(size=(2, 5)), rng.uniform(-1, 1, size=(2, 5))
    phi, phi2 = rng.uniform(-1, 1, size=(2, 5))
    alphas = np.full(5, config.alpha)
    one = sarsa_update(SarsaState(weights, trace.copy()), phi, 1, 0.3, phi2, 0,
                       alphas, config)  # fmt: skip
    n = 3
    many = sarsa_update_batch(
        SarsaState(weights, np.tile(trace, (n, 1, 1))), np.tile(phi, (n, 1)),
        np.ones(n, dtype=int), np.full(n, 0.3), np.tile(phi2, (n, 1)),
        np.zeros(n, dtype=int), np.zeros(n, dtype=bool), np.ones(n, dtype=bool),
        alphas, config,
    )  # fmt: skip
    np.testing.assert_allclose(many.state.weights, one.state.weights, atol=1e-12)
    for j in range(n):
        np.testing.assert_allclose(many.state.traces[j], one.state.traces, atol=1e-12)


def test_batch_update_averages_active_episodes_and_ignores_inactive_ones() -> None:
    rng = np.random.default_rng(3)
    config = SarsaConfig(alpha=0.05, lam=0.9, gamma=0.95)
    weights = rng.normal(size=(2, 4))
    traces = rng.uniform(-1, 1, size=(3, 2, 4))
    phi, phi2 = rng.uniform(-1, 1, size=(2, 3, 4))
    a, a2 = np.array([0, 1, 1]), np.array([1, 1, 0])
    r, terminal = np.array([1.0, -2.0, 0.5]), np.array([False, True, False])
    alphas = np.full(4, config.alpha)
    active = np.array([True, True, False])
    out = sarsa_update_batch(SarsaState(weights, traces), phi, a, r, phi2, a2,
                             terminal, active, alphas, config)  # fmt: skip
    # each active episode alone from the same θ; the step is their mean change
    total = np.zeros_like(weights)
    for j in (0, 1):
        one = sarsa_update(
            SarsaState(weights, traces[j].copy()), phi[j], a[j], r[j],
            None if terminal[j] else phi2[j], a2[j], alphas, config,
        )  # fmt: skip
        total += one.state.weights - weights
        np.testing.assert_allclose(out.state.traces[j], one.state.traces, atol=1e-12)
    np.testing.assert_allclose(out.state.weights, weights + total / 2, atol=1e-12)
    np.testing.assert_array_equal(out.state.traces[2], traces[2])
    assert out.td_error[2] == 0.0


def test_epsilon_greedy_breaks_ties_uniformly_and_explores_at_rate_epsilon() -> None:
    rng = np.random.default_rng(4)
    n = 20_000
    # ties between actions 0 and 2: each with probability 1/2; a binomial count's
    # standard deviation is sqrt(n/4) ≈ 71, so ±4 sd is ±283
    q = np.array([1.0, 0.0, 1.0])
    counts = np.bincount(
        [epsilon_greedy(q, 0.0, rng=rng) for _ in range(n)], minlength=3
    )
    assert counts[1] == 0 and abs(counts[0] - n / 2) < 283
    batch = epsilon_greedy_batch(np.tile(q, (n, 1)), 0.0, rng=rng)
    assert np.sum(batch == 1) == 0 and abs(np.sum(batch == 0) - n / 2) < 283
    # ε = 0.3 with a unique maximum: the others each get ε/3 = 0.1 (sd ≈ 42)
    q = np.array([0.0, 5.0, 1.0])
    for picks in (
        np.array([epsilon_greedy(q, 0.3, rng=rng) for _ in range(n)]),
        epsilon_greedy_batch(np.tile(q, (n, 1)), 0.3, rng=rng),
    ):
        counts = np.bincount(picks, minlength=3)
        assert abs(counts[0] - 0.1 * n) < 170 and abs(counts[2] - 0.1 * n) < 170


@pytest.mark.parametrize("epsilon", [2.0, -1.0, np.nan, True])
def test_epsilon_greedy_refuses_epsilon_outside_the_unit_interval(epsilon) -> None:
    """ε = 2 (or True) explored at every step and ε = −1 (or NaN) never, silently."""
    rng = np.random.default_rng(0)
    q = np.array([0.0, 1.0])
    match = r"epsilon: expected a number in \[0, 1\]"
    with pytest.raises(ValueError, match=match):
        epsilon_greedy(q, epsilon, rng=rng)
    with pytest.raises(ValueError, match=match):
        epsilon_greedy_batch(q[None], epsilon, rng=rng)


def test_epsilon_greedy_refuses_action_values_of_the_wrong_shape() -> None:
    """A (1, A) row picked an index into the flattened array; a 1-D batch failed
    unpacking its shape; no actions failed inside numpy's max."""
    rng = np.random.default_rng(0)
    for q in (np.zeros((1, 2)), np.zeros(0)):
        with pytest.raises(ValueError, match=r"q: expected shape \(A,\)"):
            epsilon_greedy(q, 0.0, rng=rng)
    for q in (np.zeros(2), np.zeros((2, 0))):
        with pytest.raises(ValueError, match=r"q: expected shape \(N, A\)"):
            epsilon_greedy_batch(q, 0.0, rng=rng)


def test_sarsa_learns_the_shortest_path_along_a_corridor() -> None:
    """x ∈ [0, 1], actions move ±0.1, reward −1 per step, goal at x ≥ 1 from x = 0:
    the optimal return is −10; zero initial values are optimistic, ε = 0."""
    basis = FourierBasis(4, np.array([0.0]), np.array([1.0]))
    config = SarsaConfig(alpha=0.1, lam=0.9, gamma=1.0, epsilon=0.0)
    alphas = config.alpha * basis.step_scale
    rng = np.random.default_rng(5)
    state = init_state(2, basis.n_features)
    lengths = []
    for _ in range(40):
        state = reset_traces(state)
        x, steps = 0.0, 0
        a = epsilon_greedy(state.weights @ basis(np.array([x])), 0.0, rng=rng)
        while True:
            x2, steps = max(x + (0.1 if a == 1 else -0.1), 0.0), steps + 1
            done = x2 >= 1.0 - 1e-9 or steps >= 200
            a2 = epsilon_greedy(state.weights @ basis(np.array([x2])), 0.0, rng=rng)
            phi2 = None if x2 >= 1.0 - 1e-9 else basis(np.array([x2]))
            state = sarsa_update(
                state, basis(np.array([x])), a, -1.0, phi2, a2, alphas, config
            ).state
            if done:
                break
            x, a = x2, a2
        lengths.append(steps)
    assert lengths[0] > 10  # the first episode wanders
    assert lengths[-5:] == [10] * 5


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"alpha": 0.0}, "alpha"),
        ({"lam": 1.5}, "lam"),
        ({"gamma": -0.1}, "gamma"),
        ({"epsilon": 2.0}, "epsilon"),
        ({"traces": "dutch"}, "traces"),
        # bools passed as 1 and 0 (alpha = True: the largest step size); a string
        # failed comparing str with float
        ({"alpha": True}, r"alpha: expected a number with 0 < alpha <= 1, got True"),
        ({"lam": False}, r"lam: expected a number in \[0, 1\], got False"),
        ({"gamma": np.True_}, "gamma: expected a number"),
        ({"epsilon": "0.1"}, "epsilon: expected a number"),
    ],
)
def test_bad_config_raises_naming_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        SarsaConfig(**kwargs)


@pytest.mark.parametrize("value", [True, np.nan, "0"])
def test_init_state_refuses_an_initial_value_that_is_not_a_finite_number(value):
    """initial_value = True gave weights of 1."""
    with pytest.raises(ValueError, match="initial_value: expected a finite number"):
        init_state(2, 3, initial_value=value)


def test_init_state_sets_constant_feature_weight() -> None:
    state = init_state(3, 5, initial_value=7.0)
    np.testing.assert_array_equal(state.weights[:, 0], 7.0)
    np.testing.assert_array_equal(state.weights[:, 1:], 0.0)
    assert reset_traces(state, 4).traces.shape == (4, 3, 5)
    with pytest.raises(ValueError, match="n_actions"):
        init_state(0, 5)


def test_updates_refuse_bad_actions_and_a_diverged_td_error() -> None:
    """A negative action indexed the last action's weights; a NaN reward made
    every weight of the action NaN, which then chose action 0 silently."""
    config = SarsaConfig()
    state = init_state(3, 2)
    phi, alphas = np.array([1.0, 0.5]), np.full(2, 0.1)
    for a, a2, match in [(-1, 0, "action: "), (3, 0, "action: "),
                         (0, None, "action_next"), (0, 3, "action_next")]:  # fmt: skip
        with pytest.raises(ValueError, match=match):
            sarsa_update(state, phi, a, 0.0, phi, a2, alphas, config)
    sarsa_update(state, phi, 0, 0.0, None, None, alphas, config)  # terminal: no a'
    with pytest.raises(ValueError, match="Sarsa.* diverged"):
        sarsa_update(state, phi, 0, np.nan, phi, 1, alphas, config)
    batch = reset_traces(state, 2)
    two, ok = np.stack([phi, phi]), np.ones(2, bool)

    def update(actions, actions_next, rewards):
        return sarsa_update_batch(batch, two, np.array(actions), np.array(rewards),
                                  two, np.array(actions_next), ~ok, ok, alphas,
                                  config)  # fmt: skip

    update([0, 2], [1, 0], [0.0, 0.0])
    with pytest.raises(ValueError, match="actions: expected indices in"):
        update([0, -1], [1, 0], [0.0, 0.0])
    with pytest.raises(ValueError, match="actions_next: expected indices in"):
        update([0, 1], [1, 3], [0.0, 0.0])
    with pytest.raises(ValueError, match="Sarsa.* diverged"):
        update([0, 1], [1, 0], [0.0, np.inf])


def test_counts_must_be_integers_naming_the_argument() -> None:
    """init_state(2.5, 3) failed inside numpy ("'float' object cannot be
    interpreted as an integer"), (True, 3) with "an integer is required" and
    ('3', 3) comparing str with int; reset_traces(state, -1) with "negative
    dimensions", and n_episodes = 0 gave traces no batch update could use."""
    for args, match in [
        ((2.5, 3), r"n_actions: expected an integer >= 1, got 2.5 \(float\)"),
        ((True, 3), r"n_actions: expected an integer >= 1, got True \(bool\)"),
        (("3", 3), "n_actions: expected an integer"),
        ((3, 0), "n_features: expected >= 1, got 0"),
        ((3, np.float64(4.0)), "n_features: expected an integer"),
    ]:
        with pytest.raises(ValueError, match=match):
            init_state(*args)
    state = init_state(np.int64(3), np.int32(2))  # numpy integers are integers
    assert reset_traces(state, np.int64(2)).traces.shape == (2, 3, 2)
    for n, match in [
        (-1, "n_episodes: expected >= 1, got -1"),
        (0, "n_episodes: expected >= 1, got 0"),
        (2.0, "n_episodes: expected an integer"),
        (True, "n_episodes: expected an integer"),
    ]:
        with pytest.raises(ValueError, match=match):
            reset_traces(state, n)


def test_update_refuses_inputs_that_do_not_match_the_weights() -> None:
    """Traces of shape (1, A, F) (from reset_traces(state, 1)) gave 3-D weights
    and added φ to every action's trace; a float action failed with an IndexError;
    negative (or NaN) step sizes were taken."""
    state = init_state(3, 2)
    phi = np.array([1.0, 0.5])
    good = {"state": state, "phi": phi, "action": 0, "reward": -1.0,
            "phi_next": phi, "action_next": np.int64(2),
            "step_sizes": np.full(2, 0.1), "config": SarsaConfig()}  # fmt: skip
    sarsa_update(**good)  # numpy integer actions are integers
    for change, match in [
        ({"state": reset_traces(state, 1)},
         r"state.traces: expected shape \(A, F\) = \(3, 2\), got \(1, 3, 2\)"),
        ({"state": SarsaState(np.zeros(2), np.zeros(2))},
         r"state.weights: expected shape \(A, F\), got \(2,\)"),
        ({"state": SarsaState(np.zeros((1, 3, 2)), np.zeros((1, 3, 2)))},
         r"state.weights: expected shape \(A, F\), got \(1, 3, 2\)"),
        ({"phi": np.ones(3)}, r"phi: expected shape \(F,\) = \(2,\), got \(3,\)"),
        ({"phi_next": np.ones((1, 2))}, r"phi_next: expected shape \(F,\)"),
        ({"step_sizes": np.ones(3)}, r"step_sizes: expected shape \(F,\)"),
        ({"step_sizes": np.array([0.1, -0.1])}, "step_sizes: expected entries >= 0"),
        ({"step_sizes": np.array([0.1, np.nan])}, "step_sizes: expected entries"),
        ({"action": 1.0}, r"action: expected an integer index in \[0, 3\), got 1.0"),
        ({"action": True}, "action: expected an integer index"),
        ({"action_next": np.float64(2.0)}, "action_next: expected an integer index"),
        ({"reward": np.array([1.0])}, "reward: expected a real number"),
    ]:  # fmt: skip
        with pytest.raises(ValueError, match=match):
            sarsa_update(**(good | change))


def test_batch_update_refuses_arrays_that_do_not_match_n_episodes() -> None:
    """Rewards of shape (1,) and one episode's (A, F) trace were broadcast over
    all N episodes; actions of the wrong length or a float dtype failed inside
    numpy; a float action of a one-episode batch was truncated to an index."""
    state = reset_traces(init_state(3, 2), 2)
    two = np.array([[1.0, 0.5], [0.2, -0.3]])
    good = {"state": state, "phi": two, "actions": np.array([0, 2]),
            "rewards": np.zeros(2), "phi_next": two, "actions_next": np.array([1, 0]),
            "terminal": np.zeros(2, bool), "active": np.ones(2, bool),
            "step_sizes": np.full(2, 0.1), "config": SarsaConfig()}  # fmt: skip
    one = good | {"state": reset_traces(state, 1), "phi": two[:1],
                  "actions": np.array([0]), "rewards": np.zeros(1),
                  "phi_next": two[:1], "actions_next": np.array([1]),
                  "terminal": np.zeros(1, bool),
                  "active": np.ones(1, bool)}  # fmt: skip
    sarsa_update_batch(**good)
    sarsa_update_batch(**one)
    for base, change, match in [
        (good, {"rewards": np.zeros(1)},
         r"rewards: expected shape \(N,\) = \(2,\), got \(1,\)"),
        (good, {"state": SarsaState(state.weights, state.traces[0])},
         r"state.traces: expected shape \(N >= 1, A, F\) with \(A, F\) = \(3, 2\)"),
        (good, {"state": reset_traces(state, 1)._replace(traces=np.zeros((0, 3, 2))),
                "phi": two[:0], "actions": np.array([], int), "rewards": np.zeros(0),
                "phi_next": two[:0], "actions_next": np.array([], int),
                "terminal": np.zeros(0, bool), "active": np.ones(0, bool)},
         r"state.traces: expected shape \(N >= 1, A, F\)"),
        (good, {"phi": two[:1]}, r"phi: expected shape \(N, F\) = \(2, 2\)"),
        (good, {"phi_next": two[:, :1]}, r"phi_next: expected shape \(N, F\)"),
        (good, {"actions": np.array([0, 1, 2])}, r"actions: expected shape \(N,\)"),
        (good, {"actions_next": np.array([1.0, 0.0])},
         "actions_next: expected integer indices, got dtype float64"),
        (good, {"terminal": np.zeros(3, bool)}, r"terminal: expected shape \(N,\)"),
        (good, {"active": np.ones(1, bool)}, r"active: expected shape \(N,\)"),
        (good, {"step_sizes": np.array([0.1, -0.1])}, "step_sizes: expected entries"),
        (one, {"actions": np.array([0.7])}, "actions: expected integer indices"),
        # a float flag of 0.5 counted as True
        (good, {"terminal": np.full(2, 0.5)}, "terminal: expected booleans"),
        (good, {"active": np.ones(2)}, "active: expected booleans, got dtype float64"),
    ]:  # fmt: skip
        with pytest.raises(ValueError, match=match):
            sarsa_update_batch(**(base | change))


def test_q_values_are_theta_times_phi() -> None:
    """Q(s, a) = θ_a · φ(s), for one state and for a batch (A = F would hide a
    transposed θ from the shapes)."""
    rng = np.random.default_rng(7)
    weights = rng.normal(size=(3, 3))
    phi = rng.normal(size=(4, 3))
    expected = [[weights[a] @ p for a in range(3)] for p in phi]
    np.testing.assert_allclose(q_values(weights, phi), expected, atol=1e-12)
    np.testing.assert_allclose(q_values(weights, phi[0]), expected[0], atol=1e-12)


def test_replacing_trace_takes_phi_only_where_it_is_larger_in_magnitude() -> None:
    """With γλ = 1 the taken action's trace row e = (0.5, −0.8, 0.2, −0.3) and
    φ = (−0.9, 0.3, 0.1, 0.3) give (−0.9, −0.8, 0.2, −0.3): a negative φ_0 larger
    in magnitude replaces, a smaller positive φ_1 above a negative e_1 does not, and
    a tie keeps e; single and (general-path) batch updates agree."""
    config = SarsaConfig(alpha=0.1, lam=1.0, gamma=1.0, traces="replacing")
    row = np.array([0.5, -0.8, 0.2, -0.3])
    phi = np.array([-0.9, 0.3, 0.1, 0.3])
    expected = np.array([-0.9, -0.8, 0.2, -0.3])
    traces = np.stack([row, np.zeros(4)])
    alphas = np.full(4, 0.1)
    one = sarsa_update(SarsaState(np.zeros((2, 4)), traces), phi, 0, 0.0, None,
                       None, alphas, config)  # fmt: skip
    np.testing.assert_array_equal(one.state.traces[0], expected)
    n = 2
    many = sarsa_update_batch(
        SarsaState(np.zeros((2, 4)), np.tile(traces, (n, 1, 1))),
        np.tile(phi, (n, 1)), np.zeros(n, dtype=int), np.zeros(n), np.tile(phi, (n, 1)),
        np.zeros(n, dtype=int), np.ones(n, dtype=bool), np.ones(n, dtype=bool),
        alphas, config,
    )  # fmt: skip
    for j in range(n):
        np.testing.assert_array_equal(many.state.traces[j], one.state.traces)


def test_an_inactive_terminal_episode_leaves_theta_alone() -> None:
    """An inactive episode's δ is 0 whatever its terminal flag: the batch step is
    the active episode's single update (n_active = 1)."""
    rng = np.random.default_rng(8)
    config = SarsaConfig(alpha=0.05, lam=0.9, gamma=0.95)
    weights = rng.normal(size=(2, 4))
    traces = rng.uniform(-1, 1, size=(2, 2, 4))
    phi, phi2 = rng.uniform(-1, 1, size=(2, 2, 4))
    alphas = np.full(4, config.alpha)
    out = sarsa_update_batch(
        SarsaState(weights, traces.copy()), phi, np.array([0, 1]),
        np.array([0.5, 2.0]), phi2, np.array([1, 0]), np.array([False, True]),
        np.array([True, False]), alphas, config,
    )  # fmt: skip
    one = sarsa_update(SarsaState(weights, traces[0].copy()), phi[0], 0, 0.5,
                       phi2[0], 1, alphas, config)  # fmt: skip
    np.testing.assert_allclose(out.state.weights, one.state.weights, atol=1e-12)
    np.testing.assert_array_equal(out.td_error[1], 0.0)
    np.testing.assert_array_equal(out.state.traces[1], traces[1])


def test_closed_ends_of_the_valid_ranges_are_accepted() -> None:
    """α = 1 and ε = 1 are valid (the table's (0, 1] and [0, 1]); a zero step size
    freezes its feature's weight."""
    assert SarsaConfig(alpha=1.0, epsilon=1.0).alpha == 1.0
    rng = np.random.default_rng(9)
    picks = epsilon_greedy_batch(np.tile([0.0, 5.0], (4000, 1)), 1.0, rng=rng)
    # ε = 1: uniform over 2 actions, sd of the count sqrt(4000/4) ≈ 32, ±4 sd = 126
    assert abs(np.sum(picks == 1) - 2000) < 126
    assert epsilon_greedy(np.array([0.0, 5.0]), 1.0, rng=rng) in (0, 1)
    state = init_state(2, 3)
    phi = np.array([1.0, 0.5, -0.5])
    out = sarsa_update(state, phi, 0, -1.0, None, None, np.array([0.1, 0.0, 0.1]),
                       SarsaConfig())  # fmt: skip
    assert out.state.weights[0, 1] == 0.0
    np.testing.assert_allclose(out.state.weights[0, [0, 2]], [-0.1, 0.05], atol=1e-15)


def test_batch_ties_are_broken_only_among_maximal_actions() -> None:
    """Values closer than 1 apart: the random tie-break key must not move the
    argmax to a smaller value."""
    rng = np.random.default_rng(10)
    q = np.tile([0.0, 0.1, 0.05], (1000, 1))
    np.testing.assert_array_equal(epsilon_greedy_batch(q, 0.0, rng=rng), 1)


def test_a_one_episode_batch_that_is_inactive_changes_nothing() -> None:
    """N = 1 takes the single-update path: an inactive episode must still leave θ
    and its trace alone with δ = 0, as in the general path (N > 1)."""
    rng = np.random.default_rng(11)
    config = SarsaConfig(alpha=0.05, lam=0.9, gamma=0.95)
    weights = rng.normal(size=(2, 4))
    traces = rng.uniform(-1, 1, size=(1, 2, 4))
    phi, phi2 = rng.uniform(-1, 1, size=(2, 1, 4))
    out = sarsa_update_batch(
        SarsaState(weights, traces), phi, np.array([0]), np.array([1.0]), phi2,
        np.array([1]), np.array([False]), np.array([False]), np.full(4, 0.05),
        config,
    )  # fmt: skip
    np.testing.assert_array_equal(out.state.weights, weights)
    np.testing.assert_array_equal(out.state.traces, traces)
    np.testing.assert_array_equal(out.td_error, [0.0])


@pytest.mark.parametrize("n", [0, 1, 2], ids=["single", "batch-1", "batch-2"])
def test_updates_leave_the_state_they_are_given_alone(n: int) -> None:
    """A new SarsaState out, the old one unchanged: decaying the traces in place
    rewrote the caller's (the state a caller keeps, e.g. to compare, moved)."""
    rng = np.random.default_rng(12)
    config = SarsaConfig(alpha=0.05, lam=0.9, gamma=0.95)
    weights = rng.normal(size=(2, 4))
    traces = rng.uniform(-1, 1, size=(2, 4) if n == 0 else (n, 2, 4))
    phi, phi2 = rng.uniform(-1, 1, size=(2, 4))
    state = SarsaState(weights.copy(), traces.copy())
    alphas = np.full(4, config.alpha)
    if n == 0:
        out = sarsa_update(state, phi, 0, 1.0, phi2, 1, alphas, config)
    else:
        out = sarsa_update_batch(
            state, np.tile(phi, (n, 1)), np.zeros(n, int), np.ones(n),
            np.tile(phi2, (n, 1)), np.ones(n, int), np.zeros(n, bool),
            np.ones(n, bool), alphas, config,
        )  # fmt: skip
    assert not np.array_equal(out.state.weights, weights)  # it did update
    np.testing.assert_array_equal(state.weights, weights)
    np.testing.assert_array_equal(state.traces, traces)


def test_batch_choices_are_each_rows_own_greedy_action() -> None:
    """ε = 0, no ties: each row's choice is that row's argmax, whatever the other
    rows' values (a maximum over the whole batch left rows below it at action 0)."""
    rng = np.random.default_rng(13)
    q = rng.normal(size=(200, 4)) + rng.normal(scale=10.0, size=(200, 1))
    expected = [max(range(4), key=lambda a, row=row: row[a]) for row in q]
    np.testing.assert_array_equal(epsilon_greedy_batch(q, 0.0, rng=rng), expected)
