"""Gathering: the data are what the simulator does, episodes are reproducible from
the rng, and diverging episodes are dropped and reported."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from hipmdp.data import wrap_angle
from tasks import acrobot, cartpole, collect
from tasks.acrobot import AcrobotParams
from tasks.cartpole import CartpoleParams

ACROBOTS = [AcrobotParams(), AcrobotParams(1.3, 0.7, 0.9, 1.1)]


def gather(seed=0, **kwargs):
    options = dict(episodes_per_instance=2, max_steps=15)
    options.update(kwargs)
    return collect.collect(
        "acrobot", ACROBOTS, rng=np.random.default_rng(seed), **options
    )


def test_transitions_follow_the_simulator_and_carry_the_parameters():
    result = gather(instance_ids=[4, 9])
    t = result.transitions
    # Random torques cannot swing up within 15 steps: every episode is full length.
    assert len(t) == 2 * 2 * 15 and result.n_episodes == 4 and not result.diverged
    assert t.angle_dims == acrobot.ANGLE_DIMS and t.state_dim == acrobot.STATE_DIM
    np.testing.assert_array_equal(np.unique(t.instances), [4, 9])
    assert result.parameters.row(9) == {
        "link_mass_1": 1.3,
        "link_mass_2": 0.7,
        "link_length_1": 0.9,
        "link_length_2": 1.1,
        "link_shape_1": 1.0,
        "link_shape_2": 1.0,
    }
    np.testing.assert_array_equal(t.rewards, -1.0)
    np.testing.assert_array_equal(np.flatnonzero(t.dones), [14, 29, 44, 59])
    within = ~t.dones[:-1]  # consecutive transitions of one episode chain up
    np.testing.assert_array_equal(t.states[1:][within], t.next_states[:-1][within])
    # Replaying transitions on a fresh model of its instance gives the same s'.
    for i in [0, 17, 31, 58]:
        params = ACROBOTS[[4, 9].index(t.instances[i])]
        model = acrobot.make_model(params)
        data = mujoco.MjData(model)
        s = t.states[i]
        data.qpos[:], data.qvel[:] = s[:2], s[2:]
        data.ctrl[0] = acrobot.ACTIONS[t.actions[i]]
        mujoco.mj_step(model, data, acrobot.N_SUB_STEPS)
        replay = np.r_[wrap_angle(data.qpos), data.qvel]
        np.testing.assert_allclose(replay, t.next_states[i], atol=1e-9)


def test_an_episodes_last_transition_ends_in_the_state_that_ended_it():
    """Random pushes topple the pole within the step limit: each episode's last
    next_state is past the failure thresholds (none before it is), and is one
    action of MuJoCo's from its state, as every other next_state is."""
    result = collect.collect(
        "cartpole", [CartpoleParams(1.0, 0.3, 0.8)], episodes_per_instance=4,
        rng=np.random.default_rng(8),
    )  # fmt: skip
    t = result.transitions
    assert np.count_nonzero(t.dones) == 4 and len(t) < 4 * cartpole.DEFAULT_MAX_STEPS
    np.testing.assert_array_equal(cartpole.failed(t.next_states), t.dones)
    model = cartpole.make_model(CartpoleParams(1.0, 0.3, 0.8))
    data = mujoco.MjData(model)
    for i in np.flatnonzero(t.dones):
        data.qpos[:], data.qvel[:] = t.states[i, :2], t.states[i, 2:]
        data.ctrl[0] = cartpole.ACTIONS[t.actions[i]]
        mujoco.mj_step(model, data, cartpole.N_SUB_STEPS)
        replay = np.r_[data.qpos[0], wrap_angle(data.qpos[1]), data.qvel]
        np.testing.assert_allclose(replay, t.next_states[i], atol=1e-9)


def test_same_rng_gives_the_same_data_and_another_does_not():
    a, b, c = gather(seed=1).transitions, gather(seed=1).transitions, gather(2)
    for name in ("states", "actions", "next_states", "instances", "rewards"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.states, c.transitions.states)


def test_each_instance_starts_from_its_own_stream():
    """Instance i's episodes start from states drawn by the i-th stream spawned
    from rng (the policy's is spawned after them): its first start state is that
    of an environment seeded with that stream. Two identical instances thus
    start apart, and one instance's data do not depend on the others'."""
    result = collect.collect(
        "acrobot", [ACROBOTS[0], ACROBOTS[0]], episodes_per_instance=1,
        rng=np.random.default_rng(5), max_steps=3, policy=lambda s: 1,
    )  # fmt: skip
    t = result.transitions
    streams = np.random.default_rng(5).spawn(2)
    for i, stream in enumerate(streams):
        env = acrobot.swingup(ACROBOTS[0], seed=stream, max_steps=3)
        first = t.states[t.instances == i][0]
        np.testing.assert_array_equal(first, env.reset().observation["state"])
    assert not np.array_equal(t.states[t.instances == 0], t.states[t.instances == 1])


