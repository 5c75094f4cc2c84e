"""Acrobot swing-up (Sutton & Barto, *Reinforcement Learning*, 1998, §11.3) on
MuJoCo, one compiled model per instance.

Symbols: `m₁, m₂` link masses (kg); `l₁, l₂` link lengths (m); `lc_i = l_i / 2` the
centres of mass; `I_i = k_i m_i l_i²` the moments of inertia about the centres of
mass (kg·m², the book's 1 at nominal; the shape `k_i` is 1 unless set, see
`AcrobotParams`); `g = 9.8` m/s²;
`τ ∈ ACTIONS = (-1, 0, +1)` N·m the elbow torque.

State `s = (θ₁, θ₂, θ̇₁, θ̇₂)`, shape `(4,)` (`STATE_DIM`): `θ₁ = 0` hangs straight
down, `θ₂` is the elbow angle relative to link 1, angles (`ANGLE_DIMS`) wrapped to
(-π, π]. The tip is at height `y = -l₁ cos θ₁ - l₂ cos(θ₁ + θ₂)` above the shoulder.

Task: every episode starts near hanging at rest, each of the four state entries
uniform in [-0.1, 0.1] (drawn from the task's seed). Each step holds the chosen
torque for 0.2 s and gives reward -1, so the return is minus the number of steps
taken. The episode ends (discount 0) when the tip is higher than the first link's
length above the shoulder, `y > l₁` (the book's goal line at nominal lengths; with
rewritten lengths it stays reachable since `l₁ + l₂ > l₁`), or (discount 1) after
`max_steps` steps (default 500).

Integration: MuJoCo's RK4 with a 10 ms step, 20 steps per action, on every
instance whose elbow the torque accelerates by at most `ELBOW_ACCELERATION` = 4
rad/s² per N·m (`elbow_acceleration`: 1.8 for the nominal instance, at most 2.5
for every experiment's). Against a tolerance-1e-13 ODE solve of the book
equations, one 0.2 s action errs below 1e-5 for |θ̇₁| ≤ 5, |θ̇₂| ≤ 8 rad/s
(tests/test_acrobot.py; measured on three samples of 150 random states and
actions of the experiment instances: at most 1.7e-6 to 4.0e-6, and at 20 ms
2.5e-5 to 6.4e-5).

A lighter, shorter or slimmer link swings faster: random torques drive it to
hundreds of rad/s, and at 10 ms one action of such an instance erred by up to
1e7. Its step is halved until the acceleration per halving is within the limit
(`sub_steps`: 10 ms / 2^k, 20 · 2^k steps per action; k = 7 at the slowest
corner of the bounds). Against a quarter or an eighth of that step, one
random-torque action then errs by at most 7.6e-5 over the 64 corners and 300
instances drawn log-uniformly inside the bounds (200–300 actions each, a new
start at the goal), but in longer runs such instances keep gaining speed (there
is no damping, and velocities are not clipped, see below), and so does the
error: 2.9e-4 at 350 rad/s on one instance, 1e-2 at the slowest corner after it
spun up to 1,300 rad/s in 200 actions that ignored the goal. Nothing bounds it
for any fixed step; tests/test_tasks_contract.py checks three fast instances to
1e-4 (at 10 ms they erred by 0.3 to 24).

Deviation from the book: velocities are not clipped (the book clips θ̇₁ to ±4π and
θ̇₂ to ±9π rad/s). Clipping is not part of the equations of motion and would make
the dynamics non-smooth. Random-torque episodes of the experiments' instances
stay below those limits; the fast instances above exceed them.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import mujoco
import numpy as np
from dm_control.rl import control

from tasks._common import (
    DiscreteActionTask,
    StatePhysics,
    check_max_steps,
    check_params,
    load_spec,
    parameter,
    pose_points,
    set_link,
    validate_parameters,
)

Array = np.ndarray

#: Elbow torques (N·m) indexed by the discrete action `a`; the actuator's control
#: range is `[ACTIONS.min(), ACTIONS.max()]`.
ACTIONS = np.array([-1.0, 0.0, 1.0])
#: State `(θ₁, θ₂, θ̇₁, θ̇₂)`: its dimension and which entries are angles.
STATE_DIM = 4
#: The state's entries by name (data descriptions, tables).
STATE_NAMES = ("theta1", "theta2", "theta1_dot", "theta2_dot")
ANGLE_DIMS = (0, 1)
#: Seconds per action; MuJoCo RK4 steps of 10 ms per action at most (`sub_steps`).
CONTROL_TIMESTEP = 0.2
N_SUB_STEPS = 20
#: rad/s² per N·m of elbow torque above which the step is halved (`sub_steps`).
ELBOW_ACCELERATION = 4.0
DEFAULT_MAX_STEPS = 500
GRAVITY = 9.8  # m/s², as assets/mjcf/acrobot.xml
#: Half-width of the uniform initial-state noise around hanging at rest.
INITIAL_NOISE = 0.1


@dataclasses.dataclass(frozen=True)
class AcrobotParams:
    """Instance parameters of the acrobot, validated on construction.

    ==============  ====  =======  ===========
    name            unit  nominal  valid range
    ==============  ====  =======  ===========
    link_mass_1     kg    1.0      [0.2, 5.0]
    link_mass_2     kg    1.0      [0.2, 5.0]
    link_length_1   m     1.0      [0.2, 5.0]
    link_length_2   m     1.0      [0.2, 5.0]
    link_shape_1    -     1.0      [0.7, 1.5]
    link_shape_2    -     1.0      [0.7, 1.5]
    ==============  ====  =======  ===========

    `-` marks a dimensionless parameter. The centre of mass is at mid-link.
    The moment of inertia about it is `I_i = k_i m_i l_i²` with
    `k_i = link_shape_i`, the link's shape (the nominal 1 gives the book's
    1 kg·m² at nominal mass and length). A fixed
    `k_i` keeps the shape when a mass or length changes (DESIGN §6); then the
    passive dynamics depend on the masses only through `m₁ / m₂`, and scaling
    both scales the torque's effect alone. `k_i = 1 / (m_i l_i²)` instead holds
    the book's `I_i = 1` kg·m² as the masses change, as the book's equations do
    when only `m₁, m₂` are rewritten (`book_inertia`); then each mass also
    changes how fast its link swings.

    Raises:
        ValueError: naming the field and the bound, for a value that is not a
            finite number inside its range.
    """

    link_mass_1: float = parameter(1.0, "kg", 0.2, 5.0)
    link_mass_2: float = parameter(1.0, "kg", 0.2, 5.0)
    link_length_1: float = parameter(1.0, "m", 0.2, 5.0)
    link_length_2: float = parameter(1.0, "m", 0.2, 5.0)
    link_shape_1: float = parameter(1.0, "-", 0.7, 1.5)
    link_shape_2: float = parameter(1.0, "-", 0.7, 1.5)

    def __post_init__(self) -> None:
        validate_parameters(self)

    @property
    def inertias(self) -> tuple[float, float]:
        """`(I₁, I₂)`, kg·m²: each link's moment of inertia about its centre of
        mass, `I_i = k_i m_i l_i²`."""
        return (
            self.link_shape_1 * self.link_mass_1 * self.link_length_1**2,
            self.link_shape_2 * self.link_mass_2 * self.link_length_2**2,
        )


def book_inertia(
    link_mass_1: float = 1.0,
    link_mass_2: float = 1.0,
    link_length_1: float = 1.0,
    link_length_2: float = 1.0,
) -> AcrobotParams:
    """The instance whose links keep the book's `I₁ = I₂ = 1` kg·m² whatever
    their masses and lengths (`k_i = 1 / (m_i l_i²)`, within its bounds).

    Raises:
        ValueError: as `AcrobotParams`, naming `link_shape_i` when `m_i l_i²`
            is outside [1 / 1.5, 1 / 0.7] = [0.67, 1.43] kg·m².
    """
    # the masses and lengths checked first (a zero one raised ZeroDivisionError)
    params = AcrobotParams(link_mass_1, link_mass_2, link_length_1, link_length_2)
    return dataclasses.replace(
        params,
        link_shape_1=1.0 / (params.link_mass_1 * params.link_length_1**2),
        link_shape_2=1.0 / (params.link_mass_2 * params.link_length_2**2),
    )


def book_inertia_range() -> tuple[float, float]:
    """`m l²` (kg·m²) over which a link can keep the book's 1 kg·m²: the link
    shape `1 / (m l²)` must lie within its bounds, so `[1 / 1.5, 1 / 0.7]`."""
    field = {f.name: f for f in dataclasses.fields(AcrobotParams)}["link_shape_1"]
    low, high = field.metadata["bounds"]
    return 1.0 / high, 1.0 / low


def with_book_inertia(params: AcrobotParams) -> AcrobotParams:
    """`params` with the link shapes that keep the book's `I₁ = I₂ = 1` kg·m²
    at its masses and lengths (`book_inertia`; raises as it does)."""
    return book_inertia(
        params.link_mass_1,
        params.link_mass_2,
        params.link_length_1,
        params.link_length_2,
    )


def make_model(params: AcrobotParams | None = None) -> mujoco.MjModel:
    """Compile `assets/mjcf/acrobot.xml` rewritten to `params` with `mujoco.MjSpec`.

    Link `i` gets mass `m_i`, centre of mass at `l_i / 2`, inertia `I_i` about it
    and a capsule of length `l_i`; the elbow sits at `l₁` and the tip site at
    `l₂` below it.
    """
    params = _check_params(params)
    spec = load_spec("acrobot.xml")
    m1, m2 = params.link_mass_1, params.link_mass_2
    l1, l2 = params.link_length_1, params.link_length_2
    i1, i2 = params.inertias
    set_link(spec.body("link_1"), spec.geom("link_1"), m1, l1, i1, down=-1)
    spec.body("link_2").pos = [0.0, 0.0, -l1]
    set_link(spec.body("link_2"), spec.geom("link_2"), m2, l2, i2, down=-1)
    spec.site("tip").pos = [0.0, 0.0, -l2]
    # halving by a power of two is exact: instances at 10 ms keep it to the bit
    spec.option.timestep /= sub_steps(params) // N_SUB_STEPS  # the XML's 10 ms
    return spec.compile()


def elbow_acceleration(params: AcrobotParams | None = None) -> float:
    """The largest angular acceleration of the elbow per N·m of elbow torque,
    rad/s² per N·m: `max over θ₂ of (M⁻¹)₂₂` (`mass_matrix`), taken on 721
    elbow angles, 0.5° apart. Sets the integration step (`sub_steps`)."""
    theta_2 = np.linspace(-np.pi, np.pi, 721)
    states = np.zeros((theta_2.size, STATE_DIM))
    states[:, 1] = theta_2
    m = mass_matrix(states, params)
    det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    return float(np.max(m[:, 0, 0] / det))


def sub_steps(params: AcrobotParams | None = None) -> int:
    """MuJoCo steps per action on the instance: `N_SUB_STEPS · 2^k`, the least
    `k ≥ 0` with `elbow_acceleration(params) · max|τ| / 2^k ≤ ELBOW_ACCELERATION`
    (20 steps of 10 ms for the nominal instance and every experiment's)."""
    a = elbow_acceleration(params) * float(np.abs(ACTIONS).max())
    k = max(0, math.ceil(math.log2(a / ELBOW_ACCELERATION)))
    return N_SUB_STEPS * 2**k


class Physics(StatePhysics):
    """Acrobot physics: `state()` is `(θ₁, θ₂, θ̇₁, θ̇₂)` with angles wrapped."""

    ANGLE_DIMS = ANGLE_DIMS


def tip_height(states: Array, params: AcrobotParams | None = None) -> Array:
    """Height of the tip above the shoulder for an array of states.

    `y = -l₁ cos θ₁ - l₂ cos(θ₁ + θ₂)`.

    Args:
        states: `(..., 4)` states `(θ₁, θ₂, θ̇₁, θ̇₂)`.
        params: the instance (nominal if None).

    Returns:
        `y`, shape `(...)`, in m.
    """
    params = _check_params(params)
    states = _check_states(states)
    theta_1, theta_2 = states[..., 0], states[..., 1]
    return -params.link_length_1 * np.cos(theta_1) - params.link_length_2 * np.cos(
        theta_1 + theta_2
    )


def mass_matrix(states: Array, params: AcrobotParams | None = None) -> Array:
    """The generalised inertia matrix `M(θ₂)` of the book's equations of motion.

    `M = [[d₁, d₂], [d₂, m₂ l_c2² + I₂]]` with `d₁ = m₁ l_c1² + m₂ (l₁² + l_c2² +
    2 l₁ l_c2 cos θ₂) + I₁ + I₂`, `d₂ = m₂ (l_c2² + l₁ l_c2 cos θ₂) + I₂`,
    `l_ci = l_i / 2` and `I_i` the links' inertias (Sutton & Barto 1998, §11.3).

    Args:
        states: `(..., 4)` states (only `θ₂` is used); params: the instance.

    Returns:
        `M`, shape `(..., 2, 2)`, in kg·m².
    """
    params = _check_params(params)
    states = _check_states(states)
    m1, m2 = params.link_mass_1, params.link_mass_2
    l1, l2 = params.link_length_1, params.link_length_2
    lc1, lc2 = l1 / 2, l2 / 2
    i1, i2 = params.inertias
    c2 = np.cos(states[..., 1])
    d1 = m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * c2) + i1 + i2
    d2 = m2 * (lc2**2 + l1 * lc2 * c2) + i2
    out = np.empty(states.shape[:-1] + (2, 2))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0] = d1, d2, d2
    out[..., 1, 1] = m2 * lc2**2 + i2
    return out


