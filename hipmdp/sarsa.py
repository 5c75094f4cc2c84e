"""Sarsa(λ) with linear function approximation and ε-greedy action selection.

Sutton & Barto (1998), §8.4 (gradient-descent Sarsa(λ)), with the per-feature step
sizes of the Fourier basis (Konidaris et al. 2011). Symbols:

- ``A`` discrete actions, ``F`` features, ``φ(s)`` the feature vector (shape ``(F,)``).
- ``θ``: one weight vector per action, ``weights`` of shape ``(A, F)``;
  ``Q(s, a) = θ_a · φ(s)``.
- ``e``: eligibility traces, ``traces`` of shape ``(A, F)`` (one episode) or
  ``(N, A, F)`` (``N`` episodes run in lockstep, see :func:`sarsa_update_batch`).
- ``α_i``: per-feature step sizes, ``step_sizes`` of shape ``(F,)`` (for a Fourier
  basis ``α_i = α / ‖c_i‖``, i.e. ``config.alpha * basis.step_scale``).

One update, for the transition ``(s, a, r, s', a')``::

    δ = r + γ Q(s', a') − Q(s, a)          (δ = r − Q(s, a) if s' is terminal)
    e ← γλ e;  e_a ← φ(s) + e_a  (accumulating)  or  e_a ← repl(e_a, φ(s))  (replacing)
    θ ← θ + δ (α ⊙ e)

``repl`` generalises replacing traces (Singh & Sutton 1996) to features in [-1, 1]:
each entry takes ``φ_i`` where ``|φ_i| > |e_{a,i}|`` and keeps ``e_{a,i}`` elsewhere,
so ``|e| ≤ 1`` always; for binary features it is the classic ``e_{a,i} ← 1``. Other
actions' traces are only decayed, not cleared (with a dense basis every feature is
active in every state, so clearing would cut all credit for the other actions).

Everything is explicit state: :class:`SarsaState` in, a new :class:`SarsaState` out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from hipmdp.data import check_integer, is_integer, is_real_number

Array = NDArray[np.float64]
TraceKind = Literal["replacing", "accumulating"]


_DIVERGED = (
    "Sarsa(λ) diverged: a non-finite TD error (a non-finite reward or weight; "
    "a smaller step size α may help)"
)


def _is_index(value: object, n: int) -> bool:
    """An integer (Python or numpy, not a bool, not a float) in ``[0, n)``."""
    return is_integer(value) and 0 <= value < n


def _shaped(name: str, value: object, shape: tuple[int, ...], symbols: str) -> Array:
    """``value`` as an array of exactly ``shape`` (``symbols`` spells it, e.g.
    ``"(N, F)"``), or a ValueError naming ``name``: broadcasting would silently
    apply one episode's trace or reward to all of them."""
    out = np.asarray(value)
    if out.shape != shape:
        raise ValueError(f"{name}: expected shape {symbols} = {shape}, got {out.shape}")
    return out


def _check_step_sizes(step_sizes: object, n_features: int) -> Array:
    """``α_i`` of shape ``(F,)``, each ``>= 0`` (one ``O(F)`` scan, cheaper than the
    ``O(A F)`` update; NaN fails it too)."""
    alphas = _shaped("step_sizes", step_sizes, (n_features,), "(F,)")
    if not alphas.min() >= 0.0:
        raise ValueError(
            f"step_sizes: expected entries >= 0, got a minimum of {alphas.min()}"
        )
    return alphas


def _check_epsilon(epsilon: object) -> None:
    """ε, a number (not a bool) in ``[0, 1]``; a ValueError naming it otherwise."""
    if not (is_real_number(epsilon) and 0.0 <= epsilon <= 1.0):
        raise ValueError(f"epsilon: expected a number in [0, 1], got {epsilon!r}")


