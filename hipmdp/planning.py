"""Dynamics models and Dyna-style planning: Sarsa(λ) episodes simulated on a model.

Symbols: ``N`` states in a batch (or episodes in lockstep), ``D`` state dimension,
``s`` states ``(N, D)``, ``a`` discrete actions ``(N,)``, ``s'`` next states ``(N, D)``,
``Δ = s' − s`` (angle changes as ``hipmdp.Transitions.deltas`` gives them; the
angle dimensions of ``s'`` are wrapped to ``(−π, π]``).

- :class:`DynamicsModel`: anything with ``predict(states, actions) -> next_states``
  (batched). Implementations: the true simulator of an instance
  (``tasks.agents.SimulatorModel``), a learned model through :class:`LearnedModel`
  (the HiP-MDP with a weight belief, or a baseline GP), and :class:`StepwiseModel`
  for a one-state-at-a-time function.
- :class:`SimulatedEpisodes`: ``N`` episodes on a model run at once, one batched
  ``predict`` per step, with the task's reward and termination applied to the
  predicted arrays (a :class:`PlanningTask`).
- :func:`plan`: Dyna-style planning (DESIGN §4): simulated Sarsa(λ) episodes started
  from states the real instance produced, updating the agent's weights.
- :func:`open_loop_errors`: a model's ``k``-step prediction errors along recorded
  episodes, what a planner on the model meets.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray
from tqdm.auto import tqdm

from hipmdp import sarsa
from hipmdp.data import (
    Transitions,
    check_angle_dims,
    check_integer,
    check_rng,
    is_integer,
    wrap_angle,
)
from hipmdp.fourier import FourierBasis
from hipmdp.sarsa import (
    SarsaConfig,
    SarsaState,
    SarsaStep,
    epsilon_greedy_batch,
    reset_traces,
    sarsa_update_batch,
)

Array = NDArray[np.float64]


@runtime_checkable
class DynamicsModel(Protocol):
    """A batched one-step dynamics model."""

    def predict(self, states: Array, actions: NDArray[np.int64]) -> Array:
        """Next states ``s'``, shape ``(N, D)``, for ``states`` ``(N, D)`` and integer
        ``actions`` ``(N,)``."""
        ...


def _check_batch(states: Array, actions: Any) -> tuple[Array, NDArray[np.int64]]:
    s = np.asarray(states, dtype=np.float64)
    a = np.asarray(actions)
    if s.ndim != 2:
        raise ValueError(f"states: expected shape (N, D), got {s.shape}")
    if a.shape != (s.shape[0],) or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(
            f"actions: expected integer shape ({s.shape[0]},), got {a.dtype} {a.shape}"
        )
    return s, a.astype(np.int64, copy=False)


def _state_dim(obj: Any) -> int | None:
    """``obj.state_dim`` if it is an integer (Python or numpy), else None."""
    d = getattr(obj, "state_dim", None)
    return int(d) if is_integer(d) else None


def _checked_next_states(next_states: Any, shape: tuple[int, ...]) -> Array:
    """A model's ``s'`` as floats, exactly ``shape`` ``(N, D)`` and finite; a
    ValueError naming ``model.predict`` otherwise (a ``(N,)`` prediction for
    one-dimensional states would broadcast to ``(N, N)``)."""
    s2 = np.asarray(next_states, dtype=np.float64)
    if s2.shape != shape:
        raise ValueError(
            f"model.predict: expected next states of shape {shape}, got shape "
            f"{s2.shape}"
        )
    if not np.all(np.isfinite(s2)):
        raise ValueError("model.predict: expected finite next states")
    return s2


@dataclass(frozen=True)
class LearnedModel:
    """Adapter from a model of ``Δ`` to a :class:`DynamicsModel`.

    ``s' = s + E[Δ | s, a]``, with the angle dimensions of ``s'`` wrapped to
    ``(−π, π]``.

    Args:
        model: anything with ``predict(states, actions, belief) -> (mean, var)``
            (the HiP-MDP) or ``predict(states, actions) -> (mean, var)`` (a
            baseline GP); ``mean`` is ``E[Δ]``, shape ``(N, D)``; ``var`` is unused.
            If the model also has ``predict_mean`` with the same arguments,
            returning ``E[Δ]`` only, that is called instead: planning needs no
            variance, and a GP's predictive variance costs ``O(n²)`` per state
            against ``O(n)`` for its mean. If it has ``mean_predictor(belief)``
            (or ``mean_predictor()`` without a belief), returning a callable
            ``(states, actions) -> E[Δ]`` equal to ``predict_mean``, that is built
            once here and called instead (the HiP-MDP's and the GP baselines'
            :class:`~hipmdp.kernels.KernelMeans`: planning calls the model with
            one state at a time, where per-call overhead dominates). A model and
            belief that do not fit together then fail here, not at ``predict``.
        belief: the weight belief passed to ``model.predict``, or ``None`` to call
            it without one. Planning "with the posterior-mean weights" is the
            HiP-MDP's ``predict`` with the current belief (its mean prediction).
            The adapter keeps this belief: after ``model.update``, build a new
            ``LearnedModel`` with the updated one.
        angle_dims: state dimensions that are angles; for a model that records
            the angles it was fitted with (``info["angle_dims"]``, as a fitted
            HiP-MDP does), the same ones, or a ValueError says they differ.
            ``None`` (the default): the model's recorded ones, or none for a
            model that records none. They are checked against ``D`` here when
            the model (or the mean predictor built from it) has a
            ``state_dim``, otherwise against the states given to ``predict``,
            before the model is called.
    """

    model: Any
    belief: Any = None
    angle_dims: tuple[int, ...] | None = None
    _mean: Callable[[Array, NDArray[np.int64]], Array] | None = field(
        init=False, repr=False, compare=False, default=None
    )

    def __post_init__(self) -> None:
        if not callable(getattr(self.model, "predict", None)):  # e.g. (belief, model)
            raise ValueError(
                f"model: expected a model of Δs with predict, got "
                f"{type(self.model).__name__} (LearnedModel(model, belief))"
            )
        d = _state_dim(self.model)
        object.__setattr__(self, "angle_dims", self._checked_angle_dims(d))
        if hasattr(self.model, "mean_predictor"):
            extra = () if self.belief is None else (self.belief,)
            try:
                inspect.signature(self.model.mean_predictor).bind(*extra)
            except TypeError:
                need = "takes no belief" if extra else "needs a belief, got None"
                raise ValueError(f"belief: the model's mean_predictor {need}") from None
            object.__setattr__(self, "_mean", self.model.mean_predictor(*extra))
            if d is None:  # the predictor may know D (a KernelMeans does)
                check_angle_dims(self.angle_dims, _state_dim(self._mean))

    def _checked_angle_dims(self, d: int | None) -> tuple[int, ...]:
        # a fitted HiP-MDP records the angles of its batch (hipmdp.fit): planning
        # must wrap the same ones
        info = getattr(self.model, "info", None)
        fitted = info.get("angle_dims") if isinstance(info, dict) else None
        dims = None if self.angle_dims is None else check_angle_dims(self.angle_dims, d)
        if fitted is not None:
            try:  # the model's own record, not the argument, when it is wrong
                fitted = check_angle_dims(fitted, d)
            except ValueError as error:
                raise ValueError(
                    "model: info['angle_dims'], the angles it records (and the "
                    "default of angle_dims): " + str(error).removeprefix("angle_dims: ")
                ) from None
        if dims is None:
            return () if fitted is None else fitted
        if fitted is not None and fitted != dims:
            raise ValueError(
                f"angle_dims: {dims} differs from the fitted model's {fitted}"
            )
        return dims

    def predict(self, states: Array, actions: NDArray[np.int64]) -> Array:
        """``s + E[Δ]`` with angles wrapped, shape ``(N, D)``. The model is given
        copies of the states and actions: one that writes into its arguments
        cannot move the planner's own."""
        s, a = _check_batch(states, actions)
        if self.angle_dims and max(self.angle_dims) >= s.shape[1]:
            # D was unknown when built: an IndexError when wrapping, after the model
            raise ValueError(
                f"angle_dims: expected indices in [0, {s.shape[1]}) (the states' "
                f"dimension D), got {self.angle_dims}"
            )
        args = (s.copy(), a.copy())
        if self.belief is not None:
            args = (*args, self.belief)
        if self._mean is not None:
            mean = self._mean(*args[:2])
        elif hasattr(self.model, "predict_mean"):
            mean = self.model.predict_mean(*args)
        else:
            mean, _ = self.model.predict(*args)
        mean = np.asarray(mean, dtype=np.float64)
        if mean.shape != s.shape:
            raise ValueError(
                f"model.predict: expected a mean of shape {s.shape}, got {mean.shape}"
            )
        next_states = s + mean
        if self.angle_dims:
            dims = list(self.angle_dims)
            next_states[:, dims] = wrap_angle(next_states[:, dims])
        return next_states