def energy(states: Array, params: AcrobotParams | None = None) -> Array:
    """Mechanical energy `½ q̇ᵀ M q̇ + V`, with `V` zero at the shoulder's height.

    `V = −g ((m₁ l_c1 + m₂ l₁) cos θ₁ + m₂ l_c2 cos(θ₁ + θ₂))`, `g = 9.8` m/s²: the
    hanging acrobot at rest has `V = −g (m₁ l_c1 + m₂ (l₁ + l_c2))`. Without
    torque the energy is conserved; the motor changes it by the work of the elbow
    torque.

    Args:
        states: `(..., 4)` states `(θ₁, θ₂, θ̇₁, θ̇₂)`; params: the instance.

    Returns:
        `E`, shape `(...)`, in J.
    """
    kinetic, potential = _energy_terms(states, params)
    return kinetic + potential


def _energy_terms(states: Array, params: AcrobotParams | None) -> tuple[Array, Array]:
    """`(½ q̇ᵀ M q̇, V)` of `energy`, each shape `(...)`."""
    params = _check_params(params)
    states = _check_states(states)
    m1, m2 = params.link_mass_1, params.link_mass_2
    l1, l2 = params.link_length_1, params.link_length_2
    t1, t2, q_dot = states[..., 0], states[..., 1], states[..., 2:]
    kinetic = 0.5 * np.einsum(
        "...i,...ij,...j->...", q_dot, mass_matrix(states, params), q_dot
    )
    potential = -GRAVITY * (
        (m1 * l1 / 2 + m2 * l1) * np.cos(t1) + m2 * l2 / 2 * np.cos(t1 + t2)
    )
    return kinetic, potential


