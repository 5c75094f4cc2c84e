"""The acrobot model is the Sutton & Barto acrobot, with every parameter rewritten
consistently; the swing-up task's reward, goal and step limit."""

from __future__ import annotations

import dataclasses
import re

import mujoco
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from tasks import acrobot
from tasks.acrobot import AcrobotParams
from tests._rk4 import assert_fourth_order

REWRITTEN = [
    AcrobotParams(),
    AcrobotParams(0.7, 1.3, 1.0, 1.0),
    AcrobotParams(1.3, 0.7, 0.6, 1.8),
    AcrobotParams(0.2, 5.0, 5.0, 0.2),
    # the book's I = 1 held while the masses change, and shapes of their own
    acrobot.book_inertia(0.7, 1.3),
    AcrobotParams(1.3, 0.7, 0.6, 1.8, link_shape_1=0.7, link_shape_2=1.5),
]
#: the two rewritten masses, and the same with the book's inertias
MASSES = [REWRITTEN[1], REWRITTEN[2], REWRITTEN[4]]


def book_accelerations(s: np.ndarray, tau: float, p: AcrobotParams) -> np.ndarray:
    """(θ̈₁, θ̈₂) from Sutton & Barto (1998) §11.3, with lc = l/2, g = 9.8 and the
    instance's inertias."""
    m1, m2 = p.link_mass_1, p.link_mass_2
    l1, l2 = p.link_length_1, p.link_length_2
    lc1, lc2, g = l1 / 2, l2 / 2, 9.8
    I1, I2 = p.link_shape_1 * m1 * l1**2, p.link_shape_2 * m2 * l2**2
    t1, t2, dt1, dt2 = s
    d1 = m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * np.cos(t2)) + I1 + I2
    d2 = m2 * (lc2**2 + l1 * lc2 * np.cos(t2)) + I2
    phi2 = m2 * lc2 * g * np.cos(t1 + t2 - np.pi / 2)
    phi1 = (
        -m2 * l1 * lc2 * dt2**2 * np.sin(t2)
        - 2 * m2 * l1 * lc2 * dt2 * dt1 * np.sin(t2)
        + (m1 * lc1 + m2 * l1) * g * np.cos(t1 - np.pi / 2)
        + phi2
    )
    ddt2 = (tau + d2 / d1 * phi1 - m2 * l1 * lc2 * dt1**2 * np.sin(t2) - phi2) / (
        m2 * lc2**2 + I2 - d2**2 / d1
    )
    ddt1 = -(d2 * ddt2 + phi1) / d1
    return np.array([ddt1, ddt2])


def mujoco_accelerations(model, s, tau):
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.ctrl[0] = s[:2], s[2:], tau
    mujoco.mj_forward(model, data)
    return data.qacc.copy()


@pytest.mark.parametrize("params", REWRITTEN, ids=str)
def test_accelerations_equal_book_equations(params):
    rng = np.random.default_rng(0)
    model = acrobot.make_model(params)
    for _ in range(50):
        s = rng.uniform(-1, 1, 4) * [np.pi, np.pi, 4 * np.pi, 9 * np.pi]
        tau = rng.uniform(-1, 1)
        np.testing.assert_allclose(
            mujoco_accelerations(model, s, tau),
            book_accelerations(s, tau, params),
            rtol=1e-8,
            atol=1e-8,
        )


def test_nominal_model_is_the_book_acrobot():
    model = acrobot.make_model()
    np.testing.assert_array_equal(model.body_mass[1:], [1.0, 1.0])
    np.testing.assert_array_equal(model.body_inertia[1:, 1], [1.0, 1.0])
    np.testing.assert_array_equal(model.body_ipos[1:], [[0, 0, -0.5], [0, 0, -0.5]])
    np.testing.assert_array_equal(model.opt.gravity, [0, 0, -9.8])
    np.testing.assert_array_equal(model.dof_damping, [0, 0])
    np.testing.assert_array_equal(model.dof_armature, [0, 0])
    assert model.nu == 1 and model.actuator_trnid[0, 0] == model.joint("elbow").id
    np.testing.assert_array_equal(
        model.actuator_ctrlrange[0], [acrobot.ACTIONS.min(), acrobot.ACTIONS.max()]
    )
    np.testing.assert_array_equal(acrobot.ACTIONS, [-1.0, 0.0, 1.0])
    assert model.opt.timestep * acrobot.N_SUB_STEPS == pytest.approx(0.2, abs=1e-15)