@dataclass(frozen=True)
class StepwiseModel:
    """A :class:`DynamicsModel` from ``step(state (D,), action) -> next_state (D,)``,
    applied row by row (for simulators that cannot batch)."""

    step: Callable[[Array, int], Array]

    def predict(self, states: Array, actions: NDArray[np.int64]) -> Array:
        """Row-by-row ``step``, shape ``(N, D)``; each ``step`` must return a finite
        next state of shape ``(D,)`` (a scalar or a ``(1,)`` return was broadcast
        over the row)."""
        s, a = _check_batch(states, actions)
        out = np.empty_like(s)
        for n in range(s.shape[0]):
            s2 = self.step(s[n], int(a[n]))
            # a tuple holding an array: numpy's error was "inhomogeneous shape"
            # (a tuple of numbers is a state)
            if isinstance(s2, tuple) and any(np.ndim(x) for x in s2):
                raise ValueError(
                    f"step: expected the next state alone, got a tuple of "
                    f"{len(s2)} for row {n} (a gym-style (state, reward, done, ...)? "
                    "the task's reward and terminal give those)"
                )
            s2 = np.asarray(s2, dtype=np.float64)
            if s2.shape != s.shape[1:]:
                raise ValueError(
                    f"step: expected a next state of shape (D,) = {s.shape[1:]}, got "
                    f"shape {s2.shape} for row {n} (action {a[n]})"
                )
            if not np.all(np.isfinite(s2)):
                raise ValueError(
                    f"step: expected a finite next state, got {s2} for row {n} "
                    f"(action {a[n]})"
                )
            out[n] = s2
        return out