def conserve_energy(
    states: Array,
    torques: Array,
    next_states: Array,
    params: AcrobotParams | None = None,
    dt: float = CONTROL_TIMESTEP,
) -> Array:
    """Rescale predicted velocities so that each step's energy change is the elbow
    torque's work.

    Without damping, holding torque `τ` for one step changes the energy by exactly
    `τ Δθ₂` (`E' = E(s) + τ Δθ₂`). A one-step model's velocity errors break this;
    errors of either sign add `½ εᵀ M ε` on average. Here the predicted velocities
    `q̇'` are scaled by `c ≥ 0` so that `½ c² q̇'ᵀ M(θ₂') q̇' + V(θ') = E'`: in the
    metric of `M` the closest point to `q̇'` with that energy. The angles are kept.
    Where `E' < V(θ')` the velocities become 0; where `q̇' = 0` they stay 0.

    `Δθ₂` is the predicted elbow change, wrapped, plus the multiple of 2π that
    brings it nearest to `dt (θ̇₂ + θ̇₂') / 2` (a step may turn the elbow by more
    than π).

    Args:
        states: `s`, shape `(N, 4)`; torques: `τ` in N·m, shape `(N,)`;
        next_states: predicted `s'`, shape `(N, 4)`; params: the instance whose
        energy is conserved (nominal if None); dt: seconds per step.

    Returns:
        `s'` with rescaled velocities, shape `(N, 4)`.
    """
    params = _check_params(params)
    s = _check_states(states)
    s2 = _check_states(next_states)
    tau = np.asarray(torques, dtype=float)
    if s.ndim != 2 or s2.shape != s.shape or tau.shape != s.shape[:1]:
        raise ValueError(
            "states, next_states, torques: expected shapes (N, 4), (N, 4), (N,), got "
            f"{s.shape}, {s2.shape}, {tau.shape}"
        )
    turn = np.remainder(s2[:, 1] - s[:, 1] + np.pi, 2 * np.pi) - np.pi
    mean_turn = dt * (s[:, 3] + s2[:, 3]) / 2
    turn += 2 * np.pi * np.round((mean_turn - turn) / (2 * np.pi))
    target = energy(s, params) + tau * turn
    # the two terms apart: E − V would cancel the kinetic energy's digits when slow
    kinetic, potential = _energy_terms(s2, params)
    moving = kinetic > 0
    scale = np.ones(len(s))
    scale[moving] = np.sqrt(
        np.maximum(target[moving] - potential[moving], 0.0) / kinetic[moving]
    )
    out = s2.copy()
    out[:, 2:] *= scale[:, None]
    return out


