"""Agents on live instances: Sarsa(λ) with a Fourier basis learning on a dm_control
environment, the transitions they saw, and the true-simulator dynamics model.

Symbols: ``s`` state ``(D,)``, ``a`` action index, ``r`` reward, ``φ(s)`` Fourier
features ``(F,)``, ``θ`` weights ``(A, F)``.

Per-domain defaults (:data:`DOMAINS`); the orders are the paper's (Doshi-Velez &
Konidaris, §5), the rest standard Sarsa(λ) values (Sutton & Barto 1998, §8.4 and
§11.3: λ = 0.9, ε = 0 with optimistic initial values; Konidaris et al. 2011: α = 0.001
with per-feature scaling ``α_i = α / ‖c_i‖``), accumulating traces:

========  =====  ==========================================  =====  ===  ====  ===  ===
domain    order  state box (normalisation, clipped)          α      λ    γ     ε    q₀
========  =====  ==========================================  =====  ===  ====  ===  ===
cartpole  3      x ±2.4 m, θ ±12°, ẋ ±2.5 m/s, θ̇ ±3.5 rad/s  0.001  0.9  0.99  0    100
acrobot   5      θ₁, θ₂ ±π, θ̇₁ ±4π, θ̇₂ ±9π rad/s            0.001  0.9  1     0    0
========  =====  ==========================================  =====  ===  ====  ===  ===

The acrobot's velocity box is Sutton & Barto's velocity limits; the cart-pole's
position and angle boxes are its failure thresholds. ``q₀`` is the initial action
value (``hipmdp.sarsa.init_state``): optimistic in both tasks (rewards are −1 per
step for the acrobot; +1 per step for the cart-pole, whose returns stay below
``1 / (1 − γ) = 100``), so ε = 0 still explores.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from dm_control.rl import control
from numpy.typing import NDArray
from tqdm.auto import tqdm

from hipmdp.data import Transitions, check_integer
from hipmdp.fourier import FourierBasis
from hipmdp.planning import PlanningTask
from hipmdp.sarsa import (
    SarsaConfig,
    SarsaState,
    epsilon_greedy,
    init_state,
    reset_traces,
    sarsa_update,
)
from tasks import acrobot, cartpole

Array = NDArray[np.float64]


@dataclasses.dataclass(frozen=True)
class Domain:
    """What an agent needs to know about a domain.

    Attributes:
        name: ``"cartpole"`` or ``"acrobot"``.
        make_env: ``make_env(params, *, seed, max_steps) -> Environment``.
        params_type: the domain's parameter dataclass.
        order: Fourier order ``n``.
        low, high: the normalisation box, shape ``(D,)`` each.
        sarsa: default Sarsa(λ) hyperparameters.
        initial_value: ``q₀``, the optimistic initial action value.
        max_steps: default step limit per episode.
        angle_dims: which state dimensions are angles.
        n_actions: ``A``.
        planning_task: ``planning_task(params, max_steps) -> PlanningTask``: the
            task's reward and termination on arrays of predicted states.
    """

    name: str
    make_env: Callable[..., control.Environment]
    params_type: type
    order: int
    low: tuple[float, ...]
    high: tuple[float, ...]
    sarsa: SarsaConfig
    initial_value: float
    max_steps: int
    angle_dims: tuple[int, ...]
    n_actions: int
    planning_task: Callable[[Any, int], PlanningTask]

    def basis(self) -> FourierBasis:
        """The domain's Fourier basis."""
        return FourierBasis(self.order, np.array(self.low), np.array(self.high))


def _acrobot_planning_task(params: Any, max_steps: int) -> PlanningTask:
    """Reward −1 per step; terminal when the predicted tip is above ``l₁``
    (``tasks.acrobot.goal_reached`` on the predicted states)."""

    def reward(states: Array, actions: Array, next_states: Array) -> Array:
        return np.full(states.shape[0], -1.0)

    def terminal(next_states: Array) -> NDArray[np.bool_]:
        return acrobot.goal_reached(next_states, params)

    return PlanningTask(reward, terminal, max_steps)


ACROBOT = Domain(
    name="acrobot",
    make_env=acrobot.swingup,
    params_type=acrobot.AcrobotParams,
    order=5,
    low=(-np.pi, -np.pi, -4 * np.pi, -9 * np.pi),
    high=(np.pi, np.pi, 4 * np.pi, 9 * np.pi),
    sarsa=SarsaConfig(alpha=0.001, lam=0.9, gamma=1.0, epsilon=0.0),
    initial_value=0.0,
    max_steps=acrobot.DEFAULT_MAX_STEPS,
    angle_dims=acrobot.ANGLE_DIMS,
    n_actions=len(acrobot.ACTIONS),
    planning_task=_acrobot_planning_task,
)