@dataclass(frozen=True)
class PlanningTask:
    """What a task means on arrays of predicted states.

    Args:
        reward: ``reward(states, actions, next_states) -> r``, shape ``(N,)``.
        terminal: ``terminal(next_states) -> bool``, shape ``(N,)``: the episode ends
            without bootstrapping (goal reached, or failure).
        max_steps: episodes are cut (with bootstrapping) after this many steps.
    """

    reward: Callable[[Array, NDArray[np.int64], Array], Array]
    terminal: Callable[[Array], NDArray[np.bool_]]
    max_steps: int

    def __post_init__(self) -> None:
        # a wrong signature failed at the first planning step, in the planner's
        # frame, with Python's own "takes 1 positional argument but 3 were given"
        for name, args in (("reward", "(states, actions, next_states)"),
                           ("terminal", "(next_states)")):  # fmt: skip
            _check_callable(f"task.{name}", getattr(self, name), args)
        check_integer("max_steps", self.max_steps, 1)


def _check_callable(name: str, fn: Any, args: str) -> None:
    """A ValueError naming ``name`` unless ``fn`` is callable with the positional
    arguments ``args`` spells (``"(x, y)"``); a callable whose signature cannot
    be read (some builtins) passes."""
    if not callable(fn):
        raise ValueError(f"{name}: expected a function {args}, got {type(fn).__name__}")
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):
        return
    n = args.count(",") + 1
    try:
        signature.bind(*range(n))
    except TypeError:
        raise ValueError(
            f"{name}: expected a function {args}, got one with signature {signature}"
        ) from None


class StepResult(NamedTuple):
    """One lockstep step: ``next_states`` ``(N, D)``; ``rewards`` ``(N,)``;
    ``terminal`` ``(N,)``; ``truncated`` ``(N,)`` (the step limit was hit)."""

    next_states: Array
    rewards: Array
    terminal: NDArray[np.bool_]
    truncated: NDArray[np.bool_]


def _checked_rows(name: str, value: Any, n: int, kind: str) -> Array:
    """A task's answer for ``n`` rows: shape ``(n,)``, finite numbers (``kind``
    ``"f"``) or booleans (``"b"``; 0/1 integers too, as `Transitions` dones); a
    scalar reward was spread over every episode, and a float terminal of 0.5
    counted as reached."""
    out = np.asarray(value)
    if kind == "b" and out.dtype.kind in "iu" and np.isin(out, (0, 1)).all():
        out = out.astype(bool)
    ok = out.shape == (n,) and (
        out.dtype.kind == "b"
        if kind == "b"
        else out.dtype.kind in "iuf" and bool(np.all(np.isfinite(out)))
    )
    if not ok:
        what = "booleans (or 0/1)" if kind == "b" else "finite numbers"
        raise ValueError(
            f"{name}: expected {what} of shape ({n},), one per active episode, got "
            f"{out.dtype} {out.shape}"
        )
    return out