def goal_reached(states: Array, params: AcrobotParams | None = None) -> Array:
    """Whether the tip is higher than `l₁` above the shoulder, `y > l₁`.

    Args:
        states: `(..., 4)` states; params: the instance (nominal if None).

    Returns:
        Boolean array of shape `(...)`.
    """
    params = _check_params(params)
    return tip_height(states, params) > params.link_length_1


def link_points(states: Array, params: AcrobotParams | None = None) -> Array:
    """Shoulder, elbow and tip positions posed by MuJoCo's kinematics.

    Args:
        states: `(N, 4)` states (only the angles are used); params: the instance.

    Returns:
        `(N, 3, 3)`: per state the world positions of the shoulder, elbow and tip.
    """
    states = np.atleast_2d(_check_states(states))
    return pose_points(make_model(params), states, ("link_1", "link_2"), "tip")


class SwingUp(DiscreteActionTask):
    """Swing the tip above `l₁`: reward -1 per step, ends at the goal."""

    def __init__(self, params: AcrobotParams, *, max_steps: int, seed: Any) -> None:
        super().__init__(
            ACTIONS, initial_noise=INITIAL_NOISE, max_steps=max_steps, seed=seed
        )
        self.params = params

    def is_terminal(self, state: Array) -> bool:
        return bool(goal_reached(state, self.params))

    def get_reward(self, physics: Physics) -> float:
        return -1.0