@pytest.mark.parametrize("params", MASSES, ids=str)
def test_one_action_converges_to_the_ode_at_fourth_order(params):
    """MuJoCo's RK4 converges to Sutton & Barto's equations at fourth order as its
    step is halved (`tests._rk4`; measured ratios 15.8-16.6; errors at the model's
    own step up to 1.6e-8)."""
    assert_fourth_order(acrobot, book_accelerations, params, [np.pi, np.pi, 5, 8])


def test_a_fast_instance_converges_at_its_own_step():
    """A light, short-linked acrobot (160 steps of 1.25 ms per action, `sub_steps`)
    from states as fast as its random-torque episodes reach, at its own step.
    (At the bounds' corners the step is so fine that h/4's error is round-off,
    where no order can be read.)"""
    params = AcrobotParams(0.5, 0.3, 0.6, 0.4)
    assert acrobot.sub_steps(params) == 8 * acrobot.N_SUB_STEPS
    assert_fourth_order(acrobot, book_accelerations, params, [np.pi, np.pi, 20, 60])


def elbow_responses(params: AcrobotParams, theta_2: np.ndarray) -> np.ndarray:
    """|θ̈₂| that 1 N·m of elbow torque adds, at rest, per elbow angle: MuJoCo's
    θ̈₂ under τ = 1 minus under τ = 0 (linear in τ: (M⁻¹)₂₂ τ)."""
    model = acrobot.make_model(params)
    return np.array(
        [
            abs(
                mujoco_accelerations(model, np.array([0.0, t, 0.0, 0.0]), 1.0)[1]
                - mujoco_accelerations(model, np.array([0.0, t, 0.0, 0.0]), 0.0)[1]
            )
            for t in theta_2
        ]
    )


@pytest.mark.parametrize("params", REWRITTEN, ids=str)
def test_elbow_acceleration_is_the_unit_torques_greatest_effect(params):
    """`elbow_acceleration` (which sets the step) is the largest |θ̈₂| per N·m of
    elbow torque at any elbow angle, against MuJoCo on a 2° grid of angles,
    which holds the straight and folded arms (θ₂ = 0, ±π)."""
    effect = elbow_responses(params, np.linspace(-np.pi, np.pi, 181))
    assert acrobot.elbow_acceleration(params) == pytest.approx(max(effect), rel=1e-9)