@dataclass(frozen=True)
class SarsaConfig:
    """Hyperparameters of Sarsa(λ).

    ========== ===================================================== ==========
    name       meaning                                               valid
    ========== ===================================================== ==========
    alpha      base step size α (scaled per feature by the basis)    (0, 1]
    lam        trace decay λ                                         [0, 1]
    gamma      discount γ                                            [0, 1]
    epsilon    exploration rate ε of the ε-greedy policy             [0, 1]
    traces     ``"replacing"`` or ``"accumulating"``
    ========== ===================================================== ==========
    """

    alpha: float = 0.001
    lam: float = 0.9
    gamma: float = 1.0
    epsilon: float = 0.0
    traces: TraceKind = "accumulating"

    def __post_init__(self) -> None:
        if not (is_real_number(self.alpha) and 0.0 < self.alpha <= 1.0):
            raise ValueError(
                f"alpha: expected a number with 0 < alpha <= 1, got {self.alpha!r}"
            )
        for name in ("lam", "gamma", "epsilon"):
            value = getattr(self, name)
            if not (is_real_number(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"{name}: expected a number in [0, 1], got {value!r}")
        if self.traces not in ("replacing", "accumulating"):
            raise ValueError(
                f"traces: expected 'replacing' or 'accumulating', got {self.traces!r}"
            )


class SarsaState(NamedTuple):
    """Learner state: ``weights`` θ, shape ``(A, F)``; ``traces`` e, shape ``(A, F)``
    for one episode or ``(N, A, F)`` for ``N`` episodes in lockstep."""

    weights: Array
    traces: Array


class SarsaStep(NamedTuple):
    """Result of one update: the new ``state`` and the TD error ``td_error`` δ
    (a float, or shape ``(N,)`` for a batch)."""

    state: SarsaState
    td_error: float | Array


def init_state(
    n_actions: int, n_features: int, initial_value: float = 0.0
) -> SarsaState:
    """Initial weights and zero traces, shapes ``(A, F)``.

    ``θ_{a,0} = q₀`` (``initial_value``) and every other weight zero, so with a
    constant feature ``φ_0 ≡ 1`` (a Fourier basis's ``c_0 = 0``) ``Q(s, a) = q₀``
    everywhere. An optimistic ``q₀`` (above every achievable return) makes a greedy
    agent try every action (Sutton & Barto 1998, §2.7): ``q₀ = 0`` is optimistic
    for rewards ≤ 0 (the acrobot's −1 per step); for the cart-pole's +1 per step it
    is ``1 / (1 − γ)``.
    """
    check_integer("n_actions", n_actions, 1)
    check_integer("n_features", n_features, 1)
    if not (is_real_number(initial_value) and np.isfinite(initial_value)):
        raise ValueError(
            f"initial_value: expected a finite number, got {initial_value!r}"
        )
    weights = np.zeros((n_actions, n_features))
    weights[:, 0] = initial_value
    return SarsaState(weights, np.zeros((n_actions, n_features)))


def reset_traces(state: SarsaState, n_episodes: int | None = None) -> SarsaState:
    """Zero traces at the start of an episode: shape ``(A, F)``, or
    ``(n_episodes, A, F)`` for lockstep episodes."""
    shape = state.weights.shape
    if n_episodes is not None:
        check_integer("n_episodes", n_episodes, 1)
        shape = (n_episodes, *shape)
    return SarsaState(state.weights, np.zeros(shape))


def q_values(weights: Array, phi: Array) -> Array:
    """``Q(s, ·) = θ φ(s)``: shape ``(A,)`` for ``phi`` of shape ``(F,)``, or
    ``(N, A)`` for ``phi`` of shape ``(N, F)``."""
    return phi @ weights.T


def epsilon_greedy(q: Array, epsilon: float, *, rng: np.random.Generator) -> int:
    """ε-greedy choice from action values ``q`` (shape ``(A,)``).

    With probability ε a uniformly random action, otherwise a greedy one with ties
    broken uniformly at random (with zero initial weights every action ties, and a
    fixed tie-break would never explore).
    """
    _check_epsilon(epsilon)
    q = np.asarray(q)
    if q.ndim != 1 or q.size == 0:
        raise ValueError(f"q: expected shape (A,) with A >= 1, got {q.shape}")
    if epsilon > 0.0 and rng.random() < epsilon:
        return int(rng.integers(q.shape[0]))
    best = np.flatnonzero(q == q.max())
    return int(best[0] if best.size == 1 else rng.choice(best))


def epsilon_greedy_batch(
    q: Array, epsilon: float, *, rng: np.random.Generator
) -> NDArray[np.int64]:
    """Row-wise ε-greedy choices from ``q`` (shape ``(N, A)``), shape ``(N,)``;
    ties among maximal actions broken uniformly at random."""
    _check_epsilon(epsilon)
    q = np.asarray(q)
    if q.ndim != 2 or q.shape[1] == 0:
        raise ValueError(f"q: expected shape (N, A) with A >= 1, got {q.shape}")
    n, n_actions = q.shape
    # A random key below the smallest gap breaks ties at random without moving the
    # argmax between actions whose values differ.
    is_max = q == q.max(axis=1, keepdims=True)
    actions = np.argmax(is_max * (1.0 + rng.random((n, n_actions))), axis=1)
    if epsilon > 0.0:
        explore = rng.random(n) < epsilon
        actions[explore] = rng.integers(n_actions, size=int(explore.sum()))
    return actions


def _check_weights(weights: Array) -> tuple[int, int]:
    """``(A, F)`` of ``θ``; a ValueError unless it is a 2-D array."""
    if weights.ndim != 2:
        raise ValueError(f"state.weights: expected shape (A, F), got {weights.shape}")
    return weights.shape


def _check_indices(name: str, a: object, n: int, n_actions: int) -> NDArray[np.int64]:
    """Action indices ``a``, shape ``(N,)``, of an integer dtype, in ``[0, A)``."""
    a = _shaped(name, a, (n,), "(N,)")
    if a.dtype.kind not in "iu":
        raise ValueError(f"{name}: expected integer indices, got dtype {a.dtype}")
    if a.min() < 0 or a.max() >= n_actions:
        raise ValueError(
            f"{name}: expected indices in [0, {n_actions}), got values from "
            f"{a.min()} to {a.max()}"
        )
    return a


def sarsa_update(
    state: SarsaState,
    phi: Array,
    action: int,
    reward: float,
    phi_next: Array | None,
    action_next: int | None,
    step_sizes: Array,
    config: SarsaConfig,
) -> SarsaStep:
    """One Sarsa(λ) update for ``(s, a, r, s', a')`` (equations in the module doc).

    Args:
        state: ``θ`` of shape ``(A, F)`` and ``e`` of shape ``(A, F)``.
        phi: ``φ(s)``, shape ``(F,)``.
        action: ``a``.
        reward: ``r``.
        phi_next: ``φ(s')``, shape ``(F,)``, or ``None`` if ``s'`` is terminal.
        action_next: ``a'`` (ignored when ``s'`` is terminal).
        step_sizes: ``α_i``, shape ``(F,)``.
        config: ``γ``, ``λ`` and the trace kind.
    """
    weights, traces = state
    n_actions, n_features = _check_weights(weights)
    traces = _shaped("state.traces", traces, (n_actions, n_features), "(A, F)")
    phi = _shaped("phi", phi, (n_features,), "(F,)")
    step_sizes = _check_step_sizes(step_sizes, n_features)
    if not _is_index(action, n_actions):
        raise ValueError(
            f"action: expected an integer index in [0, {n_actions}), got {action!r}"
        )
    if not is_real_number(reward):
        raise ValueError(f"reward: expected a real number, got {reward!r}")
    if phi_next is not None:
        phi_next = _shaped("phi_next", phi_next, (n_features,), "(F,)")
        if not _is_index(action_next, n_actions):
            raise ValueError(
                f"action_next: expected an integer index in [0, {n_actions}) when "
                f"phi_next is given (s' not terminal), got {action_next!r}"
            )
    return _update(
        weights, traces, phi, action, reward, phi_next, action_next, step_sizes, config
    )


def _update(
    weights: Array,
    traces: Array,
    phi: Array,
    action: int,
    reward: float,
    phi_next: Array | None,
    action_next: int | None,
    step_sizes: Array,
    config: SarsaConfig,
) -> SarsaStep:
    """:func:`sarsa_update` on checked inputs (its loops check once, not per
    step: the checks cost as much as the update at F = 1296)."""
    target = reward
    if phi_next is not None:
        target += config.gamma * float(weights[action_next] @ phi_next)
    delta = target - float(weights[action] @ phi)
    if not math.isfinite(delta):
        raise ValueError(_DIVERGED)
    traces = traces * (config.gamma * config.lam)
    if config.traces == "accumulating":
        traces[action] += phi
    else:
        row = traces[action]
        traces[action] = np.where(np.abs(phi) > np.abs(row), phi, row)
    weights = weights + delta * (step_sizes * traces)
    return SarsaStep(SarsaState(weights, traces), delta)


def sarsa_update_batch(
    state: SarsaState,
    phi: Array,
    actions: NDArray[np.int64],
    rewards: Array,
    phi_next: Array,
    actions_next: NDArray[np.int64],
    terminal: NDArray[np.bool_],
    active: NDArray[np.bool_],
    step_sizes: Array,
    config: SarsaConfig,
) -> SarsaStep:
    """One lockstep Sarsa(λ) update for ``N`` episodes sharing one ``θ``.

    Each episode ``j`` keeps its own trace ``e_j`` (shape ``(A, F)``); every ``δ_j``
    is computed with the same ``θ`` and the step is the mean over the ``n_active``
    running episodes::

        θ ← θ + (1 / n_active) Σ_j δ_j (α ⊙ e_j)      over active episodes j

    With ``N = 1`` this is exactly :func:`sarsa_update`. With ``N > 1`` it is a
    synchronous mini-batch step: averaging (not summing) keeps it stable when the
    episodes are alike (``N`` identical episodes would otherwise take an ``N``-times
    larger step), at the price that ``N`` lockstep episodes move ``θ`` about as far
    as one sequential episode, with less variance.

    Args:
        state: ``θ`` of shape ``(A, F)`` and ``e`` of shape ``(N, A, F)``.
        phi: ``φ(s_j)``, shape ``(N, F)``.
        actions: ``a_j``, shape ``(N,)``.
        rewards: ``r_j``, shape ``(N,)``.
        phi_next: ``φ(s'_j)``, shape ``(N, F)`` (rows of terminal ``s'`` ignored).
        actions_next: ``a'_j``, shape ``(N,)``.
        terminal: ``s'_j`` terminal (no bootstrap), shape ``(N,)``.
        active: episodes still running (others leave ``θ`` and their trace alone),
            shape ``(N,)``.
        step_sizes: ``α_i``, shape ``(F,)``.
        config: ``γ``, ``λ`` and the trace kind.

    Returns:
        The new state and ``δ``, shape ``(N,)`` (zero for inactive episodes).
    """
    weights, traces = state
    n_actions, n_features = _check_weights(weights)
    traces = np.asarray(traces)
    af = (n_actions, n_features)
    if traces.ndim != 3 or traces.shape[0] == 0 or traces.shape[1:] != af:
        raise ValueError(
            f"state.traces: expected shape (N >= 1, A, F) with (A, F) = {af} (the "
            f"weights'), got {traces.shape}"
        )
    n = traces.shape[0]
    phi = _shaped("phi", phi, (n, n_features), "(N, F)")
    phi_next = _shaped("phi_next", phi_next, (n, n_features), "(N, F)")
    rewards = _shaped("rewards", rewards, (n,), "(N,)")
    terminal = _shaped("terminal", terminal, (n,), "(N,)")
    active = _shaped("active", active, (n,), "(N,)")
    for name, flags in (("terminal", terminal), ("active", active)):
        if flags.dtype != bool:  # a float 0.5 counted as True
            raise ValueError(f"{name}: expected booleans, got dtype {flags.dtype}")
    step_sizes = _check_step_sizes(step_sizes, n_features)
    actions = _check_indices("actions", actions, n, n_actions)
    actions_next = _check_indices("actions_next", actions_next, n, n_actions)
    return _update_batch(
        weights, traces, phi, actions, rewards, phi_next, actions_next, terminal,
        active, step_sizes, config,
    )  # fmt: skip


def _update_batch(
    weights: Array,
    traces: Array,
    phi: Array,
    actions: NDArray[np.int64],
    rewards: Array,
    phi_next: Array,
    actions_next: NDArray[np.int64],
    terminal: NDArray[np.bool_],
    active: NDArray[np.bool_],
    step_sizes: Array,
    config: SarsaConfig,
) -> SarsaStep:
    """:func:`sarsa_update_batch` on checked inputs (``hipmdp.planning``'s loop
    checks its first step's, whose shapes and kinds the later steps keep)."""
    n = traces.shape[0]
    if n == 1:  # one episode: the cheaper single update, same numbers
        if not active[0]:
            return SarsaStep(SarsaState(weights, traces), np.zeros(1))
        one = _update(
            weights, traces[0], phi[0], int(actions[0]), float(rewards[0]),
            None if terminal[0] else phi_next[0], int(actions_next[0]), step_sizes,
            config,
        )  # fmt: skip
        return SarsaStep(
            SarsaState(one.state.weights, one.state.traces[None]),
            np.array([one.td_error]),
        )
    rows = np.arange(n)
    q = np.einsum("nf,nf->n", weights[actions], phi)
    q_next = np.einsum("nf,nf->n", weights[actions_next], phi_next)
    delta = rewards + np.where(terminal, 0.0, config.gamma * q_next) - q
    delta = np.where(active, delta, 0.0)
    if not np.all(np.isfinite(delta)):
        raise ValueError(_DIVERGED)
    decay = np.where(active, config.gamma * config.lam, 1.0)
    traces = traces * decay[:, None, None]
    taken = traces[rows, actions]  # (N, F) traces of the actions taken
    if config.traces == "accumulating":
        new_rows = taken + phi
    else:
        new_rows = np.where(np.abs(phi) > np.abs(taken), phi, taken)
    traces[rows, actions] = np.where(active[:, None], new_rows, taken)
    n_active = max(int(np.count_nonzero(active)), 1)
    weights = weights + step_sizes * np.einsum("n,naf->af", delta / n_active, traces)
    return SarsaStep(SarsaState(weights, traces), delta)