def swingup(
    params: AcrobotParams | None = None,
    *,
    seed: Any = None,
    max_steps: int = DEFAULT_MAX_STEPS,
) -> control.Environment:
    """The swing-up environment on the instance `params` (nominal if None).

    `env.step(a)` takes an action index `a ∈ {0, 1, 2}` (torque `ACTIONS[a]`); the
    observation is `{"state": (θ₁, θ₂, θ̇₁, θ̇₂)}` with angles wrapped.

    Args:
        params: the instance; seed: anything `np.random.default_rng` accepts, for
        the initial states; max_steps: the step limit per episode.
    """
    params = _check_params(params)
    max_steps = check_max_steps(max_steps)
    task = SwingUp(params, max_steps=max_steps, seed=seed)  # checks seed first
    physics = Physics.from_mj_model(make_model(params))
    return control.Environment(
        physics, task, n_sub_steps=sub_steps(params), legacy_step=False
    )


def _check_params(params: AcrobotParams | None) -> AcrobotParams:
    return check_params(params, AcrobotParams)


def _check_states(states: Array) -> Array:
    states = np.asarray(states, dtype=float)
    if states.ndim < 1 or states.shape[-1] != STATE_DIM:
        raise ValueError(
            f"states must have shape (..., {STATE_DIM}), got {states.shape}"
        )
    return states
