"""Contract every task honours: spec-conforming finite observations with wrapped
angles, determinism given seed and actions, and parameters that change the
dynamics."""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import subprocess
import sys

import mujoco
import numpy as np
import pytest
from dm_env import specs

from hipmdp.data import wrap_angle
from tasks import acrobot, cartpole
from tasks._common import wrap_scalar_angle

DOMAINS = {
    "acrobot": (acrobot, acrobot.swingup, acrobot.AcrobotParams(1.3, 0.7, 1.0, 1.0)),
    "cartpole": (cartpole, cartpole.balance, cartpole.CartpoleParams(1.0, 0.3, 0.8)),
}
#: What the modules' docstrings state: the half-width of the start states' box
#: and the default step limit per episode.
DOCUMENTED = {"acrobot": (0.1, 500), "cartpole": (0.05, 300)}


def _registered() -> list[str]:
    from tasks.collect import DOMAINS as registered

    return sorted(registered)


def test_every_table_of_domains_names_the_same_ones():
    """A domain is registered in several tables (README, Development); one left
    out fails only for the policy or command that reads it. And this file's
    DOMAINS must name every one, so that the contract is checked for it."""
    from benchmarks import simulation
    from tasks import agents, generate, rollout

    tables = {
        "tasks.agents.DOMAINS": agents.DOMAINS,
        "tasks.rollout.MODULES": rollout.MODULES,
        "tasks.generate.DEFAULT_VARY": generate.DEFAULT_VARY,
        "benchmarks.simulation.DOMAINS": simulation.DOMAINS,
        "this file's DOMAINS": DOMAINS,
        "this file's DOCUMENTED": DOCUMENTED,
    }
    for name, table in tables.items():
        assert sorted(table) == _registered(), name


@pytest.mark.parametrize("name", _registered())
def test_the_step_is_the_same_in_every_table(name):
    """One action is ``N_SUB_STEPS`` MuJoCo steps of the model's timestep:
    the module's ``CONTROL_TIMESTEP``, the environment's control step and the
    ``dt`` that transitions record (and unwrap angle changes with) must agree,
    and a nominal instance takes ``N_SUB_STEPS`` (``sub_steps``)."""
    from tasks.collect import DOMAINS as registered
    from tasks.rollout import MODULES

    module, factory, _ = DOMAINS[name]
    assert MODULES[name] is module
    step = module.make_model().opt.timestep * module.N_SUB_STEPS
    assert step == pytest.approx(module.CONTROL_TIMESTEP, rel=1e-12)
    assert registered[name].dt == module.CONTROL_TIMESTEP
    assert factory(seed=0).control_timestep() == pytest.approx(step, rel=1e-12)
    assert module.sub_steps() == module.N_SUB_STEPS


def run(factory, params, seed, actions):
    """Observations of one episode (reset, then the actions until it ends)."""
    env = factory(params, seed=seed)
    observations = [env.reset().observation["state"]]
    for a in actions:
        step = env.step(a)
        observations.append(step.observation["state"])
        if step.last():
            break
    return np.array(observations)


@pytest.mark.parametrize("name", DOMAINS)
def test_observations_conform_to_the_spec_and_wrap_angles(name):
    module, factory, params = DOMAINS[name]
    env = factory(params, seed=0, max_steps=200)
    spec = env.observation_spec()
    assert list(spec) == ["state"]
    assert spec["state"].shape == (module.STATE_DIM,)
    action_spec = env.action_spec()
    assert isinstance(action_spec, specs.DiscreteArray)
    assert action_spec.num_values == len(module.ACTIONS)
    rng = np.random.default_rng(0)
    step = env.reset()
    # Spinning the first joint fast makes an unwrapped angle leave (-π, π].
    env.physics.data.qvel[module.ANGLE_DIMS[0]] = 20.0
    raw_angles = []
    while True:
        spec["state"].validate(step.observation["state"])
        state = step.observation["state"]
        assert np.all(np.isfinite(state))
        angles = state[list(module.ANGLE_DIMS)]
        assert np.all((angles > -np.pi) & (angles <= np.pi))
        np.testing.assert_allclose(
            np.cos(angles), np.cos(env.physics.data.qpos[list(module.ANGLE_DIMS)])
        )
        raw_angles.append(env.physics.data.qpos[list(module.ANGLE_DIMS)].copy())
        if step.last():
            break
        step = env.step(action_spec.generate_value() + rng.integers(2))
    if name == "acrobot":  # the test exercised wrapping (cart-pole fails at 12°)
        assert np.abs(raw_angles).max() > np.pi
    # every angle is wrapped, each on its own (ANGLE_DIMS = (0,) would leave the
    # acrobot's elbow unwrapped): the angles are the model's hinge joints, and
    # each, set past ±π, is observed wrapped
    model = env.physics.model
    hinges = [int(model.jnt_qposadr[j]) for j in range(model.njnt)
              if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]  # fmt: skip
    assert tuple(hinges) == module.ANGLE_DIMS
    for j, q in zip(module.ANGLE_DIMS, (4.0, -4.5), strict=False):
        env.physics.data.qpos[:] = 0.0
        env.physics.data.qpos[j] = q
        state = env.task.get_observation(env.physics)["state"]
        assert state[j] == pytest.approx(wrap_angle(q))