def _cartpole_planning_task(params: Any, max_steps: int) -> PlanningTask:
    """Reward 1 while the predicted state has not failed, 0 when it has; terminal
    at failure (``tasks.cartpole.failed`` on the predicted states)."""

    def reward(states: Array, actions: Array, next_states: Array) -> Array:
        return np.where(cartpole.failed(next_states), 0.0, 1.0)

    def terminal(next_states: Array) -> NDArray[np.bool_]:
        return cartpole.failed(next_states)

    return PlanningTask(reward, terminal, max_steps)


CARTPOLE = Domain(
    name="cartpole",
    make_env=cartpole.balance,
    params_type=cartpole.CartpoleParams,
    order=3,
    low=(-cartpole.X_LIMIT, -cartpole.THETA_LIMIT, -2.5, -3.5),
    high=(cartpole.X_LIMIT, cartpole.THETA_LIMIT, 2.5, 3.5),
    sarsa=SarsaConfig(alpha=0.001, lam=0.9, gamma=0.99, epsilon=0.0),
    initial_value=100.0,
    max_steps=cartpole.DEFAULT_MAX_STEPS,
    angle_dims=cartpole.ANGLE_DIMS,
    n_actions=len(cartpole.ACTIONS),
    planning_task=_cartpole_planning_task,
)

DOMAINS: dict[str, Domain] = {"cartpole": CARTPOLE, "acrobot": ACROBOT}


class EnergyConserving:
    """A dynamics model whose predicted velocities are rescaled so that each step
    changes the energy of the acrobot ``params`` by the elbow torque's work
    (:func:`tasks.acrobot.conserve_energy`; where no speed reaches that energy,
    below the predicted pose's potential or from a prediction at rest, the
    velocities are 0)."""

    def __init__(self, model, params: acrobot.AcrobotParams) -> None:
        self._model, self._params = model, params

    def predict(self, states: Array, actions: Array) -> Array:
        torques = acrobot.ACTIONS[np.asarray(actions)]
        predicted = self._model.predict(states, actions)
        return acrobot.conserve_energy(states, torques, predicted, self._params)


class SimulatorModel:
    """The true dynamics of one instance as a batched :class:`DynamicsModel`.

    ``predict`` sets the MuJoCo state ``(qpos, qvel) = s`` of a private copy of the
    instance's environment, applies the action through the task's own
    ``before_step`` (control ``ACTIONS[a]``) and calls ``physics.step(n_sub_steps)``
    exactly as ``env.step`` does; ``s'`` is ``physics.state()`` (angles wrapped).
    Rows are stepped one after another (MuJoCo steps one state at a time).

    Args:
        domain: the domain (its ``make_env`` builds the copy).
        params: the instance (nominal if None).
    """

    def __init__(self, domain: Domain, params: Any = None) -> None:
        self.domain = domain
        self.params = params
        env = domain.make_env(params, seed=0)
        self._physics = env.physics
        self._task = env.task
        self._n_sub_steps = round(env.control_timestep() / env.physics.timestep())
        self._nq = env.physics.model.nq

    def step(self, state: Array, action: int) -> Array:
        """One control step from one state: ``s'``, shape ``(D,)``."""
        physics, nq = self._physics, self._nq
        physics.data.qpos[:] = state[:nq]
        physics.data.qvel[:] = state[nq:]
        self._task.before_step(action, physics)
        physics.step(self._n_sub_steps)
        return physics.state()

    def predict(self, states: Array, actions: NDArray[np.int64]) -> Array:
        """Next states for a batch: ``states`` ``(N, D)``, ``actions`` ``(N,)`` →
        ``(N, D)``."""
        s = np.asarray(states, dtype=np.float64)
        a = np.asarray(actions)
        if s.ndim != 2 or s.shape[1] != 2 * self._nq:
            raise ValueError(
                f"states: expected shape (N, {2 * self._nq}), got {s.shape}"
            )
        if a.shape != (s.shape[0],):
            raise ValueError(f"actions: expected shape ({s.shape[0]},), got {a.shape}")
        out = np.empty_like(s)
        for n in range(s.shape[0]):
            out[n] = self.step(s[n], a[n])
        return out


class Episode(NamedTuple):
    """One real episode: the agent ``state`` after it; ``states`` ``(T + 1, D)``
    (``s_0 … s_T``); ``actions`` ``(T,)``; ``rewards`` ``(T,)``; ``terminal`` whether
    it ended in a terminal state (not by the step limit)."""

    state: SarsaState
    states: Array
    actions: NDArray[np.int64]
    rewards: Array
    terminal: bool


