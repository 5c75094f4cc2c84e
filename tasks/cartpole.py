"""Cart-pole balancing (Barto, Sutton & Anderson, 1983) on MuJoCo, one compiled
model per instance.

Symbols: `M` cart mass (kg); `m` pole mass (kg); `l` pole half-length (m), the pole a
uniform rod of length `2l` with moment of inertia `m (2l)² / 12` about its centre;
`g = 9.81` m/s² (the classic code, and Gym's, use 9.8: a 0.1% difference in the
dynamics, kept so that the published runs stand); `F ∈ ACTIONS = (-10, +10)` N
the force on the cart.

State `s = (x, θ, ẋ, θ̇)`, shape `(4,)` (`STATE_DIM`): `x` the cart position, `θ = 0`
upright and `θ > 0` leaning toward +x, the angle (`ANGLE_DIMS`) wrapped to (-π, π].

Task: every episode starts near upright at rest, each of the four state entries
uniform in [-0.05, 0.05] (drawn from the task's seed). Each step holds the chosen
force for 0.02 s. The pole fails when `|θ| > 12°` or `|x| > 2.4` m (`failed`); a
step gives reward 1 if the new state has not failed and 0 if it has, so the return
is the number of steps balanced. The episode ends (discount 0) at failure, or
(discount 1) after `max_steps` steps (default 300).

Integration: MuJoCo's RK4 with a 10 ms step, 2 steps per action (the classic code
uses one Euler step of 20 ms; RK4 integrates the same equations far more
accurately, see tests/test_cartpole.py). A light cart with a short pole swings
faster: at 10 ms, under random forces until failure, one action erred against
an eighth of the step by 6.5e-4 at the lightest corner of the bounds (cart 0.1
kg, pole 0.01 kg and 0.1 m) and 4.7e-5 at the next worst. Instances whose pole
the largest force accelerates by more than `POLE_ACCELERATION` = 32 rad/s²
(`pole_acceleration`) halve the step until it is within it (`sub_steps`: 10 ms /
2^k; k = 5 at the lightest corner), as the acrobot does; every experiment's
instances keep 10 ms. With that, one action errs below 4e-7 at every corner
(measured, 20 episodes each; the pole falls within a few steps, so, unlike the
acrobot's, these velocities stay bounded).
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

#: Cart forces (N) indexed by the discrete action `a`; the actuator's control range
#: is `[ACTIONS.min(), ACTIONS.max()]`.
ACTIONS = np.array([-10.0, 10.0])
#: State `(x, θ, ẋ, θ̇)`: its dimension and which entries are angles.
STATE_DIM = 4
#: The state's entries by name (data descriptions, tables).
STATE_NAMES = ("x", "theta", "x_dot", "theta_dot")
ANGLE_DIMS = (1,)
#: Seconds per action; MuJoCo RK4 steps of 10 ms per action.
CONTROL_TIMESTEP = 0.02
N_SUB_STEPS = 2
#: rad/s² of pole acceleration under the largest force above which the step is
#: halved (`sub_steps`; the nominal instance 14.6, every experiment's ≤ 29.6).
POLE_ACCELERATION = 32.0
DEFAULT_MAX_STEPS = 300
#: Failure thresholds: pole angle (rad) and cart position (m).
THETA_LIMIT = 12 * 2 * np.pi / 360
X_LIMIT = 2.4
#: Half-width of the uniform initial-state noise around upright at rest.
INITIAL_NOISE = 0.05


@dataclasses.dataclass(frozen=True)
class CartpoleParams:
    """Instance parameters of the cart-pole, validated on construction.

    ================  ====  =======  ============
    name              unit  nominal  valid range
    ================  ====  =======  ============
    cart_mass         kg    1.0      [0.1, 10.0]
    pole_mass         kg    0.1      [0.01, 2.0]
    pole_half_length  m     0.5      [0.1, 2.5]
    ================  ====  =======  ============

    The pole stays a uniform rod: centre of mass at `l`, inertia `m (2l)² / 12`.

    Raises:
        ValueError: naming the field and the bound, for a value that is not a
            finite number inside its range.
    """

    cart_mass: float = parameter(1.0, "kg", 0.1, 10.0)
    pole_mass: float = parameter(0.1, "kg", 0.01, 2.0)
    pole_half_length: float = parameter(0.5, "m", 0.1, 2.5)

    def __post_init__(self) -> None:
        validate_parameters(self)


def pole_acceleration(params: CartpoleParams | None = None) -> float:
    """The largest angular acceleration of the pole under the largest force, in
    rad/s²: `max|F| · max over θ of |(M⁻¹)₂₁|`, which is reached upright or
    hanging, `max|F| / (l (4M/3 + m/3))`. Sets the integration step
    (`sub_steps`)."""
    params = _check_params(params)
    M, m, l = params.cart_mass, params.pole_mass, params.pole_half_length
    return float(np.abs(ACTIONS).max()) / (l * (4 * M / 3 + m / 3))


def sub_steps(params: CartpoleParams | None = None) -> int:
    """MuJoCo steps per action on the instance: `N_SUB_STEPS · 2^k`, the least
    `k ≥ 0` with `pole_acceleration(params) / 2^k ≤ POLE_ACCELERATION` (2 steps
    of 10 ms for the nominal instance and every experiment's)."""
    a = pole_acceleration(params)
    k = max(0, math.ceil(math.log2(a / POLE_ACCELERATION)))
    return N_SUB_STEPS * 2**k


def make_model(params: CartpoleParams | None = None) -> mujoco.MjModel:
    """Compile `assets/mjcf/cartpole.xml` rewritten to `params` with `mujoco.MjSpec`.

    The cart gets mass `M`; the pole mass `m`, centre of mass at `l`, inertia
    `m (2l)² / 12` about it, a capsule of length `2l` and the tip site at `2l`.
    """
    params = _check_params(params)
    spec = load_spec("cartpole.xml")
    spec.body("cart").mass = params.cart_mass
    m, length = params.pole_mass, 2 * params.pole_half_length
    set_link(spec.body("pole"), spec.geom("pole"), m, length, m * length**2 / 12, 1)
    spec.site("tip").pos = [0.0, 0.0, length]
    # halving by a power of two is exact: instances at 10 ms keep it to the bit
    spec.option.timestep /= sub_steps(params) // N_SUB_STEPS  # the XML's 10 ms
    return spec.compile()


def link_points(states: Array, params: CartpoleParams | None = None) -> Array:
    """Cart centre, pole pivot and pole tip positions posed by MuJoCo's kinematics.

    Args:
        states: `(N, 4)` states `(x, θ, ẋ, θ̇)`; params: the instance.

    Returns:
        `(N, 3, 3)` world positions.
    """
    states = np.atleast_2d(np.asarray(states, dtype=float))
    if states.shape[-1] != 4:
        raise ValueError(f"states must have shape (N, 4), got {states.shape}")
    return pose_points(make_model(params), states, ("cart", "pole"), "tip")


class Physics(StatePhysics):
    """Cart-pole physics: `state()` is `(x, θ, ẋ, θ̇)` with the angle wrapped."""

    ANGLE_DIMS = ANGLE_DIMS


def failed(states: Array) -> Array:
    """Whether states are past the failure thresholds, `|θ| > 12°` or `|x| > 2.4`.

    Args:
        states: `(..., 4)` states `(x, θ, ẋ, θ̇)`, `θ` wrapped to (-π, π].

    Returns:
        Boolean array of shape `(...)`.
    """
    states = np.asarray(states, dtype=float)
    if states.ndim < 1 or states.shape[-1] != STATE_DIM:
        raise ValueError(
            f"states must have shape (..., {STATE_DIM}), got {states.shape}"
        )
    return (np.abs(states[..., 1]) > THETA_LIMIT) | (np.abs(states[..., 0]) > X_LIMIT)


class Balance(DiscreteActionTask):
    """Keep the pole up: reward 1 per step not failed, ends at failure."""

    def __init__(self, params: CartpoleParams, *, max_steps: int, seed: Any) -> None:
        super().__init__(
            ACTIONS, initial_noise=INITIAL_NOISE, max_steps=max_steps, seed=seed
        )
        self.params = params

    def is_terminal(self, state: Array) -> bool:
        return bool(failed(state))

    def get_reward(self, physics: Physics) -> float:
        return 0.0 if failed(self.state) else 1.0


def balance(
    params: CartpoleParams | None = None,
    *,
    seed: Any = None,
    max_steps: int = DEFAULT_MAX_STEPS,
) -> control.Environment:
    """The balancing environment on the instance `params` (nominal if None).

    `env.step(a)` takes an action index `a ∈ {0, 1}` (force `ACTIONS[a]`); the
    observation is `{"state": (x, θ, ẋ, θ̇)}` with the angle wrapped.

    Args:
        params: the instance; seed: anything `np.random.default_rng` accepts, for
        the initial states; max_steps: the step limit per episode.
    """
    params = _check_params(params)
    max_steps = check_max_steps(max_steps)
    task = Balance(params, max_steps=max_steps, seed=seed)  # checks seed first
    physics = Physics.from_mj_model(make_model(params))
    return control.Environment(
        physics, task, n_sub_steps=sub_steps(params), legacy_step=False
    )


def _check_params(params: CartpoleParams | None) -> CartpoleParams:
    return check_params(params, CartpoleParams)
