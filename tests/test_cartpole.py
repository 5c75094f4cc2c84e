"""The cart-pole model is the classic cart-pole, with every parameter rewritten
consistently; the balancing task's reward, failure and step limit."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest

from tasks import cartpole
from tasks.cartpole import CartpoleParams
from tests._rk4 import assert_fourth_order

REWRITTEN = [
    CartpoleParams(),
    CartpoleParams(1.0, 0.3, 0.8),
    CartpoleParams(2.5, 1.0, 0.2),
    CartpoleParams(0.1, 2.0, 2.5),
]


def classic_accelerations(s: np.ndarray, F: float, p: CartpoleParams) -> np.ndarray:
    """(ẍ, θ̈) of Barto, Sutton & Anderson (1983) without friction, g = 9.81."""
    M, m, l, g = p.cart_mass, p.pole_mass, p.pole_half_length, 9.81
    _, theta, _, dtheta = s
    v = (F + m * l * dtheta**2 * np.sin(theta)) / (M + m)
    ddtheta = (g * np.sin(theta) - np.cos(theta) * v) / (
        l * (4 / 3 - m * np.cos(theta) ** 2 / (M + m))
    )
    ddx = v - m * l * ddtheta * np.cos(theta) / (M + m)
    return np.array([ddx, ddtheta])


def mujoco_accelerations(model, s, F):
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.ctrl[0] = s[:2], s[2:], F
    mujoco.mj_forward(model, data)
    return data.qacc.copy()


@pytest.mark.parametrize("params", REWRITTEN, ids=str)
def test_accelerations_equal_classic_equations(params):
    rng = np.random.default_rng(0)
    model = cartpole.make_model(params)
    for _ in range(50):
        s = rng.uniform(-1, 1, 4) * [2.4, np.pi, 3, 10]
        F = rng.uniform(-10, 10)
        np.testing.assert_allclose(
            mujoco_accelerations(model, s, F),
            classic_accelerations(s, F, params),
            rtol=1e-8,
            atol=1e-8,
        )


def test_nominal_model_is_the_classic_cartpole():
    model = cartpole.make_model()
    np.testing.assert_array_equal(model.body_mass[1:], [1.0, 0.1])
    np.testing.assert_allclose(model.body_inertia[2, 1], 0.1 * 1.0**2 / 12, rtol=1e-15)
    np.testing.assert_array_equal(model.body_ipos[2], [0, 0, 0.5])
    np.testing.assert_array_equal(model.opt.gravity, [0, 0, -9.81])
    np.testing.assert_array_equal(model.dof_damping, [0, 0])
    np.testing.assert_array_equal(model.dof_frictionloss, [0, 0])
    assert model.nu == 1 and model.actuator_trnid[0, 0] == model.joint("slider").id
    np.testing.assert_array_equal(
        model.actuator_ctrlrange[0], [cartpole.ACTIONS.min(), cartpole.ACTIONS.max()]
    )
    np.testing.assert_array_equal(cartpole.ACTIONS, [-10.0, 10.0])
    assert model.opt.timestep * cartpole.N_SUB_STEPS == pytest.approx(0.02, abs=1e-15)


@pytest.mark.parametrize("params", REWRITTEN[:3], ids=str)
def test_one_action_converges_to_the_ode_at_fourth_order(params):
    """MuJoCo's RK4 converges to the classic equations at fourth order as its step
    is halved (`tests._rk4`; measured ratios 15.8-16.2, one 19.1; errors at the
    model's own step up to 1.2e-7)."""
    assert_fourth_order(cartpole, classic_accelerations, params, [2.4, 0.5, 2, 3])


@pytest.mark.parametrize("field", [f.name for f in dataclasses.fields(CartpoleParams)])
def test_every_parameter_changes_the_accelerations(field):
    rng = np.random.default_rng(2)
    states = rng.uniform(-1, 1, (10, 4)) * [1, 0.5, 1, 1]
    nominal = CartpoleParams()
    changed = cartpole.make_model(
        dataclasses.replace(nominal, **{field: 1.5 * getattr(nominal, field)})
    )
    nominal = cartpole.make_model(nominal)
    difference = max(
        np.abs(
            mujoco_accelerations(nominal, s, 10.0)
            - mujoco_accelerations(changed, s, 10.0)
        ).max()
        for s in states
    )
    assert difference > 1e-2


@pytest.mark.parametrize("field", [f.name for f in dataclasses.fields(CartpoleParams)])
@pytest.mark.parametrize(
    "value, message",
    [
        (float("nan"), "not finite"),
        (float("-inf"), "not finite"),
        (0.0, "lower bound"),
        (-0.5, "lower bound"),
        (100.0, "upper bound"),
        (None, "not a real number"),
    ],
)
def test_invalid_parameters_name_the_field_and_bound(field, value, message):
    with pytest.raises(ValueError, match=rf"CartpoleParams\.{field} .*{message}"):
        CartpoleParams(**{field: value})


def test_failed_marks_the_classic_thresholds():
    limit = 12 * np.pi / 180
    states = np.array(
        [
            [0.0, 0.99 * limit, 5.0, -5.0],
            [0.0, 1.01 * limit, 0.0, 0.0],
            [0.0, -1.01 * limit, 0.0, 0.0],
            [2.39, 0.0, 0.0, 0.0],
            [2.41, 0.0, 0.0, 0.0],
            [-2.41, 0.0, 0.0, 0.0],
            # on a threshold is not past it (the classic code's strict `>`)
            [2.4, -limit, 0.0, 0.0],
            [-2.4, limit, 0.0, 0.0],
        ]
    )
    np.testing.assert_array_equal(
        cartpole.failed(states), [False, True, True, False, True, True, False, False]
    )
    np.testing.assert_array_equal(
        cartpole.failed(states.reshape(2, 4, 4)).shape, (2, 4)
    )


def test_failed_is_decided_at_the_documented_thresholds_exactly():
    """12° and 2.4 m themselves (the module docstring's), not values near them:
    a relative 1e-9 either side of each is inside, then past it."""
    limit = np.deg2rad(12.0)
    for sign in (1.0, -1.0):
        for below, above in ((1 - 1e-9, False), (1 + 1e-9, True)):
            theta = np.array([0.0, sign * below * limit, 0.0, 0.0])
            x = np.array([sign * below * 2.4, 0.0, 0.0, 0.0])
            assert cartpole.failed(theta) == above and cartpole.failed(x) == above


def test_episode_starts_near_upright_and_ends_at_failure():
    env = cartpole.balance(seed=4)
    first = env.reset()
    assert np.all(np.abs(first.observation["state"]) <= cartpole.INITIAL_NOISE)
    step = env.step(1)
    assert step.reward == 1.0 and step.discount == 1.0 and step.mid()
    env.physics.data.qpos[:] = [0.0, 0.5]  # leaning far past 12 degrees
    step = env.step(1)
    assert step.last() and step.discount == 0.0 and step.reward == 0.0


def test_failing_on_the_last_step_is_a_termination():
    """A failure on the step the limit would truncate still ends the episode as
    a failure: reward 0 and discount 0 (a learner must not bootstrap from it)."""
    env = cartpole.balance(seed=4, max_steps=1)
    env.reset()
    env.physics.data.qpos[:] = [0.0, 0.5]  # leaning far past 12 degrees
    step = env.step(1)
    assert step.last() and step.discount == 0.0 and step.reward == 0.0


def test_always_pushing_one_way_fails_within_the_step_limit():
    env = cartpole.balance(seed=5)
    env.reset()
    n_steps, step = 0, env.step(1)
    while not step.last():
        step, n_steps = env.step(1), n_steps + 1
    assert n_steps < cartpole.DEFAULT_MAX_STEPS and step.discount == 0.0
    # Pushing +x tips the pole toward -x.
    assert step.observation["state"][1] < -cartpole.THETA_LIMIT


def test_episode_is_truncated_at_the_step_limit():
    env = cartpole.balance(seed=6, max_steps=3)
    env.reset()
    steps = [env.step(i % 2) for i in range(3)]
    assert [s.last() for s in steps] == [False, False, True]
    assert steps[-1].discount == 1.0


def test_link_points_follow_the_classic_kinematics():
    from tasks.cartpole import CartpoleParams, link_points

    params = CartpoleParams(cart_mass=1.0, pole_mass=0.2, pole_half_length=0.7)
    rng = np.random.default_rng(4)
    states = rng.uniform(-2, 2, size=(15, 4))
    pts = link_points(states, params)
    x, th = states[:, 0], states[:, 1]
    np.testing.assert_allclose(pts[:, 0], np.c_[x, 0 * x, 0 * x], atol=1e-12)
    np.testing.assert_allclose(pts[:, 1], pts[:, 0], atol=1e-12)  # pivot on the cart
    # θ > 0 leans toward +x; the tip is 2l from the pivot
    tip = np.c_[x + 1.4 * np.sin(th), 0 * x, 1.4 * np.cos(th)]
    np.testing.assert_allclose(pts[:, 2], tip, atol=1e-12)


@pytest.mark.parametrize("params", REWRITTEN, ids=str)
def test_pole_acceleration_is_the_largest_forces_greatest_effect(params):
    """`pole_acceleration` (which sets the step) is the largest |θ̈| the largest
    force adds at any pole angle: MuJoCo's θ̈ under F = 10 N minus under F = 0
    (linear in F: (M⁻¹)₂₁ F), at rest on a 1° grid of angles, which holds the
    upright and hanging poles where it peaks."""
    model = cartpole.make_model(params)
    effect = [
        abs(
            mujoco_accelerations(model, np.array([0.0, theta, 0.0, 0.0]), 10.0)[1]
            - mujoco_accelerations(model, np.array([0.0, theta, 0.0, 0.0]), 0.0)[1]
        )
        for theta in np.linspace(-np.pi, np.pi, 361)
    ]
    assert cartpole.pole_acceleration(params) == pytest.approx(max(effect), rel=1e-9)


@pytest.mark.parametrize("half_length, n_sub", [(0.232, 2), (0.225, 4)])
def test_the_step_is_halved_just_past_32_rad_s2(half_length, n_sub):
    """The documented threshold, `POLE_ACCELERATION` = 32 rad/s² under the
    largest force, on each side of it: a short pole at 31.5 rad/s² (MuJoCo's θ̈
    under 10 N minus under 0, upright at rest, where it peaks) keeps 2 steps of
    10 ms, at 32.5 the step is halved."""
    params = CartpoleParams(pole_half_length=half_length)
    model, upright = cartpole.make_model(params), np.zeros(4)
    peak = abs(
        mujoco_accelerations(model, upright, 10.0)[1]
        - mujoco_accelerations(model, upright, 0.0)[1]
    )
    assert (peak > 32.0) == (n_sub == 4) and abs(peak - 32.0) < 1.0
    assert cartpole.sub_steps(params) == n_sub
    assert model.opt.timestep == 0.01 / (n_sub // 2)


def test_a_light_cart_poles_action_still_lasts_0_02_s():
    """At the lightest corner the step is 10 ms / 2⁵ (`sub_steps`): the
    environment takes that many more steps per action, so an action still
    lasts the documented 0.02 s."""
    light = CartpoleParams(0.1, 0.01, 0.1)
    assert cartpole.sub_steps(light) == 2**5 * cartpole.N_SUB_STEPS
    env = cartpole.balance(light, seed=0)
    env.reset()
    env.step(0)
    assert env.physics.data.time == pytest.approx(cartpole.CONTROL_TIMESTEP)
    assert env.control_timestep() == pytest.approx(cartpole.CONTROL_TIMESTEP)


@pytest.mark.parametrize("params", REWRITTEN, ids=str)
def test_the_drawn_pole_spans_the_pole(params):
    """The capsule a rendering shows runs from the pivot to the tip: half-length
    `l` centred at `l` above the pivot."""
    model = cartpole.make_model(params)
    l = params.pole_half_length
    assert model.geom("pole").size[1] == pytest.approx(l, rel=1e-12)
    np.testing.assert_allclose(model.geom("pole").pos, [0.0, 0.0, l], rtol=1e-12)