def test_a_policy_callable_chooses_the_actions():
    result = collect.collect(
        "cartpole",
        [CartpoleParams()],
        episodes_per_instance=3,
        rng=np.random.default_rng(3),
        policy=lambda s: int(s[1] + 0.5 * s[3] > 0),  # push toward the lean
    )
    t = result.transitions
    np.testing.assert_array_equal(
        t.actions, (t.states[:, 1] + 0.5 * t.states[:, 3] > 0).astype(int)
    )
    # This simple controller balances far longer than random pushes (~20 steps).
    assert len(t) / result.n_episodes > 100
    assert np.all(t.rewards[~t.dones] == 1.0)


def test_diverging_episode_is_dropped_and_reported(monkeypatch):
    """A huge velocity injected at the 20th step makes MuJoCo warn (BADQVEL)."""
    original = acrobot.SwingUp.before_step
    calls = []

    def before_step(self, action, physics):
        original(self, action, physics)
        calls.append(action)
        if len(calls) == 20:  # step 5 of the second episode of instance 0
            physics.data.qvel[0] = 1e12

    monkeypatch.setattr(acrobot.SwingUp, "before_step", before_step)
    result = gather()
    assert result.n_episodes == 4 and len(result.transitions) == 3 * 15
    (divergence,) = result.diverged
    assert divergence[:3] == (0, 1, 4) and "BADQVEL" in divergence.reason
    assert np.all(np.isfinite(result.transitions.next_states))
    assert np.all(np.abs(result.transitions.next_states[:, 2:]) < 100)


def test_non_finite_state_is_dropped_and_reported(monkeypatch):
    original = cartpole.Physics.state

    def state(self):
        s = original(self)
        return s * np.nan if self.data.time > 0.1 else s  # after 5 steps

    monkeypatch.setattr(cartpole.Physics, "state", state)
    result = collect.collect(
        "cartpole",
        [CartpoleParams(), CartpoleParams(pole_mass=0.2)],
        episodes_per_instance=2,
        rng=np.random.default_rng(4),
    )
    assert len(result.diverged) == 4 and len(result.transitions) == 0
    assert {d.reason for d in result.diverged} == {"non-finite state"}
    assert [d.step for d in result.diverged] == [5, 5, 5, 5]
    assert result.parameters.values.shape == (2, 3)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(domain="no_such_domain"), "domain must be one of"),
        (dict(instances=[]), "at least one"),
        (dict(instances=[CartpoleParams()]), "instances must be AcrobotParams"),
        (dict(instance_ids=[0, 0]), "instance_ids must be 2 distinct"),
        (dict(instance_ids=[0]), "instance_ids must be 2 distinct"),
        (dict(instance_ids=[0.5, 1.5]), "instance_ids must be 2 distinct ints"),
        (dict(instance_ids=[True, 2]), "instance_ids must be 2 distinct ints"),
        (dict(episodes_per_instance=0), "episodes_per_instance must be"),
        (dict(episodes_per_instance=True), "episodes_per_instance must be"),
        (dict(max_steps=-1), "max_steps must be"),
        (dict(rng=0), "rng: expected a numpy Generator or a sequence of 2"),
        (dict(rng=[np.random.default_rng(0)]), "rng: expected .* a sequence of 2"),
        (dict(rng=[np.random.default_rng(0), 1]), "rng: expected .* a sequence of 2"),
        (dict(policy="random"), "policy must be callable"),
        (dict(policy=lambda s: 3), r"policy returned action 3, expected \[0, 3\)"),
        (dict(policy=lambda s: 0.5), "policy must return an int"),
        (dict(policy=lambda s: True), "policy must return an int"),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs, message):
    arguments = dict(
        domain="acrobot",
        instances=ACROBOTS,
        episodes_per_instance=1,
        rng=np.random.default_rng(0),
        max_steps=3,
    )
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=message):
        collect.collect(
            arguments.pop("domain"), arguments.pop("instances"), **arguments
        )


@pytest.mark.parametrize("n_actions", [0, -2, True, 2.0])
def test_the_random_policy_refuses_a_bad_action_count_when_made(n_actions):
    """Not at its first draw inside an episode (0 actions), and not silently as
    one action (True) or a float count."""
    with pytest.raises(ValueError, match="n_actions must be a positive int"):
        collect.random_policy(n_actions, rng=np.random.default_rng(0))