@pytest.mark.parametrize("name", DOMAINS)
def test_same_seed_and_actions_give_the_same_trajectory(name):
    _, factory, params = DOMAINS[name]
    actions = np.random.default_rng(1).integers(0, 2, 40)
    first = run(factory, params, 7, actions)
    np.testing.assert_array_equal(first, run(factory, params, 7, actions))
    assert not np.array_equal(first[0], run(factory, params, 8, actions)[0])


@pytest.mark.parametrize("name", DOMAINS)
def test_start_states_are_uniform_on_the_noise_box(name):
    """s₀ ~ U[−c, c] in every coordinate (qpos and qvel): over 400 resets each
    coordinate's mean, variance (c²/3) and both halves of the box agree with it
    to within 4 standard errors."""
    module, factory, _ = DOMAINS[name]
    env, c, n = factory(None, seed=11), module.INITIAL_NOISE, 400
    s0 = np.array([env.reset().observation["state"] for _ in range(n)])
    assert np.all(np.abs(s0) <= c)
    assert np.all(np.abs(s0.mean(axis=0)) < 4 * c / np.sqrt(3 * n))
    # Var of a U[−c, c] sample variance: (μ₄ − σ⁴)/n = (c⁴/5 − c⁴/9)/n
    se_var = np.sqrt((c**4 / 5 - c**4 / 9) / n)
    assert np.all(np.abs(s0.var(axis=0) - c**2 / 3) < 4 * se_var)
    assert np.all(np.abs(np.mean(s0 < 0, axis=0) - 0.5) < 4 * np.sqrt(0.25 / n))
    # and independently: a sample correlation of independent coordinates has
    # standard error about 1 / √n (drawing qvel equal to qpos would give 1)
    correlation = np.corrcoef(s0, rowvar=False)[np.triu_indices(s0.shape[1], 1)]
    assert np.all(np.abs(correlation) < 4 / np.sqrt(n))


@pytest.mark.parametrize("name", DOMAINS)
def test_noise_box_and_step_limit_are_the_documented_ones(name):
    module, factory, _ = DOMAINS[name]
    noise, max_steps = DOCUMENTED[name]
    assert module.INITIAL_NOISE == noise
    assert factory(None).task.max_steps == max_steps


@pytest.mark.parametrize(
    "name, spec",
    [(n, f) for n in DOMAINS for f in dataclasses.fields(type(DOMAINS[n][2]))],
    ids=lambda x: x if isinstance(x, str) else x.name,
)
def test_each_parameter_alone_changes_the_dynamics(name, spec):
    """Every parameter, moved alone from its nominal value halfway to its upper
    bound, changes the motion under the same actions from the same start (the
    test below moves them all at once, so a parameter that make_model ignored
    passed it). 10 actions; 1e-6 against the 0.07 to 1.2 measured."""
    _, factory, params = DOMAINS[name]
    moved = dataclasses.replace(
        type(params)(), **{spec.name: (spec.default + spec.metadata["bounds"][1]) / 2}
    )
    actions = np.random.default_rng(2).integers(0, 2, 10)
    nominal, changed = run(factory, None, 3, actions), run(factory, moved, 3, actions)
    n = min(len(nominal), len(changed))
    assert np.abs(nominal[1:n] - changed[1:n]).max() > 1e-6, moved