@pytest.mark.parametrize("link_mass_2, n_sub", [(0.3, 20), (0.29, 40)])
def test_the_step_is_halved_just_past_4_rad_s2_per_n_m(link_mass_2, n_sub):
    """The documented threshold, `ELBOW_ACCELERATION` = 4 rad/s² per N·m of the
    largest torque (1 N·m), on each side of it: a light second link at 3.98
    (MuJoCo's response) keeps 20 steps of 10 ms, at 4.08 the step is halved."""
    params = AcrobotParams(link_mass_2=link_mass_2)
    peak = max(elbow_responses(params, np.linspace(-np.pi, np.pi, 181)))
    assert (peak > 4.0) == (n_sub == 40) and abs(peak - 4.0) < 0.1
    assert acrobot.sub_steps(params) == n_sub
    assert acrobot.make_model(params).opt.timestep == 0.01 / (n_sub // 20)


@pytest.mark.parametrize("field", [f.name for f in dataclasses.fields(AcrobotParams)])
def test_every_parameter_changes_the_accelerations(field):
    rng = np.random.default_rng(2)
    states = rng.uniform(-1, 1, (10, 4)) * [np.pi, np.pi, 3, 3]
    nominal = acrobot.make_model()
    changed = acrobot.make_model(dataclasses.replace(AcrobotParams(), **{field: 1.2}))
    difference = max(
        np.abs(
            mujoco_accelerations(nominal, s, 1.0)
            - mujoco_accelerations(changed, s, 1.0)
        ).max()
        for s in states
    )
    assert difference > 1e-2


@pytest.mark.parametrize("params", REWRITTEN, ids=str)
def test_tip_height_is_the_tip_site_height(params):
    rng = np.random.default_rng(3)
    states = rng.uniform(-np.pi, np.pi, (20, 4))
    model = acrobot.make_model(params)
    data = mujoco.MjData(model)
    heights = []
    for s in states:
        data.qpos[:] = s[:2]
        mujoco.mj_kinematics(model, data)
        heights.append(data.site("tip").xpos[2])
    np.testing.assert_allclose(acrobot.tip_height(states, params), heights, atol=1e-12)
    np.testing.assert_array_equal(
        acrobot.goal_reached(states, params),
        np.array(heights) > params.link_length_1,
    )


@pytest.mark.parametrize("params", REWRITTEN, ids=str)
def test_the_drawn_links_span_the_links(params):
    """The capsules a rendering shows run from each joint to the next joint or
    the tip: half-length `l_i / 2`, centred `l_i / 2` below the joint."""
    model = acrobot.make_model(params)
    for name, l in (("link_1", params.link_length_1), ("link_2", params.link_length_2)):
        assert model.geom(name).size[1] == pytest.approx(l / 2, rel=1e-12)
        np.testing.assert_allclose(model.geom(name).pos, [0, 0, -l / 2], rtol=1e-12)


FIELDS = {f.name: f.metadata["bounds"] for f in dataclasses.fields(AcrobotParams)}


@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize(
    "value, message",
    [
        (float("nan"), "not finite"),
        (float("inf"), "not finite"),
        (0.0, "lower bound {low}"),
        (-1.0, "lower bound {low}"),
        ("above", "upper bound {high}"),
        ("1.0", "not a real number"),
    ],
)
def test_invalid_parameters_name_the_field_and_bound(field, value, message):
    low, high = FIELDS[field]
    value = 1.1 * high if value == "above" else value
    message = re.escape(message.format(low=low, high=high))
    with pytest.raises(ValueError, match=rf"AcrobotParams\.{field} .*{message}"):
        AcrobotParams(**{field: value})


def test_a_parameters_message_gives_its_unit_and_none_for_a_shape():
    """The unit follows each bound; a dimensionless field (`-` in the table) has
    none printed."""
    with pytest.raises(ValueError) as error:
        AcrobotParams(link_mass_1=9.0)
    assert str(error.value) == (
        "AcrobotParams.link_mass_1 must be in [0.2, 5.0] kg, got 9.0 "
        "(outside the upper bound 5.0 kg)"
    )
    with pytest.raises(ValueError) as error:
        AcrobotParams(link_shape_1=2.0)
    assert str(error.value) == (
        "AcrobotParams.link_shape_1 must be in [0.7, 1.5], got 2.0 "
        "(outside the upper bound 1.5)"
    )


def test_inertia_is_the_shape_times_m_l_squared():
    params = AcrobotParams(0.7, 1.3, 0.9, 1.2, link_shape_1=0.7, link_shape_2=1.5)
    assert params.inertias == pytest.approx((0.7 * 0.7 * 0.81, 1.5 * 1.3 * 1.44))
    assert AcrobotParams(0.7, 1.3).inertias == pytest.approx((0.7, 1.3))
    assert acrobot.book_inertia(0.7, 1.3).inertias == pytest.approx((1.0, 1.0))
    assert acrobot.book_inertia(0.9, 1.2, 1.0, 1.05).inertias == pytest.approx((1, 1))
    assert acrobot.book_inertia(1.2, 0.9, 1.05, 1.0).inertias == pytest.approx((1, 1))
    # with_book_inertia keeps the masses and lengths, rewrites only the shapes
    params = AcrobotParams(0.9, 1.2, 1.1, 0.95, link_shape_1=0.8, link_shape_2=1.3)
    booked = acrobot.with_book_inertia(params)
    assert booked.inertias == pytest.approx((1.0, 1.0))
    assert booked == dataclasses.replace(
        params, link_shape_1=booked.link_shape_1, link_shape_2=booked.link_shape_2
    )
    with pytest.raises(ValueError, match=r"AcrobotParams\.link_shape_1 .*upper"):
        acrobot.book_inertia(0.6)  # I = 1 would need k = 1.67
    # a zero mass or length: the field's bound, not a ZeroDivisionError
    with pytest.raises(ValueError, match=r"AcrobotParams\.link_mass_1 .*lower"):
        acrobot.book_inertia(0.0)
    with pytest.raises(ValueError, match=r"AcrobotParams\.link_length_2 .*lower"):
        acrobot.book_inertia(1.0, 1.0, 1.0, 0.0)


def test_book_inertia_range_is_where_a_link_can_keep_i_equal_1():
    """`book_inertia_range()` bounds `m l²`: `book_inertia` accepts a link at
    either end (its shape `1 / (m l²)` is then a bound of `link_shape`) and
    refuses one 1% outside."""
    low, high = acrobot.book_inertia_range()
    assert low == pytest.approx(1 / 1.5) and high == pytest.approx(1 / 0.7)
    for m_l2 in (low, high):
        assert acrobot.book_inertia(m_l2).inertias == pytest.approx((1.0, 1.0))
    for m_l2, bound in ((0.99 * low, "upper"), (1.01 * high, "lower")):
        with pytest.raises(ValueError, match=rf"link_shape_1 .*{bound}"):
            acrobot.book_inertia(m_l2)


def accelerations(params: AcrobotParams, tau: float, states: np.ndarray) -> np.ndarray:
    model = acrobot.make_model(params)
    return np.array([mujoco_accelerations(model, s, tau) for s in states])


def test_with_scaled_inertia_only_the_mass_ratio_shapes_the_passive_motion():
    # I = m l²: M, the Coriolis and the gravity terms all scale with c when both
    # masses do, so without torque the motion is the same and the torque's
    # effect scales by 1/c. With the book's I = 1 held, the motion changes.
    states = np.random.default_rng(7).uniform(-1, 1, (10, 4)) * [np.pi, np.pi, 3, 6]
    light, heavy = AcrobotParams(0.7, 0.7), AcrobotParams(1.3, 1.3)
    np.testing.assert_allclose(
        accelerations(light, 0.0, states), accelerations(heavy, 0.0, states), atol=1e-9
    )
    torque = {
        p: accelerations(p, 1.0, states) - accelerations(p, 0.0, states)
        for p in (light, heavy)
    }
    np.testing.assert_allclose(torque[light] * 0.7, torque[heavy] * 1.3, atol=1e-9)
    passive = [
        accelerations(acrobot.book_inertia(m, m), 0.0, states) for m in (0.7, 1.3)
    ]
    assert np.abs(passive[0] - passive[1]).max() > 1.0


def test_episode_starts_near_hanging_and_ends_at_the_goal():
    env = acrobot.swingup(seed=4)
    first = env.reset()
    assert np.all(np.abs(first.observation["state"]) <= acrobot.INITIAL_NOISE)
    step = env.step(1)
    assert step.reward == -1.0 and step.discount == 1.0 and step.mid()
    env.physics.data.qpos[:] = [np.pi, 0.0]  # standing straight up: above the goal
    env.physics.data.qvel[:] = 0.0
    step = env.step(1)
    assert step.last() and step.discount == 0.0 and step.reward == -1.0


def test_reaching_the_goal_on_the_last_step_is_a_termination():
    """A goal reached on the step the limit would truncate still ends the
    episode at the goal: discount 0 (a learner must not bootstrap from it)."""
    env = acrobot.swingup(seed=4, max_steps=1)
    env.reset()
    env.physics.data.qpos[:] = [np.pi, 0.0]  # standing straight up: above the goal
    env.physics.data.qvel[:] = 0.0
    step = env.step(1)
    assert step.last() and step.discount == 0.0


def test_the_goal_line_is_the_instances_first_link_length():
    """The task ends at the instance's goal line, `y > l₁`: a tip 0.8 m up is
    past it for l₁ = 0.6 m, and short of it for the nominal l₁ = 1 m."""
    params = REWRITTEN[2]  # l₁ = 0.6 m, l₂ = 1.8 m
    s = np.array([0.0, np.arccos(-1.4 / 1.8), 0.0, 0.0])  # y = -0.6 + 1.4
    assert acrobot.tip_height(s, params) == pytest.approx(0.8)
    assert acrobot.swingup(params, seed=0).task.is_terminal(s)
    up = np.array([np.pi, np.arccos(-0.2), 0.0, 0.0])  # nominal: y = 1 - 0.2
    assert acrobot.tip_height(up, acrobot.AcrobotParams()) == pytest.approx(0.8)
    assert not acrobot.swingup(seed=0).task.is_terminal(up)


def test_a_tip_exactly_on_the_goal_line_has_not_reached_it():
    """The goal is strictly above the line, `y > l₁` (the module docstring's
    "higher than", Gym's strict `>`). Straight down with the elbow folded back
    up, `θ = (0, π)`, and `l₂ = 2 l₁`: the tip is at `-l₁ + l₂ = l₁` exactly;
    a hair longer `l₂` puts it past the line."""
    s = np.array([0.0, np.pi, 0.0, 0.0])
    on_line = AcrobotParams(link_length_1=1.0, link_length_2=2.0)
    assert acrobot.tip_height(s, on_line) == 1.0  # cos π = -1 exactly
    assert not acrobot.goal_reached(s, on_line)
    assert not acrobot.swingup(on_line, seed=0).task.is_terminal(s)
    past = AcrobotParams(link_length_1=1.0, link_length_2=2.0 + 1e-9)
    assert acrobot.goal_reached(s, past)


def test_episode_is_truncated_at_the_step_limit():
    env = acrobot.swingup(seed=5, max_steps=3)
    env.reset()
    steps = [env.step(1) for _ in range(3)]
    assert [s.last() for s in steps] == [False, False, True]
    assert steps[-1].discount == 1.0


@pytest.mark.parametrize("action", [3, -1, 1.0, np.array([1]), "1", True, np.True_])
def test_invalid_action_is_rejected(action):
    env = acrobot.swingup(seed=6)
    env.reset()
    with pytest.raises(ValueError, match="integer index"):
        env.step(action)


def test_link_points_follow_the_book_kinematics():
    from tasks.acrobot import AcrobotParams, link_points, tip_height

    params = AcrobotParams(
        link_mass_1=1.0, link_mass_2=1.0, link_length_1=0.8, link_length_2=1.3
    )
    rng = np.random.default_rng(3)
    states = rng.uniform(-np.pi, np.pi, size=(20, 4))
    pts = link_points(states, params)
    t1, t12 = states[:, 0], states[:, 0] + states[:, 1]
    np.testing.assert_allclose(pts[:, 0], 0.0, atol=1e-12)  # the shoulder is fixed
    elbow = 0.8 * np.c_[np.sin(t1), np.zeros(20), -np.cos(t1)]
    np.testing.assert_allclose(pts[:, 1], elbow, atol=1e-12)
    tip = elbow + 1.3 * np.c_[np.sin(t12), np.zeros(20), -np.cos(t12)]
    np.testing.assert_allclose(pts[:, 2], tip, atol=1e-12)
    np.testing.assert_allclose(pts[:, 2, 2], tip_height(states, params), atol=1e-12)


@pytest.mark.parametrize("params", REWRITTEN, ids=str)
def test_energy_and_mass_matrix_equal_mujocos(params):
    """Against MuJoCo's own energy (mjENBL_ENERGY) and dense inertia matrix."""
    rng = np.random.default_rng(7)
    model = acrobot.make_model(params)
    model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    data = mujoco.MjData(model)
    states = rng.uniform(-1, 1, (20, 4)) * [np.pi, np.pi, 4 * np.pi, 9 * np.pi]
    energies, matrices = [], []
    for s in states:
        data.qpos[:], data.qvel[:] = s[:2], s[2:]
        mujoco.mj_forward(model, data)
        energies.append(data.energy.sum())
        full = np.zeros((2, 2))
        mujoco.mj_fullM(model, data, full)
        matrices.append(full)
    np.testing.assert_allclose(
        acrobot.energy(states, params), energies, rtol=1e-10, atol=1e-10
    )
    np.testing.assert_allclose(
        acrobot.mass_matrix(states, params), matrices, rtol=1e-10, atol=1e-12
    )


@pytest.mark.parametrize("params", MASSES, ids=str)
def test_energy_changes_by_the_elbow_torques_work(params):
    """Along an accurate ODE solution of the book's equations, E(t) − E(0) is the
    work ∫ τ θ̇₂ dt (zero without torque)."""
    rng = np.random.default_rng(8)
    for tau in (0.0, 1.0, -1.0):
        s = rng.uniform(-1, 1, 4) * [np.pi, np.pi, 5, 8]
        sol = solve_ivp(
            lambda t, y, tau=tau: np.r_[y[2:4], book_accelerations(y[:4], tau, params),
                                        tau * y[3]],
            (0.0, 1.0), np.r_[s, 0.0], method="DOP853", rtol=1e-12, atol=1e-12,
        )  # fmt: skip
        y = sol.y[:, -1]
        change = acrobot.energy(y[:4], params) - acrobot.energy(s, params)
        assert change == pytest.approx(y[4], abs=1e-8)
        if tau != 0.0:
            assert abs(y[4]) > 1e-3  # the torque did work: the test can see it


@pytest.mark.parametrize("params", [REWRITTEN[0], *MASSES], ids=str)
def test_conserve_energy_leaves_the_simulators_steps_alone(params):
    """MuJoCo's steps already change the energy by the torque's work, also at
    elbow speeds that turn it by more than π in one step."""
    from tasks.agents import ACROBOT, SimulatorModel

    rng = np.random.default_rng(9)
    states = rng.uniform(-1, 1, (40, 4)) * [np.pi, np.pi, 4, 8]
    states[:10, 3] = rng.choice([-1, 1], 10) * rng.uniform(18, 22, 10)
    actions = rng.integers(0, 3, 40)
    true_next = SimulatorModel(ACROBOT, params).predict(states, actions)
    assert np.any(np.abs(true_next[:10, 3] + states[:10, 3]) * 0.1 > np.pi)
    out = acrobot.conserve_energy(states, acrobot.ACTIONS[actions], true_next, params)
    np.testing.assert_allclose(out, true_next, rtol=1e-4, atol=1e-6)


def test_conserve_energy_rescales_velocities_to_the_works_energy():
    """Against a root-find of E(θ', c q̇') = E(s) + τ Δθ₂ for the scale c."""
    from scipy.optimize import brentq

    params = REWRITTEN[1]
    rng = np.random.default_rng(10)
    states = rng.uniform(-1, 1, (30, 4)) * [np.pi, np.pi, 4, 8]
    torques = rng.choice(acrobot.ACTIONS, 30)
    predicted = states + rng.normal(0, [0.1, 0.1, 0.5, 0.5], (30, 4))
    out = acrobot.conserve_energy(states, torques, predicted, params)
    np.testing.assert_array_equal(out[:, :2], predicted[:, :2])  # angles kept
    for s, tau, p, o in zip(states, torques, predicted, out, strict=True):
        turn = p[1] - s[1]  # small steps: no wrap
        target = acrobot.energy(s, params) + tau * turn

        def gap(c, p=p, target=target):
            return acrobot.energy(np.r_[p[:2], c * p[2:]], params) - target

        if gap(0.0) >= 0:  # not reachable by scaling: at rest
            np.testing.assert_array_equal(o[2:], 0.0)
        else:
            c = brentq(gap, 0.0, 100.0, xtol=1e-14)
            np.testing.assert_allclose(o[2:], c * p[2:], rtol=1e-9, atol=1e-12)
    assert np.any(np.abs(out[:, 2:] - predicted[:, 2:]) > 1e-3)  # it did change


def test_conserve_energy_rejects_mismatched_shapes():
    s = np.zeros((3, 4))
    with pytest.raises(ValueError, match="torques"):
        acrobot.conserve_energy(s, np.zeros(2), s)
    with pytest.raises(ValueError, match="next_states"):
        acrobot.conserve_energy(s, np.zeros(3), np.zeros((2, 4)))
    # a batch of batches is not (N, 4), even when torques has its first length
    s = np.zeros((3, 2, 4))
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        acrobot.conserve_energy(s, np.zeros(3), s)


def test_conserve_energy_stops_a_prediction_above_the_steps_energy():
    """From hanging at rest, a prediction of the upright pose cannot be met by any
    speed: the velocities become 0 (and a prediction at rest stays at rest)."""
    s = np.zeros((2, 4))
    predicted = np.array([[np.pi, 0.0, 0.5, -0.5], [0.0, 0.0, 0.0, 0.0]])
    out = acrobot.conserve_energy(s, np.zeros(2), predicted)
    np.testing.assert_array_equal(out, [[np.pi, 0.0, 0.0, 0.0], [0.0] * 4])


def test_conserve_energy_keeps_its_precision_at_low_speeds():
    """The kinetic energy of a slow prediction is not lost to cancellation
    against the potential (~20 J)."""
    s = np.zeros((3, 4))
    predicted = np.zeros((3, 4))
    predicted[:, 2:] = np.array([1e-4, 1e-6, 1e-8])[:, None]
    tau = np.array([1.0, 1.0, 1.0])
    predicted[:, 1] = 0.01  # the elbow turned: the torque did 0.01 J of work
    out = acrobot.conserve_energy(s, tau, predicted)
    change = acrobot.energy(out) - acrobot.energy(s)
    np.testing.assert_allclose(change, 0.01, atol=1e-9)
    assert np.all(out[:, 2:] / predicted[:, 2:] > 1)  # sped up, not stopped