@dataclass
class SimulatedEpisodes:
    """``N`` episodes on a model, stepped at once with one batched ``predict``.

    Episodes that ended stay put (their rows are not sent to the model) until all
    have ended; ``active`` says which still run.

    Args:
        model: the dynamics model.
        task: reward, termination and step limit.
        start_states: ``s_0`` for each episode, shape ``(N, D)``.
    """

    model: DynamicsModel
    task: PlanningTask
    start_states: Array
    states: Array = field(init=False)
    steps: NDArray[np.int64] = field(init=False)
    returns: Array = field(init=False)
    active: NDArray[np.bool_] = field(init=False)
    reached: NDArray[np.bool_] = field(init=False)

    def __post_init__(self) -> None:
        s0 = np.array(self.start_states, dtype=np.float64)
        if s0.ndim != 2 or s0.shape[0] < 1:
            raise ValueError(
                f"start_states: expected shape (N >= 1, D), got {s0.shape}"
            )
        bad = np.argwhere(~np.isfinite(s0))
        if bad.size:
            raise ValueError(
                f"start_states: expected finite values, got {s0[tuple(bad[0])]} at "
                f"index {tuple(int(i) for i in bad[0])}"
            )
        self.states = s0
        self.steps = np.zeros(s0.shape[0], dtype=np.int64)
        self.returns = np.zeros(s0.shape[0])
        self.active = np.ones(s0.shape[0], dtype=bool)
        self.reached = np.zeros(s0.shape[0], dtype=bool)

    def step(self, actions: NDArray[np.int64]) -> StepResult:
        """Advance the active episodes by ``actions`` (integers, shape ``(N,)``;
        entries of ended episodes are ignored). Rows of ended episodes are returned
        unchanged with zero reward and ``terminal = truncated = False``."""
        n = self.states.shape[0]
        actions = np.asarray(actions)
        # one action per episode: with more the extra ones were dropped silently
        if actions.shape != (n,) or actions.dtype.kind not in "iu":
            raise ValueError(
                f"actions: expected integers of shape (N,) = ({n},), got "
                f"{actions.dtype} {actions.shape}"
            )
        idx = np.flatnonzero(self.active)
        next_states = self.states.copy()
        rewards = np.zeros(n)
        terminal = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        if idx.size:
            s, a = self.states[idx], actions[idx]
            s2 = _checked_next_states(self.model.predict(s, a), s.shape)
            next_states[idx] = s2
            rewards[idx] = _checked_rows(
                "task.reward", self.task.reward(s, a, s2), len(idx), "f"
            )
            terminal[idx] = _checked_rows(
                "task.terminal", self.task.terminal(s2), len(idx), "b"
            )
            self.steps[idx] += 1
            truncated[idx] = ~terminal[idx] & (self.steps[idx] >= self.task.max_steps)
            self.returns[idx] += rewards[idx]
            self.reached[idx] = terminal[idx]
            self.active[idx] = ~(terminal[idx] | truncated[idx])
        self.states = next_states
        return StepResult(next_states, rewards, terminal, truncated)


class PlanResult(NamedTuple):
    """Planning output: the agent ``state`` (weights updated, traces zero, shape
    ``(A, F)``); per simulated episode the ``steps`` ``(E,)``, ``returns`` ``(E,)`` and
    whether a terminal state was ``reached`` ``(E,)``."""

    state: SarsaState
    steps: NDArray[np.int64]
    returns: Array
    reached: NDArray[np.bool_]


def _update_checked_once(state: SarsaState, *args) -> SarsaStep:
    """:func:`hipmdp.sarsa.sarsa_update_batch` without its checks, for the steps
    of :func:`run_sarsa_episodes` after the first."""
    return sarsa._update_batch(state.weights, state.traces, *args)