@pytest.mark.parametrize("name", DOMAINS)
def test_different_parameters_give_different_dynamics(name):
    _, factory, params = DOMAINS[name]
    actions = np.random.default_rng(2).integers(0, 2, 10)
    nominal = run(factory, None, 3, actions)
    rewritten = run(factory, params, 3, actions)
    np.testing.assert_array_equal(nominal[0], rewritten[0])  # same initial state
    n = min(len(nominal), len(rewritten))
    assert np.abs(nominal[1:n] - rewritten[1:n]).max() > 1e-3


@pytest.mark.parametrize("name", DOMAINS)
def test_factory_rejects_bad_arguments(name):
    module, factory, _ = DOMAINS[name]
    with pytest.raises(ValueError, match="params must be"):
        factory({"pole_mass": 1.0})
    for max_steps in (0, True, 2.5):  # a bool is not a count; 2.5 steps is not one
        with pytest.raises(ValueError, match="max_steps must be a positive int"):
            factory(None, max_steps=max_steps)
    for seed in (-1, 2.5, "0"):  # numpy's own message named no field
        with pytest.raises(ValueError, match=rf"^seed: expected .*, got {seed!r} \("):
            factory(None, seed=seed)


@pytest.mark.parametrize("name", DOMAINS)
def test_each_episode_gets_the_full_step_limit(name):
    """The step count restarts at every reset: a second episode is truncated
    after `max_steps` steps too, not at its first."""
    _, factory, _ = DOMAINS[name]
    env = factory(None, seed=0, max_steps=3)
    for _ in range(2):
        env.reset()
        steps = [env.step(0) for _ in range(3)]  # too few to reach goal or failure
        assert [s.last() for s in steps] == [False, False, True]
        assert steps[-1].discount == 1.0


@pytest.mark.parametrize("name", DOMAINS)
def test_parameters_are_stored_as_floats_and_refuse_bools(name):
    """Whatever real type a value comes as (an int, a NumPy integer), the field
    holds a Python float, so instances compare, hash and serialise to JSON as
    the numbers they are; a bool is not a number here (True would pass as 1)."""
    params_type = type(DOMAINS[name][2])
    first = dataclasses.fields(params_type)[0].name  # its bounds contain 1
    params = params_type(**{first: np.int64(1)})
    assert type(getattr(params, first)) is float
    assert json.loads(json.dumps(dataclasses.asdict(params)))[first] == 1.0
    assert params == params_type(**{first: 1.0})
    assert hash(params) == hash(params_type(**{first: 1.0}))
    with pytest.raises(ValueError, match=rf"\.{first} .*not a real number"):
        params_type(**{first: True})


@pytest.mark.parametrize("name", DOMAINS)
def test_link_points_refuse_states_of_another_width(name):
    module = DOMAINS[name][0]
    for width in (module.STATE_DIM - 1, module.STATE_DIM + 1):
        with pytest.raises(ValueError, match="states must have shape"):
            module.link_points(np.zeros((3, width)))


def test_tasks_are_headless():
    """Importing and stepping both tasks prints no GLFW/display warning, with no
    display and no MUJOCO_GL set (plain dm_control warns in this setting)."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY")}
    code = (
        "from tasks import acrobot, cartpole\n"
        "for f in (acrobot.swingup, cartpole.balance):\n"
        "    env = f(seed=0); env.reset(); env.step(0)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    assert "GLFW" not in result.stderr + result.stdout
    assert "display" not in (result.stderr + result.stdout).lower()


def test_scalar_wrap_agrees_with_the_array_wrap():
    x = np.r_[
        np.pi,
        -np.pi,
        3 * np.pi,
        -3 * np.pi,
        0.0,
        1e-300,
        -1e-300,
        1e6,
        -1e6,
        np.random.default_rng(0).uniform(-50, 50, 200),
    ]
    wrapped = np.array([wrap_scalar_angle(v) for v in x])
    assert np.all((wrapped > -np.pi) & (wrapped <= np.pi))
    np.testing.assert_allclose(wrapped, wrap_angle(x), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(x), atol=1e-9)


def corners(params_type):
    """Every corner of a parameter dataclass's documented bounds."""
    fields = dataclasses.fields(params_type)
    for values in itertools.product(*(f.metadata["bounds"] for f in fields)):
        yield params_type(*values)


