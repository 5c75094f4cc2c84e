"""Open-loop random action sequences on many instances at once with `mujoco.rollout`.

Symbols: `b` instance, `E` episodes, `T` control steps per episode (the step limit),
`n` MuJoCo steps per control step (the instance's, the domain module's
`sub_steps(params)`: `N_SUB_STEPS`, or a multiple of it for a fast instance),
`D` state dimension, `A` actions.

An open-loop episode is exactly what the domain's dm_control environment does with a
fixed action sequence: it starts from `s₀` (drawn like the task does, `U[-c, c]^D`),
each control step holds `ctrl = ACTIONS[a_t]` for `n` calls of `mj_step`, the state is
`(qpos, qvel)` with angles wrapped to (-π, π], rewards and termination are the task's
(`tasks.agents.DOMAINS[...].planning_task` on arrays) and the episode ends at the
first terminal state or after `T` steps. `tests/test_generate_scale.py` checks the
result equals stepping the environment with the same actions, bit for bit.

All episodes of a block of instances go to one `mujoco.rollout.rollout` call with a
list of per-instance models (C loop, no Python per step), `chunk` control steps at a
time: after each chunk, episodes that have ended are dropped from the batch, so
early-terminating episodes (cart-pole failures) cost at most one chunk.

Divergence: MuJoCo resets the data when the acceleration blows up (a warning, which
the environment turns into `PhysicsError`). A reset sends the simulation time back,
so an episode whose time does not increase at every step, or whose state is not
finite, is dropped and reported as a `Divergence`, as `tasks.collect` does.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from hipmdp.data import ParameterTable, Transitions
from tasks import acrobot, agents, cartpole
from tasks._common import parameter_names, parameter_values
from tasks.collect import (
    Collection,
    Divergence,
    _check_instances,
    _check_positive_int,
    get_domain,
    instance_streams,
)

Array = np.ndarray

#: Per domain: its module (`make_model`, `ACTIONS`, `N_SUB_STEPS`, `sub_steps`,
#: `INITIAL_NOISE`, `DEFAULT_MAX_STEPS`).
MODULES = {"acrobot": acrobot, "cartpole": cartpole}
STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS
#: Control steps per `mujoco.rollout` call.
DEFAULT_CHUNK = 25


class OpenLoop(NamedTuple):
    """Rolled-out episodes, `E` of them with step limit `T`.

    Attributes:
        states: `s_0 … s_T` per episode, shape `(E, T + 1, D)`, angles wrapped; only
            the first `lengths[e] + 1` rows of episode `e` are meaningful.
        lengths: control steps taken, shape `(E,)`, in `[1, T]`.
        rewards: shape `(E, T)`, meaningful up to `lengths`.
        diverged: the control step at which the episode diverged, or -1, `(E,)`.
    """

    states: Array
    lengths: Array
    rewards: Array
    diverged: Array


def wrap(x: Array) -> Array:
    """Angles wrapped to (-π, π] exactly as `tasks._common.wrap_scalar_angle` does.

    `math.remainder(x, 2π)` per element: `r = fmod(x, 2π)` is exact, and moving `r`
    from `(π, 2π)` to `(-π, 0)` (or back) by `∓2π` is exact by Sterbenz's lemma; -π
    maps to π. Any shape.
    """
    two_pi = 2 * np.pi
    r = np.fmod(x, two_pi)
    r = np.where(r > np.pi, r - two_pi, r)
    r = np.where(r < -np.pi, r + two_pi, r)
    return np.where(r == -np.pi, np.pi, r)


def rollout_episodes(
    domain: str,
    instances: Sequence[Any],
    episode_instance: Array,
    initial_states: Array,
    actions: Array,
    *,
    chunk: int = DEFAULT_CHUNK,
) -> OpenLoop:
    """Roll out open-loop action sequences on their instances.

    Args:
        domain: "acrobot" or "cartpole".
        instances: parameters of the `B` instances.
        episode_instance: for each episode, its index into `instances`, `(E,)`.
        initial_states: `s₀` per episode, `(E, D)` (qpos then qvel).
        actions: action indices per episode, `(E, T)`; `T` is the step limit.
        chunk: control steps per `mujoco.rollout` call (at `N_SUB_STEPS` MuJoCo
            steps each; an instance with a finer step takes proportionally fewer).

    Returns:
        `OpenLoop`.
    """
    spec = get_domain(domain)
    module = MODULES[domain]
    episode_instance = np.asarray(episode_instance)
    initial_states = np.asarray(initial_states, dtype=float)
    actions = np.asarray(actions)
    n_episodes, n_steps = actions.shape if actions.ndim == 2 else (-1, -1)
    if n_episodes < 1 or n_steps < 1:
        raise ValueError(f"actions must have shape (E, T), got {actions.shape}")
    if initial_states.shape != (n_episodes, spec.state_dim):
        raise ValueError(
            f"initial_states must have shape ({n_episodes}, {spec.state_dim}), "
            f"got {initial_states.shape}"
        )
    # integers: a bool array would pass the bounds and then act as a mask, a
    # float one fail as an index deep inside
    if (
        episode_instance.shape != (n_episodes,)
        or episode_instance.dtype.kind not in "iu"
        or not np.all((episode_instance >= 0) & (episode_instance < len(instances)))
    ):
        raise ValueError(
            f"episode_instance must be {n_episodes} integer indices into "
            f"{len(instances)} instances, got {_described(episode_instance)}"
        )
    if actions.dtype.kind not in "iu" or np.any(
        (actions < 0) | (actions >= spec.n_actions)
    ):
        raise ValueError(
            f"actions must be integer indices in [0, {spec.n_actions}), got "
            f"{_described(actions)}"
        )
    _check_positive_int("chunk", chunk)

    # MuJoCo steps per action: the instance's own (a fast instance takes shorter
    # steps, `sub_steps`); one rollout per count
    n_subs = np.array([module.sub_steps(p) for p in instances])
    counts = np.unique(n_subs[episode_instance])
    if len(counts) > 1:
        out = OpenLoop(
            np.zeros((n_episodes, n_steps + 1, spec.state_dim)),
            np.zeros(n_episodes, dtype=int), np.zeros((n_episodes, n_steps)),
            np.zeros(n_episodes, dtype=int),
        )  # fmt: skip
        for count in counts:
            rows = np.flatnonzero(n_subs[episode_instance] == count)
            part = rollout_episodes(
                domain, instances, episode_instance[rows], initial_states[rows],
                actions[rows], chunk=chunk,
            )  # fmt: skip
            for whole, piece in zip(out, part, strict=True):
                whole[rows] = piece
        return out
    models = [module.make_model(p) for p in instances]
    tasks = [agents.DOMAINS[domain].planning_task(p, n_steps) for p in instances]
    nq, n_sub = models[0].nq, int(counts[0])
    # the same MuJoCo steps per call whatever the instance's step: memory bounded
    chunk = max(1, chunk * module.N_SUB_STEPS // n_sub)
    qpos_at = mujoco.mj_stateSize(models[0], mujoco.mjtState.mjSTATE_TIME)
    data = mujoco.MjData(models[0])
    physics = np.zeros((n_episodes, mujoco.mj_stateSize(models[0], STATE_SPEC)))
    scratch = [mujoco.MjData(model) for model in models]  # MjData is costly to make
    for e, (b, s0) in enumerate(zip(episode_instance, initial_states, strict=True)):
        mujoco.mj_resetData(models[b], scratch[b])  # what env.reset() starts from
        scratch[b].qpos[:], scratch[b].qvel[:] = s0[:nq], s0[nq:]
        mujoco.mj_getState(models[b], scratch[b], physics[e], STATE_SPEC)

    states = np.zeros((n_episodes, n_steps + 1, spec.state_dim))
    states[:, 0] = initial_states
    rewards = np.zeros((n_episodes, n_steps))
    lengths = np.full(n_episodes, n_steps)
    diverged = np.full(n_episodes, -1)
    active = np.arange(n_episodes)
    controls = module.ACTIONS[actions]  # (E, T)
    for t0 in range(0, n_steps, chunk):
        t1 = min(t0 + chunk, n_steps)
        control = np.repeat(controls[active, t0:t1], n_sub, axis=1)[..., None]
        out, _ = mj_rollout.rollout(
            [models[b] for b in episode_instance[active]],
            data,
            physics[active],
            control,
        )
        ends = out[:, n_sub - 1 :: n_sub]  # state after each control step
        s = ends[..., qpos_at : qpos_at + spec.state_dim].copy()
        s[..., list(spec.angle_dims)] = wrap(s[..., list(spec.angle_dims)])
        states[active, t0 + 1 : t1 + 1] = s
        # Time must advance by one step per mj_step; a reset sends it back.
        time = np.concatenate([physics[active, :1], out[..., 0]], axis=1)
        bad = (np.diff(time, axis=1) <= 0).reshape(len(active), t1 - t0, n_sub)
        bad = bad.any(axis=2) | ~np.isfinite(s).all(axis=2)
        done = np.zeros((len(active), t1 - t0), dtype=bool)
        for b in np.unique(episode_instance[active]):
            rows = episode_instance[active] == b
            prev = states[active[rows], t0:t1]
            r = tasks[b].reward(
                prev.reshape(-1, spec.state_dim),
                actions[active[rows], t0:t1].reshape(-1),
                s[rows].reshape(-1, spec.state_dim),
            )
            rewards[active[rows], t0:t1] = r.reshape(-1, t1 - t0)
            term = tasks[b].terminal(np.nan_to_num(s[rows]).reshape(-1, spec.state_dim))
            done[rows] = term.reshape(-1, t1 - t0)
        # An episode ends at its first terminal step unless it diverged before.
        never = t1 - t0
        first_bad = np.where(bad.any(axis=1), bad.argmax(axis=1), never)
        first_done = np.where(done.any(axis=1), done.argmax(axis=1), never)
        broke = first_bad < never
        broke &= first_bad <= first_done
        ended = (first_done < never) & ~broke
        diverged[active[broke]] = t0 + first_bad[broke]
        lengths[active[ended]] = t0 + first_done[ended] + 1
        finished = broke | ended
        physics[active] = out[:, -1]
        active = active[~finished]
        if active.size == 0:
            break
    return OpenLoop(states, lengths, rewards, diverged)


def _described(x: Array) -> str:
    """An index array for an error message: dtype, shape and value range."""
    text = f"{x.dtype} of shape {x.shape}"
    if x.size and x.dtype.kind in "iufb":
        text += f" in [{x.min()}, {x.max()}]"
    return text


def collect_open_loop(
    domain: str,
    instances: Sequence[Any],
    *,
    episodes_per_instance: int,
    rng: np.random.Generator | Sequence[np.random.Generator],
    instance_ids: Sequence[int] | None = None,
    max_steps: int | None = None,
    chunk: int = DEFAULT_CHUNK,
) -> Collection:
    """Open-loop uniformly random action sequences on every instance.

    Instance `b` (the `i`-th) gets `rng.spawn(B)[i]` (or `rng[i]`,
    `tasks.collect.instance_streams`), which spawns two streams: the
    first draws the `E` initial states `U[-c, c]^{E×D}` (the draws the environment
    would make with that stream as its seed), the second the actions
    `a ~ Uniform{0, …, A-1}^{E×T}`.

    Args and Returns: as `tasks.collect.collect` (the policy is the open-loop one).
    """
    spec = get_domain(domain)
    module = MODULES[domain]
    instances = list(instances)
    ids = _check_instances(spec, instances, instance_ids)
    _check_positive_int("episodes_per_instance", episodes_per_instance)
    n_steps = module.DEFAULT_MAX_STEPS if max_steps is None else max_steps
    _check_positive_int("max_steps", n_steps)
    e_per = episodes_per_instance
    initial, actions = [], []
    for stream in instance_streams(rng, len(instances)):
        init_rng, action_rng = stream.spawn(2)
        c = module.INITIAL_NOISE
        initial.append(init_rng.uniform(-c, c, size=(e_per, spec.state_dim)))
        actions.append(action_rng.integers(spec.n_actions, size=(e_per, n_steps)))
    episode_instance = np.repeat(np.arange(len(instances)), e_per)
    result = rollout_episodes(
        domain,
        instances,
        episode_instance,
        np.concatenate(initial),
        np.concatenate(actions),
        chunk=chunk,
    )
    actions = np.concatenate(actions)
    diverged = [
        Divergence(
            ids[episode_instance[e]], e % e_per, int(step), "MuJoCo reset or NaN"
        )
        for e, step in enumerate(result.diverged)
        if step >= 0
    ]
    # Step t of episode e is kept if t < length and e did not diverge; boolean
    # indexing keeps the episodes in order and each one's steps in order.
    t = np.arange(n_steps)[None, :]
    kept = (t < result.lengths[:, None]) & (result.diverged[:, None] < 0)
    transitions = Transitions(
        states=result.states[:, :-1][kept],
        actions=actions[kept],
        next_states=result.states[:, 1:][kept],
        instances=np.broadcast_to(np.array(ids)[episode_instance][:, None], kept.shape)[
            kept
        ],
        rewards=result.rewards[kept],
        dones=(t == result.lengths[:, None] - 1)[kept],
        angle_dims=spec.angle_dims,
        dt=spec.dt,
    )
    table = ParameterTable(
        instances=np.array(ids),
        names=parameter_names(spec.params_type),
        values=np.array([parameter_values(p) for p in instances]),
    )
    return Collection(transitions, table, len(episode_instance), tuple(diverged))
