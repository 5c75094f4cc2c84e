"""Gathering transitions: run a policy on one or many instances of a domain.

Symbols: `b` instance id, `s` state `(qpos, qvel)` with angles wrapped, shape `(D,)`,
`a` discrete action index in `[0, A)`, `N` transitions.

A policy is any callable `state -> action index`; `random_policy` draws actions
uniformly. `collect_sarsa` instead runs a Sarsa(λ) agent that learns on each
instance from scratch (`tasks.agents.learn`, the paper's way of gathering data;
greedy, ε = 0, exploring through optimistic initial values, ties broken at
random) and keeps every transition it saw. A simulation that diverges (MuJoCo raises
a warning, which dm_control turns into `PhysicsError`, or a state is not finite)
ends its episode; the whole episode is then dropped from the data and reported in
`Collection.diverged`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np
from dm_control.rl import control
from tqdm import tqdm

from hipmdp.data import ParameterTable, Transitions, is_integer
from tasks import acrobot, agents, cartpole
from tasks._common import STATE_OBSERVATION, parameter_names, parameter_values

Array = np.ndarray
Policy = Callable[[Array], int]


class Domain(NamedTuple):
    """What gathering needs to know about a domain."""

    name: str
    params_type: type
    make_env: Callable[..., control.Environment]
    n_actions: int
    state_dim: int
    angle_dims: tuple[int, ...]
    dt: float  # seconds per action (angle changes are unwrapped with it)


DOMAINS = {
    "acrobot": Domain(
        "acrobot",
        acrobot.AcrobotParams,
        acrobot.swingup,
        len(acrobot.ACTIONS),
        acrobot.STATE_DIM,
        acrobot.ANGLE_DIMS,
        acrobot.CONTROL_TIMESTEP,
    ),
    "cartpole": Domain(
        "cartpole",
        cartpole.CartpoleParams,
        cartpole.balance,
        len(cartpole.ACTIONS),
        cartpole.STATE_DIM,
        cartpole.ANGLE_DIMS,
        cartpole.CONTROL_TIMESTEP,
    ),
}


class Divergence(NamedTuple):
    """One episode dropped because its simulation diverged."""

    instance: int
    episode: int
    step: int
    reason: str


class Collection(NamedTuple):
    """What `collect` gathered.

    Attributes:
        transitions: the kept transitions, `N` of them, `angle_dims` set; `dones`
            marks the last transition of each episode (goal, failure or limit).
        parameters: one row per instance id `b`, columns the dataclass fields.
        n_episodes: episodes run, kept or not.
        diverged: the dropped episodes.
    """

    transitions: Transitions
    parameters: ParameterTable
    n_episodes: int
    diverged: tuple[Divergence, ...]


def get_domain(name: str) -> Domain:
    """The registered domain called `name` (ValueError listing the choices)."""
    if name not in DOMAINS:
        raise ValueError(f"domain must be one of {sorted(DOMAINS)}, got {name!r}")
    return DOMAINS[name]


def random_policy(n_actions: int, *, rng: np.random.Generator) -> Policy:
    """A policy ignoring the state: `a ~ Uniform{0, …, n_actions - 1}`."""
    if isinstance(n_actions, bool) or not isinstance(n_actions, int) or n_actions < 1:
        raise ValueError(f"n_actions must be a positive int, got {n_actions!r}")
    return lambda state: int(rng.integers(n_actions))


def instance_streams(rng: Any, n: int) -> list[np.random.Generator]:
    """Each instance's stream: ``rng.spawn(n)`` for one Generator, or ``rng``
    itself for a sequence of ``n`` Generators (one per instance, as
    ``tasks.generate`` gives them, so an instance's data do not depend on the
    instances collected beside it). Raises ValueError naming ``rng``."""
    if isinstance(rng, np.random.Generator):
        return rng.spawn(n)
    streams = list(rng) if isinstance(rng, Sequence) else None
    if (
        streams is None
        or len(streams) != n
        or not all(isinstance(g, np.random.Generator) for g in streams)
    ):
        raise ValueError(
            f"rng: expected a numpy Generator or a sequence of {n} (one per "
            f"instance), got {rng!r}"
        )
    return streams


def collect(
    domain: str,
    instances: Sequence[Any],
    *,
    episodes_per_instance: int,
    rng: np.random.Generator | Sequence[np.random.Generator],
    policy: Policy | None = None,
    instance_ids: Sequence[int] | None = None,
    max_steps: int | None = None,
    progress: bool = False,
) -> Collection:
    """Run `policy` for `episodes_per_instance` episodes on each instance.

    Args:
        domain: "acrobot" or "cartpole".
        instances: the parameters of each instance (`AcrobotParams` or
            `CartpoleParams`), length `B`.
        episodes_per_instance: episodes per instance, ≥ 1.
        rng: all randomness (initial states, and the random policy when `policy`
            is None) is drawn from streams spawned from it: instance `i`'s
            environment from `rng.spawn(B)[i]`, the random policy from one more
            stream shared by the instances in turn. Or one Generator per
            instance (`instance_streams`): each spawns two, the environment's
            and its own random policy's.
        policy: `state (D,) -> action index`, or None for `random_policy`.
        instance_ids: the id `b` of each instance, default `0, …, B-1`.
        max_steps: step limit per episode, default the task's.
        progress: show a tqdm bar over episodes.

    Returns:
        A `Collection`.
    """
    spec = get_domain(domain)
    instances = list(instances)
    ids = _check_instances(spec, instances, instance_ids)
    _check_positive_int("episodes_per_instance", episodes_per_instance)
    if max_steps is not None:
        _check_positive_int("max_steps", max_steps)
    per_instance = not isinstance(rng, np.random.Generator)
    streams = instance_streams(rng, len(instances))
    if policy is not None and not callable(policy):
        raise ValueError(f"policy must be callable or None, got {policy!r}")

    if per_instance:
        pairs = [stream.spawn(2) for stream in streams]
        env_rngs = [env_rng for env_rng, _ in pairs]
        policies = [
            policy or random_policy(spec.n_actions, rng=policy_rng)
            for _, policy_rng in pairs
        ]
    else:
        env_rngs = streams
        if policy is None:
            policy = random_policy(spec.n_actions, rng=rng.spawn(1)[0])
        policies = [policy] * len(instances)
    kwargs = {} if max_steps is None else {"max_steps": max_steps}
    episodes: list[dict[str, Array]] = []
    diverged: list[Divergence] = []
    bar = tqdm(
        total=len(instances) * episodes_per_instance,
        desc=f"{domain} episodes",
        disable=not progress,
    )
    with bar:
        for b, params, env_rng, policy in zip(
            ids, instances, env_rngs, policies, strict=True
        ):
            env = spec.make_env(params, seed=env_rng, **kwargs)
            for episode in range(episodes_per_instance):
                result = run_episode(env, policy, spec.n_actions)
                if isinstance(result, Divergence):
                    diverged.append(result._replace(instance=b, episode=episode))
                else:
                    result["instances"] = np.full(len(result["actions"]), b)
                    episodes.append(result)
                bar.update()

    transitions = Transitions(
        **_stack(episodes, spec.state_dim), angle_dims=spec.angle_dims, dt=spec.dt
    )
    return Collection(
        transitions,
        _table(spec, ids, instances),
        len(instances) * episodes_per_instance,
        tuple(diverged),
    )


def collect_sarsa(
    domain: str,
    instances: Sequence[Any],
    *,
    episodes_per_instance: int,
    rng: np.random.Generator | Sequence[np.random.Generator],
    instance_ids: Sequence[int] | None = None,
    max_steps: int | None = None,
) -> Collection:
    """A fresh Sarsa(λ) agent learns for `episodes_per_instance` episodes on each
    instance (`tasks.agents.learn` with the domain's defaults); every transition it
    saw is kept.

    Instance `i` gets `rng.spawn(B)[i]` (or `rng[i]`, `instance_streams`), which
    spawns the environment's seed (initial states) and the agent's exploration
    stream. If the simulation
    diverges (`PhysicsError`), the instance's episodes are all dropped and
    reported as one `Divergence` with `episode = -1` (learning cannot continue
    past a diverged step).

    Args and Returns: as `collect` (the policy is the learning agent).
    """
    spec = get_domain(domain)
    instances = list(instances)
    ids = _check_instances(spec, instances, instance_ids)
    _check_positive_int("episodes_per_instance", episodes_per_instance)
    agent_domain = agents.DOMAINS[domain]
    n_steps = agent_domain.max_steps if max_steps is None else max_steps
    _check_positive_int("max_steps", n_steps)
    parts, diverged = [], []
    streams = instance_streams(rng, len(ids))
    for b, params, stream in zip(ids, instances, streams, strict=True):
        env_rng, agent_rng = stream.spawn(2)
        env = spec.make_env(params, seed=env_rng, max_steps=n_steps)
        try:
            result = agents.learn(
                env, agent_domain, episodes_per_instance, rng=agent_rng, instance=b
            )
        except control.PhysicsError as error:
            diverged.append(Divergence(b, -1, -1, f"MuJoCo warning: {error}"))
            continue
        parts.append(result.transitions)
    transitions = (
        Transitions.concatenate(parts)
        if parts
        else Transitions(
            **_stack([], spec.state_dim), angle_dims=spec.angle_dims, dt=spec.dt
        )
    )
    return Collection(
        transitions,
        _table(spec, ids, instances),
        len(ids) * episodes_per_instance,
        tuple(diverged),
    )


def run_episode(
    env: control.Environment, policy: Policy, n_actions: int
) -> dict[str, Array] | Divergence:
    """One episode from `env.reset()` until it ends.

    Returns:
        Arrays `states (T, D)`, `actions (T,)`, `next_states (T, D)`,
        `rewards (T,)`, `dones (T,)`; or a `Divergence` (with `instance` and
        `episode` set to -1) if the simulation diverged at some step.
    """
    step = env.reset()
    s = step.observation[STATE_OBSERVATION]
    rows: dict[str, list] = {
        k: [] for k in ("states", "actions", "next_states", "rewards", "dones")
    }
    t = 0
    while not step.last():
        a = policy(s)
        if isinstance(a, bool) or not isinstance(a, int | np.integer):
            raise ValueError(f"policy must return an int action index, got {a!r}")
        if not 0 <= a < n_actions:
            raise ValueError(f"policy returned action {a}, expected [0, {n_actions})")
        try:
            step = env.step(a)
        except control.PhysicsError as error:
            return Divergence(-1, -1, t, f"MuJoCo warning: {error}")
        s2 = step.observation[STATE_OBSERVATION]
        if not np.all(np.isfinite(s2)):
            return Divergence(-1, -1, t, "non-finite state")
        for key, value in zip(
            rows, (s, int(a), s2, step.reward, step.last()), strict=True
        ):
            rows[key].append(value)
        s, t = s2, t + 1
    return {k: np.array(v) for k, v in rows.items()}


def _stack(episodes: list[dict[str, Array]], state_dim: int) -> dict[str, Array]:
    """Concatenate episode arrays (empty arrays of the right shapes if none)."""
    if not episodes:
        empty_states = np.zeros((0, state_dim))
        return {
            "states": empty_states,
            "actions": np.zeros(0, dtype=int),
            "next_states": empty_states,
            "instances": np.zeros(0, dtype=int),
            "rewards": np.zeros(0),
            "dones": np.zeros(0, dtype=bool),
        }
    return {k: np.concatenate([e[k] for e in episodes]) for k in episodes[0]}


def _check_instances(
    spec: Domain, instances: list[Any], instance_ids: Sequence[int] | None
) -> list[int]:
    """The instance ids (default `0, …, B-1`) after checking `instances` and ids."""
    if not instances:
        raise ValueError("instances must hold at least one parameter set")
    for params in instances:
        if not isinstance(params, spec.params_type):
            raise ValueError(
                f"instances must be {spec.params_type.__name__}, got {params!r}"
            )
    ids = list(range(len(instances))) if instance_ids is None else list(instance_ids)
    # integers (not bools): 0.5 failed as "instances" after every episode ran,
    # True was taken as 1
    if (
        len(ids) != len(instances)
        or not all(is_integer(i) for i in ids)
        or len(set(ids)) != len(ids)
    ):
        raise ValueError(
            f"instance_ids must be {len(instances)} distinct ints, got {ids!r}"
        )
    return [int(i) for i in ids]


def _table(spec: Domain, ids: list[int], instances: list[Any]) -> ParameterTable:
    """The parameter table of `instances` with ids `ids`."""
    return ParameterTable(
        instances=np.array(ids),
        names=parameter_names(spec.params_type),
        values=np.array([parameter_values(p) for p in instances]),
    )


def _check_positive_int(name: str, value: Any) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is an integer >= 1
    (a Python or numpy one; not a bool), as :func:`hipmdp.data.check_integer`."""
    if not is_integer(value) or value < 1:
        raise ValueError(f"{name} must be a positive int, got {value!r}")