@pytest.mark.parametrize("name", DOMAINS)
def test_energy_is_conserved_at_every_corner_of_the_bounds(name):
    """Unforced and undamped, MuJoCo's total energy must stay constant: over 10 s
    from a large swing it drifts by less than 0.1% of its scale everywhere inside
    the documented bounds, each instance at its own step (the acrobot's worst
    corner drifted 3.5e-4 at a fixed 10 ms, 1.5e-6 at its own). Unforced swings
    stay slow; the test below checks the step under random torques."""
    module, _, _ = DOMAINS[name]
    n_actions = round(10.0 / module.CONTROL_TIMESTEP)
    s = np.array([2.5, 1.0, 0.0, 0.0] if name == "acrobot" else [0.0, 2.5, 0.0, 0.0])
    for params in corners(type(DOMAINS[name][2])):
        model = module.make_model(params)
        model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
        data = mujoco.MjData(model)
        data.qpos[:], data.qvel[:] = s[: model.nq], s[model.nq :]
        mujoco.mj_forward(model, data)
        e0, scale = data.energy.sum(), np.abs(data.energy).max()
        energies = []
        n_sub = round(module.CONTROL_TIMESTEP / model.opt.timestep)  # the instance's
        for _ in range(n_actions):
            mujoco.mj_step(model, data, n_sub)
            mujoco.mj_forward(model, data)
            energies.append(data.energy.sum())
        assert np.abs(np.array(energies) - e0).max() < 1e-3 * scale, params


#: Acrobots whose elbow the torque accelerates 14 to 142 times the nominal
#: instance's (`elbow_acceleration`), with the random-torque actions each is run for:
#: the corners of the bounds spin up within 40, the third needs longer. At 10 ms per
#: step one action erred by 24 and 1.8 (the corners, 40 actions) and 0.30.
FAST_ACROBOTS = [
    (acrobot.AcrobotParams(0.2, 0.2, 5.0, 0.2, 0.7, 0.7), 40),
    (acrobot.AcrobotParams(0.2, 0.2, 0.2, 0.2, 1.5, 0.7), 40),
    (acrobot.AcrobotParams(0.5, 0.3, 0.6, 0.4), 300),
]


def one_action(module, params):
    """``act(s, u)``: the state after one action of control ``u`` from state
    ``s``, at the instance's own step (``module.sub_steps``) and at a quarter of
    it. Fourth order: the quarter step's own error is 256 times smaller."""
    n_sub = module.sub_steps(params)
    model, fine = module.make_model(params), module.make_model(params)
    assert model.opt.timestep * n_sub == pytest.approx(module.CONTROL_TIMESTEP)
    fine.opt.timestep = model.opt.timestep / 4
    data, fine_data = mujoco.MjData(model), mujoco.MjData(fine)

    def act(s, u):
        for d in (data, fine_data):
            d.qpos[:], d.qvel[:], d.ctrl[0] = s[:2], s[2:], u
        mujoco.mj_step(model, data, n_sub)
        mujoco.mj_step(fine, fine_data, 4 * n_sub)
        return np.r_[data.qpos, data.qvel], np.r_[fine_data.qpos, fine_data.qvel]

    return act


@pytest.mark.parametrize(
    "params, n_actions", [(acrobot.AcrobotParams(), 300), *FAST_ACROBOTS]
)
def test_one_action_is_accurate_under_random_torques(params, n_actions):
    """Along random-torque actions from near hanging (a new start after the
    goal, as the task's episodes end there), each action at the instance's own
    step agrees with the same action at a quarter of that step to 1e-4
    (measured: at most 2e-5)."""
    act = one_action(acrobot, params)
    rng = np.random.default_rng(0)
    s = rng.uniform(-0.1, 0.1, 4)
    worst = 0.0
    for u in acrobot.ACTIONS[rng.integers(3, size=n_actions)]:
        coarse, s = act(s, u)
        worst = max(worst, np.abs(coarse - s).max())
        if acrobot.goal_reached(s, params):
            s = rng.uniform(-0.1, 0.1, 4)
    assert worst < 1e-4, (params, worst)