def run_sarsa_episodes(
    state: SarsaState,
    basis: FourierBasis,
    config: SarsaConfig,
    episodes: SimulatedEpisodes,
    *,
    rng: np.random.Generator,
    learn: bool = True,
) -> SarsaState:
    """Run lockstep episodes to their end with ε-greedy Sarsa(λ) (shared ``θ``).

    Each step: ``a = ε-greedy(θ φ(s))`` for every episode, one batched model step,
    then :func:`hipmdp.sarsa.sarsa_update_batch` (skipped when ``learn`` is false).

    Returns:
        The agent state with traces reset to zero, ``θ`` shape ``(A, F)``.
    """
    n = episodes.states.shape[0]
    step_sizes = config.alpha * basis.step_scale
    state = reset_traces(state, n)
    phi = basis(episodes.states)
    actions = epsilon_greedy_batch(phi @ state.weights.T, config.epsilon, rng=rng)
    # the first update checks its inputs (sarsa_update_batch); later steps have
    # the same shapes and kinds by construction, and the checks would cost as
    # much as the update itself (F = 1296, N = 1)
    update = sarsa_update_batch
    while episodes.active.any():
        active = episodes.active.copy()
        result = episodes.step(actions)
        phi_next = basis(result.next_states)
        actions_next = epsilon_greedy_batch(
            phi_next @ state.weights.T, config.epsilon, rng=rng
        )
        if learn:
            state = update(
                state, phi, actions, result.rewards, phi_next, actions_next,
                result.terminal, active, step_sizes, config,
            ).state  # fmt: skip
            update = _update_checked_once
        phi, actions = phi_next, actions_next
    return SarsaState(state.weights, np.zeros_like(state.weights))


def plan(
    state: SarsaState,
    basis: FourierBasis,
    config: SarsaConfig,
    model: DynamicsModel,
    task: PlanningTask,
    start_states: Array,
    n_episodes: int,
    *,
    rng: np.random.Generator,
    n_parallel: int = 1,
    progress: bool = False,
) -> PlanResult:
    """Dyna-style planning: ``n_episodes`` simulated Sarsa(λ) episodes on ``model``.

    Each episode starts from a row of ``start_states`` drawn uniformly at random
    (states the real instance produced, e.g. its episodes' initial states).
    Episodes run in groups of ``n_parallel`` in lockstep (one batched ``predict``
    per step for the whole group, one averaged update of the shared ``θ``, see
    :func:`hipmdp.sarsa.sarsa_update_batch`); with ``n_parallel = 1`` (the default,
    and the paper's protocol) this is plain sequential Sarsa(λ) on the model.

    Args:
        state: the agent, ``θ`` shape ``(A, F)``.
        basis: the Fourier basis ``φ``.
        config: Sarsa(λ) hyperparameters (ε, α, λ, γ).
        model: the dynamics model (``predict(states, actions) -> next_states``).
        task: reward and termination on predicted arrays, and the step limit.
        start_states: candidate initial states, shape ``(M, D)``.
        n_episodes: ``E``, the number of simulated episodes.
        rng: random stream for start states and exploration.
        n_parallel: episodes per lockstep group.
        progress: show a progress bar over episodes.

    Returns:
        :class:`PlanResult` with the updated agent and per-episode statistics.
    """
    _check_plan_arguments(state, basis, config, model, task)
    check_rng(rng)
    s0 = np.asarray(start_states, dtype=np.float64)
    if s0.ndim != 2 or s0.shape[0] < 1 or s0.shape[1] != basis.state_dim:
        raise ValueError(
            f"start_states: expected shape (M >= 1, {basis.state_dim}), got {s0.shape}"
        )
    check_integer("n_episodes", n_episodes, 0)
    check_integer("n_parallel", n_parallel, 1)
    if state.weights.shape[1] != basis.n_features:
        raise ValueError(
            f"state.weights: expected {basis.n_features} features, "
            f"got shape {state.weights.shape}"
        )
    steps: list[Sequence[int]] = []
    returns: list[Sequence[float]] = []
    reached: list[Sequence[bool]] = []
    with tqdm(
        total=n_episodes, desc="planning", unit="ep", disable=not progress
    ) as bar:
        done = 0
        while done < n_episodes:
            group = min(n_parallel, n_episodes - done)
            starts = s0[rng.integers(s0.shape[0], size=group)]
            episodes = SimulatedEpisodes(model, task, starts)
            state = run_sarsa_episodes(state, basis, config, episodes, rng=rng)
            steps.append(episodes.steps.tolist())
            returns.append(episodes.returns.tolist())
            reached.append(episodes.reached.tolist())
            done += group
            bar.update(group)
    return PlanResult(
        reset_traces(state),  # zero also after no episodes (the caller's were stale)
        np.array(sum(steps, []), dtype=np.int64),
        np.array(sum(returns, []), dtype=np.float64),
        np.array(sum(reached, []), dtype=bool),
    )