def run_episode(
    env: control.Environment,
    basis: FourierBasis,
    config: SarsaConfig,
    state: SarsaState,
    *,
    rng: np.random.Generator,
    learn: bool = True,
) -> Episode:
    """One episode of ε-greedy Sarsa(λ) on a live environment.

    Per step: ``a' = ε-greedy(θ φ(s'))``, then ``sarsa_update`` on
    ``(s, a, r, s', a')``; a terminal step (dm_env discount 0) does not bootstrap,
    a step-limit end (discount 1) does.

    Args:
        env: a dm_control environment with a ``"state"`` observation and integer
            actions; it is reset here.
        basis: ``φ``; config: α, λ, γ, ε; state: ``θ`` ``(A, F)`` (traces reset).
        rng: exploration stream (the environment's initial state comes from its
            own seed).
        learn: update ``θ`` (otherwise act only).
    """
    step_sizes = config.alpha * basis.step_scale
    state = reset_traces(state)
    time_step = env.reset()
    s = time_step.observation["state"]
    states, actions, rewards = [s], [], []
    phi = basis(s)
    a = epsilon_greedy(state.weights @ phi, config.epsilon, rng=rng)
    while True:
        time_step = env.step(a)
        s2, r = time_step.observation["state"], float(time_step.reward)
        terminal = time_step.last() and time_step.discount == 0.0
        states.append(s2)
        actions.append(a)
        rewards.append(r)
        phi2 = basis(s2)
        a2 = epsilon_greedy(state.weights @ phi2, config.epsilon, rng=rng)
        if learn:
            state = sarsa_update(
                state, phi, a, r, None if terminal else phi2, a2, step_sizes, config
            ).state
        if time_step.last():
            break
        phi, a = phi2, a2
    return Episode(
        state,
        np.array(states),
        np.array(actions, dtype=np.int64),
        np.array(rewards),
        bool(terminal),
    )


class LearnResult(NamedTuple):
    """Output of :func:`learn`: the agent ``state``; every ``transitions`` seen
    (one instance id); per episode the ``steps`` ``(E,)`` and ``returns`` ``(E,)``."""

    state: SarsaState
    transitions: Transitions
    steps: NDArray[np.int64]
    returns: Array


def episode_transitions(
    episode: Episode, instance: int, angle_dims: tuple[int, ...], dt: float
) -> Transitions:
    """The ``T`` transitions of one episode, ``dones`` true on the last; ``dt`` is
    the seconds per action (fast angle changes are unwrapped with it)."""
    n = episode.actions.shape[0]
    dones = np.zeros(n, dtype=bool)
    dones[-1] = True
    return Transitions(
        states=episode.states[:-1],
        actions=episode.actions,
        next_states=episode.states[1:],
        instances=np.full(n, instance),
        rewards=episode.rewards,
        dones=dones,
        angle_dims=angle_dims,
        dt=dt,
    )


def learn(
    env: control.Environment,
    domain: Domain,
    n_episodes: int,
    *,
    rng: np.random.Generator,
    config: SarsaConfig | None = None,
    state: SarsaState | None = None,
    instance: int = 0,
    progress: bool = False,
) -> LearnResult:
    """Sarsa(λ) learning for ``n_episodes`` real episodes on ``env``.

    Args:
        env: the live instance (its step limit is the episode length).
        domain: basis and defaults; config: overrides ``domain.sarsa``.
        state: a starting agent (fresh zero weights if None).
        instance: the id written into the transitions.
        rng: exploration stream; progress: show a progress bar over episodes.
    """
    check_integer("n_episodes", n_episodes, 1)
    config = domain.sarsa if config is None else config
    basis = domain.basis()
    if state is None:
        state = init_state(domain.n_actions, basis.n_features, domain.initial_value)
    parts, steps, returns = [], [], []
    bar = tqdm(range(n_episodes), desc=f"{domain.name} sarsa", disable=not progress)
    for _ in bar:
        episode = run_episode(env, basis, config, state, rng=rng)
        state = episode.state
        parts.append(
            episode_transitions(
                episode, instance, domain.angle_dims, env.control_timestep()
            )
        )
        steps.append(episode.actions.shape[0])
        returns.append(float(episode.rewards.sum()))
        bar.set_postfix(steps=steps[-1])
    return LearnResult(
        state,
        Transitions.concatenate(parts),
        np.array(steps, dtype=np.int64),
        np.array(returns),
    )