def test_a_light_cart_pole_is_accurate_under_random_forces():
    """The lightest corner of the cart-pole's bounds (cart 0.1 kg, pole 0.01 kg
    and 0.1 m): 20 random-force episodes until the pole fails, each action at
    the instance's own step against a quarter of it, to 1e-5 (at 10 ms: 6.5e-4;
    measured now: below 1e-9)."""
    params = cartpole.CartpoleParams(0.1, 0.01, 0.1)
    assert cartpole.sub_steps(params) == 2 * 2**5
    act = one_action(cartpole, params)
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(20):
        s = rng.uniform(-0.05, 0.05, 4)
        while not cartpole.failed(s):
            coarse, s = act(s, rng.choice(cartpole.ACTIONS))
            worst = max(worst, np.abs(coarse - s).max())
    assert worst < 1e-5, worst


def test_every_experiment_instance_keeps_the_10_ms_step():
    """The finer step is only for fast instances: the nominal instances and
    every preset's and generate's default ones keep exactly 10 ms (20 steps per
    acrobot action, 2 per cart-pole one), so their results stand."""
    from tasks import acrobot_swingup
    from tasks.generate import DEFAULT_VARY

    instances = [acrobot.AcrobotParams()]
    for config in acrobot_swingup.PRESETS.values():
        for book in (False, True):
            c = dataclasses.replace(config, book_inertia=book)
            instances += [c.params(*m) for m in c.train_masses + c.test_masses]
    vary = DEFAULT_VARY["acrobot"]
    instances += [
        acrobot.AcrobotParams(m1, m2)
        for m1 in vary["link_mass_1"]
        for m2 in vary["link_mass_2"]
    ]
    for params in instances:
        assert acrobot.sub_steps(params) == acrobot.N_SUB_STEPS, params
        assert acrobot.make_model(params).opt.timestep == 0.01, params
    from tasks import cartpole_prediction

    poles = [cartpole.CartpoleParams()]
    for config in cartpole_prediction.PRESETS.values():
        settings = config.train_settings + config.test_settings
        poles += [cartpole.CartpoleParams(1.0, m, l) for m, l in settings]
    vary = DEFAULT_VARY["cartpole"]
    poles += [
        cartpole.CartpoleParams(1.0, m, l)
        for m in vary["pole_mass"]
        for l in vary["pole_half_length"]
    ]
    for params in poles:
        assert cartpole.sub_steps(params) == cartpole.N_SUB_STEPS, params
        assert cartpole.make_model(params).opt.timestep == 0.01, params
    env = acrobot.swingup(FAST_ACROBOTS[0][0], seed=0)
    assert env.control_timestep() == pytest.approx(acrobot.CONTROL_TIMESTEP)
    assert acrobot.sub_steps(FAST_ACROBOTS[0][0]) == 20 * 2**6
    # the slowest corner: every parameter at its lower bound but the shapes'
    assert acrobot.sub_steps(acrobot.AcrobotParams(*[0.2] * 4, 0.7, 0.7)) == 20 * 2**7


@pytest.mark.parametrize("name", DOMAINS)
def test_docstring_table_states_each_parameter_unit_nominal_and_bounds(name):
    params_type = type(DOMAINS[name][2])
    rows = {
        line.split()[0]: line.split()
        for line in params_type.__doc__.splitlines()
        if line.strip() and line.split()[0] in params_type.__dataclass_fields__
    }
    nominal = params_type()
    for field in dataclasses.fields(params_type):
        low, high = field.metadata["bounds"]
        _, unit, value, *bounds = rows[field.name]
        assert unit == field.metadata["unit"]
        assert float(value) == getattr(nominal, field.name)
        assert " ".join(bounds) == f"[{low}, {high}]"


def test_a_parameter_declared_without_its_bounds_is_named():
    """A new domain's parameter dataclass field declared without
    ``parameter(nominal, unit, low, high)`` was a bare KeyError: 'bounds'."""
    from tasks._common import parameter, validate_parameters

    @dataclasses.dataclass(frozen=True)
    class Params:
        mass: float = parameter(1.0, "kg", 0.1, 10.0)
        length: float = 1.0

    with pytest.raises(TypeError, match=r"^Params\.length: declare it with "):
        validate_parameters(Params())