def test_the_random_policy_is_uniform_and_draws_from_its_own_stream():
    """random_policy draws every action 0..A-1. With one Generator, collect's
    random policy draws from one more stream spawned after the instances'; with
    one Generator per instance, each spawns two: the environment's, then its
    random policy's."""
    draw = collect.random_policy(3, rng=np.random.default_rng(0))
    assert {draw(None) for _ in range(300)} == {0, 1, 2}
    shared = gather(seed=6, episodes_per_instance=1, max_steps=5).transitions
    stream = np.random.default_rng(6).spawn(3)[2]  # after the two instances'
    np.testing.assert_array_equal(
        shared.actions, [stream.integers(3) for _ in range(10)]
    )
    own = collect.collect(
        "acrobot", ACROBOTS, episodes_per_instance=1, max_steps=5,
        rng=[np.random.default_rng(s) for s in (7, 8)],
    ).transitions  # fmt: skip
    for i, seed in enumerate((7, 8)):
        env_stream, policy_stream = np.random.default_rng(seed).spawn(2)
        env = acrobot.swingup(ACROBOTS[i], seed=env_stream, max_steps=5)
        mine = own.instances == i
        first = env.reset().observation["state"]
        np.testing.assert_array_equal(own.states[mine][0], first)
        np.testing.assert_array_equal(
            own.actions[mine], [policy_stream.integers(3) for _ in range(5)]
        )


def test_sarsa_gathering_keeps_the_step_limit_and_the_environments_stream():
    """collect_sarsa's max_steps is every episode's limit, the transitions carry
    the domain's seconds per action, and instance i's episodes start where an
    environment seeded with the first of the two streams its own spawns starts
    (the second is the agent's)."""
    result = collect.collect_sarsa(
        "acrobot", ACROBOTS, episodes_per_instance=2, max_steps=6,
        rng=[np.random.default_rng(s) for s in (7, 8)],
    )  # fmt: skip
    t = result.transitions
    assert len(t) == 2 * 2 * 6 and result.n_episodes == 4
    np.testing.assert_array_equal(np.flatnonzero(t.dones), [5, 11, 17, 23])
    # the seconds per action that unwrap fast angle changes: the acrobot's 0.2 s
    assert t.dt == acrobot.CONTROL_TIMESTEP and t.angle_dims == acrobot.ANGLE_DIMS
    for i, seed in enumerate((7, 8)):
        env_stream, _ = np.random.default_rng(seed).spawn(2)
        env = acrobot.swingup(ACROBOTS[i], seed=env_stream, max_steps=6)
        first = env.reset().observation["state"]
        np.testing.assert_array_equal(t.states[t.instances == i][0], first)


def _sarsa_diverging_at(monkeypatch, steps) -> collect.Collection:
    """``collect_sarsa`` on ``ACROBOTS`` (ids 4 and 9, 2 episodes of 6 steps
    each) with the velocity blown up after every step numbered in ``steps``
    (counted from 1 over the whole run)."""
    original = acrobot.SwingUp.before_step
    calls = []

    def before_step(self, action, physics):
        original(self, action, physics)
        calls.append(action)
        if len(calls) in steps:
            physics.data.qvel[0] = 1e12

    monkeypatch.setattr(acrobot.SwingUp, "before_step", before_step)
    return collect.collect_sarsa(
        "acrobot", ACROBOTS, episodes_per_instance=2, max_steps=6,
        rng=np.random.default_rng(0), instance_ids=[4, 9],
    )  # fmt: skip


def test_a_diverging_sarsa_instance_is_dropped_whole_and_reported(monkeypatch):
    """Learning cannot go on past a diverged step: all the instance's episodes
    are dropped, reported as one Divergence with episode and step -1."""
    result = _sarsa_diverging_at(monkeypatch, {8})  # instance 0's 2nd episode
    (divergence,) = result.diverged
    assert divergence[:3] == (4, -1, -1) and "BADQVEL" in divergence.reason
    assert result.n_episodes == 4 and len(result.transitions) == 2 * 6
    np.testing.assert_array_equal(np.unique(result.transitions.instances), [9])


def test_sarsa_gathering_where_every_instance_diverges_is_empty_not_an_error(
    monkeypatch,
):
    """Every instance's first step blows up: the collection still comes back, with
    no transitions (of the domain's state dimension and angles) and one
    Divergence per instance, so a caller can see what was dropped."""
    result = _sarsa_diverging_at(monkeypatch, range(1, 100))  # every step
    t = result.transitions
    assert len(t) == 0 and t.state_dim == acrobot.STATE_DIM
    assert t.angle_dims == acrobot.ANGLE_DIMS and t.dt == acrobot.CONTROL_TIMESTEP
    assert [d[:3] for d in result.diverged] == [(4, -1, -1), (9, -1, -1)]
    assert result.n_episodes == 4
