"""Pieces shared by the domains: instance parameters, model loading, the state
vector and the discrete-action dm_control task.

Conventions (DESIGN.md §1): the state is `s = (qpos, qvel)`, shape `(D,)` with
`D = 2 · nq`, angle entries wrapped to (-π, π]; an action is an index `a` into the
domain's table `ACTIONS` of controls, shape `(A,)`.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import importlib.resources
import math
import operator
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np
from dm_control import mujoco as dm_mujoco
from dm_control.mujoco import wrapper
from dm_control.suite import base
from dm_env import specs

Array = np.ndarray

#: Name of the one observation every task returns: the state `(qpos, qvel)`.
STATE_OBSERVATION = "state"


def parameter(nominal: float, unit: str, low: float, high: float) -> Any:
    """A dataclass field for an instance parameter with its unit and bounds.

    The bounds are closed, `low ≤ value ≤ high`, with `low > 0`.
    """
    return dataclasses.field(
        default=nominal, metadata={"unit": unit, "bounds": (low, high)}
    )


_REAL = (int, float, np.integer, np.floating)


@functools.cache
def _field_bounds(kind: type) -> tuple[tuple[str, float, float, str, str], ...]:
    """Per field of the parameter dataclass `kind`: its name, bounds, unit (with a
    leading space, or empty) and the start of its error message."""
    out = []
    for field in dataclasses.fields(kind):
        if "bounds" not in field.metadata or "unit" not in field.metadata:
            raise TypeError(
                f"{kind.__name__}.{field.name}: declare it with "
                "tasks._common.parameter(nominal, unit, low, high), which gives "
                "its unit and bounds"
            )
        low, high = field.metadata["bounds"]
        # "-" marks a dimensionless parameter: no unit in the message.
        unit = "" if field.metadata["unit"] == "-" else " " + field.metadata["unit"]
        where = f"{kind.__name__}.{field.name} must be in [{low}, {high}]{unit}"
        out.append((field.name, low, high, unit, where))
    return tuple(out)


def validate_parameters(params: Any) -> None:
    """Check every field of a parameter dataclass; store it as a Python float.

    Raises:
        ValueError: naming the field and its bound if a value is not a finite real
            number inside its documented bounds.
    """
    for name, low, high, unit, where in _field_bounds(type(params)):
        value = getattr(params, name)
        if isinstance(value, bool) or not isinstance(value, _REAL):
            raise ValueError(f"{where}, got {value!r} (not a real number)")
        if not math.isfinite(value):
            raise ValueError(f"{where}, got {value!r} (not finite)")
        if not low <= value <= high:
            bound = "lower bound" if value < low else "upper bound"
            raise ValueError(
                f"{where}, got {value!r} (outside the {bound} "
                f"{low if value < low else high}{unit})"
            )
        # Frozen dataclass: store plain floats so equality and hashing behave.
        object.__setattr__(params, name, float(value))


def check_params(params: Any, params_type: type) -> Any:
    """`params_type()` (nominal) for None, `params` if of that type, else ValueError."""
    if params is None:
        return params_type()
    if not isinstance(params, params_type):
        raise ValueError(
            f"params must be {params_type.__name__} or None, got {params!r}"
        )
    return params


def check_max_steps(max_steps: Any) -> int:
    """`max_steps` if it is a positive int, else ValueError."""
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
    return max_steps


def parameter_names(params_type: type) -> tuple[str, ...]:
    """Field names of a parameter dataclass, in declaration order."""
    return tuple(field.name for field in dataclasses.fields(params_type))


def parameter_values(params: Any) -> Array:
    """Field values of a parameter dataclass as an array, shape `(p,)`."""
    return parameter_matrix([params])[0]


def parameter_matrix(instances: Sequence[Any]) -> Array:
    """Field values of parameter dataclasses of one type, shape `(n, p)`, rows in
    order: `dataclasses.astuple` per row, without its deep copies (about 10
    times faster: 0.4 s for a million acrobot instances against 4.7 s, with the
    experiments' runs beside it)."""
    if not instances:
        raise ValueError("instances: expected at least one parameter dataclass")
    kind = type(instances[0])
    for i, p in enumerate(instances):
        if type(p) is not kind:
            raise ValueError(
                f"instances: expected only {kind.__name__}, got "
                f"{type(p).__name__} at index {i}"
            )
    names = parameter_names(kind)
    get = operator.attrgetter(*names)  # a tuple per row, or a value if p = 1
    rows = [get(p) for p in instances]
    return np.array(rows, dtype=float).reshape(len(instances), len(names))


def load_spec(filename: str) -> mujoco.MjSpec:
    """Parse a nominal model from the installed package data `tasks.mjcf`."""
    path = importlib.resources.files("tasks.mjcf") / filename
    return mujoco.MjSpec.from_string(path.read_text())


def set_link(
    body: Any, geom: Any, mass: float, length: float, inertia: float, down: float
) -> None:
    """Rewrite one link of a chain with `mujoco.MjSpec`.

    The link runs from its joint (the body origin) along `(0, 0, down · length)`:
    centre of mass at mid-link, `diaginertia = (I, I, I)` with `I = inertia` (only
    the component about the hinge axis enters the planar dynamics), and the drawn
    capsule follows the length.

    Args:
        body: the link's `MjsBody`; geom: its `MjsGeom`; mass in kg; length in m;
        inertia in kg·m² about the centre of mass; down: -1 hangs, +1 stands.
    """
    body.mass = mass
    body.ipos = [0.0, 0.0, down * length / 2]
    body.inertia = [inertia, inertia, inertia]
    geom.fromto = [0.0, 0.0, 0.0, 0.0, 0.0, down * length]


class StatePhysics(dm_mujoco.Physics):
    """A Physics with the project's state vector; subclasses set `ANGLE_DIMS`."""

    ANGLE_DIMS: tuple[int, ...] = ()

    @classmethod
    def from_mj_model(cls, model: mujoco.MjModel) -> StatePhysics:
        """Wrap a compiled `mujoco.MjModel` (e.g. from `MjSpec.compile`)."""
        return cls.from_model(wrapper.MjModel(model))

    def state(self) -> Array:
        """`s = (qpos, qvel)` with angles wrapped to (-π, π], shape `(D,)`."""
        nq = self.model.nq
        s = np.empty(2 * nq)
        s[:nq] = self.data.qpos
        s[nq:] = self.data.qvel
        for i in self.ANGLE_DIMS:
            s[i] = wrap_scalar_angle(s[i])
        return s


def wrap_scalar_angle(x: float) -> float:
    """`x` wrapped to (-π, π]: `x - 2π n` with `n` the nearest integer to `x / 2π`,
    computed exactly by `math.remainder` (what `hipmdp.data.wrap_angle` does for
    arrays, to within an ulp, at a fraction of its cost on one number)."""
    r = math.remainder(x, 2 * math.pi)
    return math.pi if r == -math.pi else r


class DiscreteActionTask(base.Task):
    """A task whose action is an index into a table of controls.

    `step(a)` takes `a` as a Python or NumPy integer (or a 0-d integer array) in
    `[0, A)` and applies control `ACTIONS[a]` for the whole control step. The action
    spec is a `DiscreteArray(num_values=A)`. The observation is one array,
    `{"state": s}`. Episodes start from `s₀ ~ U[-c, c]^D` (`c = initial_noise`,
    drawn from `np.random.default_rng(seed)`) and end when `is_terminal(s)`
    (discount 0) or after `max_steps` steps (discount 1).

    Subclasses define `is_terminal(state)` and `get_reward(physics)`; `self.state`
    is the state after the last step.
    """

    def __init__(
        self, actions: Array, *, initial_noise: float, max_steps: int, seed: Any
    ) -> None:
        super().__init__(random=None)  # dm_control's RandomState is not used.
        self._actions = np.asarray(actions, dtype=float)
        self.initial_noise = initial_noise
        self.max_steps = max_steps
        try:
            self.rng = np.random.default_rng(seed)
        except (TypeError, ValueError) as err:  # numpy's message names no field
            raise ValueError(
                "seed: expected what np.random.default_rng takes (None, an int "
                f">= 0, a SeedSequence or a Generator), got {seed!r} ({err})"
            ) from None
        self.steps = 0
        self.state: Array | None = None

    def action_spec(self, physics: dm_mujoco.Physics) -> specs.DiscreteArray:
        return specs.DiscreteArray(len(self._actions), dtype=np.int64, name="action")

    def initialize_episode(self, physics: StatePhysics) -> None:
        c, nq = self.initial_noise, physics.model.nq
        s0 = self.rng.uniform(-c, c, size=2 * nq)
        physics.data.qpos[:] = s0[:nq]
        physics.data.qvel[:] = s0[nq:]
        self.steps = 0
        self.state = None

    def before_step(self, action: Any, physics: dm_mujoco.Physics) -> None:
        n = len(self._actions)
        try:
            if isinstance(action, bool | np.bool_):
                raise TypeError
            index = operator.index(action)  # ints and 0-d integer arrays only
        except TypeError:
            raise ValueError(
                f"action must be an integer index in [0, {n}), got {action!r}"
            ) from None
        if not 0 <= index < n:
            raise ValueError(
                f"action must be an integer index in [0, {n}), got {index}"
            )
        physics.data.ctrl[0] = self._actions[index]

    def after_step(self, physics: StatePhysics) -> None:
        self.steps += 1
        self.state = physics.state()

    def is_terminal(self, state: Array) -> bool:
        raise NotImplementedError

    def get_termination(self, physics: StatePhysics) -> float | None:
        if self.is_terminal(self.state):
            return 0.0
        if self.steps >= self.max_steps:
            return 1.0
        return None

    def get_observation(self, physics: StatePhysics) -> collections.OrderedDict:
        return collections.OrderedDict([(STATE_OBSERVATION, physics.state())])


def pose_points(
    model: mujoco.MjModel, states: Array, bodies: tuple[str, ...], site: str
) -> Array:
    """World positions of `bodies` (their frames) and `site`, posed from states.

    Args:
        model: the compiled instance; states: `(N, 2 nq)` states `(qpos, qvel)`
        (only `qpos` is used); bodies, site: names in the model.

    Returns:
        `(N, len(bodies) + 1, 3)`, from `mj_kinematics` for each state.
    """
    data = mujoco.MjData(model)
    ids = [model.body(name).id for name in bodies]
    tip = model.site(site).id
    out = np.empty((states.shape[0], len(ids) + 1, 3))
    for n, state in enumerate(states):
        data.qpos[:] = state[: model.nq]
        mujoco.mj_kinematics(model, data)
        out[n, :-1] = data.xpos[ids]
        out[n, -1] = data.site_xpos[tip]
    return out