def _check_plan_arguments(
    state: Any, basis: Any, config: Any, model: Any, task: Any
) -> None:
    """A ValueError naming the argument of :func:`plan` that is not of its kind
    (passed in another order, they failed as AttributeErrors deep in the loop),
    and for a model whose ``predict`` needs a belief (a bare HiP-MDP) or whose
    action count differs from the agent's, or state dimension from the basis's."""
    for name, value, kind in (
        ("state", state, SarsaState), ("basis", basis, FourierBasis),
        ("config", config, SarsaConfig), ("task", task, PlanningTask),
    ):  # fmt: skip
        if not isinstance(value, kind):
            raise ValueError(
                f"{name}: expected a {kind.__name__}, got {type(value).__name__}"
            )
    predict = getattr(model, "predict", None)
    if not callable(predict):
        raise ValueError(
            f"model: expected a DynamicsModel, with predict(states, actions), got "
            f"{type(model).__name__}"
        )
    try:
        inspect.signature(predict).bind(0, 0)
    except TypeError:
        raise ValueError(
            f"model: {type(model).__name__}.predict does not take (states, "
            "actions); wrap a model of Δs that needs a belief as "
            "hipmdp.LearnedModel(model, belief)"
        ) from None
    except ValueError:  # a signature that cannot be read
        pass
    inner = model.model if isinstance(model, LearnedModel) else model
    n_actions = getattr(inner, "n_actions", None)
    if is_integer(n_actions) and n_actions != state.weights.shape[0]:
        raise ValueError(
            f"state.weights: the agent has {state.weights.shape[0]} actions, the "
            f"model {int(n_actions)}"
        )
    d = _state_dim(inner)
    if d is not None and d != basis.state_dim:
        raise ValueError(
            f"basis: expected a basis over the model's {d} state dimensions, got "
            f"one over {basis.state_dim}"
        )


def open_loop_errors(
    model: DynamicsModel, data: Transitions, horizons: Sequence[int]
) -> dict[int, Array]:
    """``k``-step open-loop prediction errors of ``model`` along recorded episodes.

    For every start ``t`` whose next ``k`` transitions belong to one episode, the
    model is rolled ``k`` steps from the recorded ``s_t`` with the recorded actions
    ``a_t … a_{t+k-1}`` (its own predictions fed back), and compared with the
    recorded ``s_{t+k}``. One-step errors (``k = 1``) say how well a model fits;
    longer horizons say how its errors compound, which is what a planner on it
    meets.

    Args:
        model: the dynamics model (``predict(states, actions) -> next_states``).
        data: transitions in time order, episodes ending where ``dones`` is true
            (all one episode if ``dones`` is None); within an episode each
            transition must start where the previous one ended.
        horizons: the ``k`` values, each an integer ``>= 1``.

    Returns:
        ``{k: ŝ_{t+k} − s_{t+k}}``, shape ``(n_k, D)`` for the ``n_k`` starts, with
        ``data.angle_dims`` wrapped to ``(−π, π]``.
    """
    try:
        ks = list(horizons)
    except TypeError:
        raise ValueError(
            f"horizons: expected a sequence of integers >= 1, got {horizons!r}"
        ) from None
    if not ks:
        raise ValueError("horizons: expected at least one integer >= 1, got none")
    for i, k in enumerate(ks):  # int(k) made 1.5 a 1 and "12" the horizons 1, 2
        check_integer(f"horizons[{i}]", k, 1)
    ks = [int(k) for k in ks]
    n = len(data)
    ends = np.zeros(n, dtype=bool) if data.dones is None else data.dones.astype(bool)
    # within an episode, transition j + 1 must start at transition j's next state
    inside = ~ends[:-1]
    gap = data.next_states[:-1][inside] - data.states[1:][inside]
    if data.angle_dims:
        gap[:, list(data.angle_dims)] = wrap_angle(gap[:, list(data.angle_dims)])
    if gap.size and np.max(np.abs(gap)) > 1e-9:
        raise ValueError(
            "data: expected transitions in time order (each starting where the "
            "previous one ended, episodes ending at dones)"
        )
    episode = np.concatenate([[0], np.cumsum(ends[:-1])])
    out = {}
    for k in ks:
        starts = np.flatnonzero(
            (np.arange(n) + k <= n)
            & (episode == episode[np.minimum(np.arange(n) + k - 1, n - 1)])
        )
        s = data.states[starts]
        shape = s.shape
        for j in range(k):
            s = _checked_next_states(model.predict(s, data.actions[starts + j]), shape)
        err = s - data.next_states[starts + k - 1]
        if data.angle_dims:
            dims = list(data.angle_dims)
            err[:, dims] = wrap_angle(err[:, dims])
        out[k] = err
    return out
