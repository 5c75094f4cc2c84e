"""Your own method in the one-step prediction benchmark.

Both prediction tables (``tasks.cartpole_prediction`` and the one of
``tasks.acrobot_swingup``) score, beside the HiP-MDP and the three GP baselines, any
method named with ``--method NAME=module:attribute``. It sees exactly what the
HiP-MDP sees, on the same test settings and the same train/test splits, and its
scores go into every table and into ``metrics.json`` under ``NAME``.

A method is an object with two methods (``attribute`` is a class or a function
that takes no arguments and returns one):

- ``fit(batch, *, rng)``: called once, on the batch data of the training
  instances (a ``hipmdp.Transitions`` whose ``instances`` tell them apart).
- ``predict(train, states, actions, *, rng) -> (mean, var)``: called once per
  test setting. ``train`` holds the setting's train transitions (the ones the
  HiP-MDP filters its belief on); ``states`` (n, D) and ``actions`` (n,) are the
  held-out test transitions' inputs. It returns the Gaussian predictive mean
  and variance of ``Δs = s' - s``, each shape (n, D), the variance > 0. Angle
  changes are measured as ``Transitions.deltas`` measures them.

Each call gets its own ``rng``, spawned from the run's seed and the method's name
only (:func:`method_seed`): adding or removing a method changes no other
method's numbers, and the same seed gives the same scores. :class:`BayesianLinear`
is a complete example.

Symbols: ``a`` action, ``d`` state dimension, ``x`` features of a state.
"""

from __future__ import annotations

import importlib
import re
import zlib
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from hipmdp.data import Transitions
from tasks.prediction import PREDICTION_METHODS

Array = np.ndarray

#: The methods every prediction table has; an added method may not take these names.
BUILT_IN = PREDICTION_METHODS
#: First spawn key of the added methods' streams (the runs' own streams are the
#: seed's children 0, 1, ..., so these never coincide with them).
METHOD_STREAM = 1000
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


class MethodSpec(NamedTuple):
    """``--method NAME=module:attribute``, parsed."""

    name: str
    module: str
    attribute: str


def parse_spec(spec: Any) -> MethodSpec:
    """Split ``"NAME=module:attribute"``; raise ValueError naming what is wrong."""
    if not isinstance(spec, str):
        raise ValueError(
            f"methods: expected strings NAME=module:attribute, got {spec!r}"
        )
    name, eq, target = spec.partition("=")
    module, colon, attribute = target.partition(":")
    if not (eq and colon and module and attribute):
        raise ValueError(f"methods: expected NAME=module:attribute, got {spec!r}")
    if not _NAME.fullmatch(name):
        raise ValueError(
            f"methods: the name {name!r} in {spec!r} must start with a letter or "
            "digit and hold only letters, digits, '_', '.' and '-'"
        )
    return MethodSpec(name, module, attribute)


def check_specs(specs: Any) -> tuple[MethodSpec, ...]:
    """Parse every spec and check that the names are new and distinct (no import:
    :func:`load` does that)."""
    if isinstance(specs, str) or not isinstance(specs, Sequence):
        raise ValueError(
            f"methods: expected a sequence of NAME=module:attribute, got {specs!r}"
        )
    parsed = tuple(parse_spec(s) for s in specs)
    names = [p.name for p in parsed]
    for p in parsed:
        if p.name in BUILT_IN:
            raise ValueError(
                f"methods: {p.name!r} is a built-in method; choose another name"
            )
        if names.count(p.name) > 1:
            raise ValueError(f"methods: the name {p.name!r} is given twice")
    return parsed


def load(spec: MethodSpec) -> Any:
    """Import ``spec.module``, call ``spec.attribute`` with no arguments, and check
    that the result has ``fit`` and ``predict``; raise ValueError if not."""
    where = f"methods: {spec.name}={spec.module}:{spec.attribute}"
    try:
        module = importlib.import_module(spec.module)
    except ImportError as err:
        raise ValueError(f"{where}: cannot import {spec.module!r} ({err})") from None
    factory = getattr(module, spec.attribute, None)
    if not callable(factory):
        raise ValueError(
            f"{where}: {spec.module!r} has no class or function {spec.attribute!r}"
        )
    try:
        method = factory()
    except Exception as err:  # the user's code: say which call failed, keep the cause
        raise ValueError(
            f"{where}: calling {spec.attribute}() with no arguments raised "
            f"{type(err).__name__}: {err}"
        ) from err
    missing = [m for m in ("fit", "predict") if not callable(getattr(method, m, None))]
    if missing:
        raise ValueError(
            f"{where}: expected an object with fit and predict methods, "
            f"{type(method).__name__} has no {' or '.join(missing)}"
        )
    return method


def method_seed(seed: int, name: str, *key: int) -> np.random.SeedSequence:
    """The stream of method ``name`` in a run with seed ``seed``: the seed's
    descendant with spawn key ``(METHOD_STREAM, crc32(name), *key)``. ``fit`` gets
    key ``(0,)``; ``predict`` on setting ``i`` of prediction table ``g`` gets
    ``(1, g, i)``."""
    crc = zlib.crc32(name.encode())
    return np.random.SeedSequence(seed, spawn_key=(METHOD_STREAM, crc, *key))


class Added(NamedTuple):
    """A fitted added method of a run: its spec, the object and the run's seed."""

    spec: MethodSpec
    method: Any
    seed: int

    @property
    def name(self) -> str:
        return self.spec.name

    def predict(
        self, train: Transitions, test: Transitions, key: tuple[int, ...]
    ) -> tuple[Array, Array]:
        """The method's (mean, var) of Δs on ``test``, checked: shapes (n, D),
        finite, var > 0. ``key``: (table, setting), as :func:`method_seed` says."""
        rng = np.random.default_rng(method_seed(self.seed, self.name, 1, *key))
        out = self.method.predict(train, test.states, test.actions, rng=rng)
        if not (isinstance(out, tuple) and len(out) == 2):
            raise ValueError(
                f"method {self.name}: predict must return (mean, var), got "
                f"{type(out).__name__}"
            )
        shape = test.states.shape
        mean, var = (np.asarray(x, dtype=float) for x in out)
        for label, x in (("mean", mean), ("var", var)):
            if x.shape != shape:
                raise ValueError(
                    f"method {self.name}: predict's {label} has shape {x.shape}, "
                    f"expected {shape}"
                )
            if not np.all(np.isfinite(x)):
                raise ValueError(f"method {self.name}: predict's {label} is not finite")
        if not np.all(var > 0):
            raise ValueError(f"method {self.name}: predict's var must be > 0")
        return mean, var


def load_all(specs: Sequence[str]) -> tuple[tuple[MethodSpec, Any], ...]:
    """``(spec, object)`` of every ``NAME=module:attribute`` of ``specs``; raise
    ValueError if any is malformed or cannot be loaded (:func:`load`). Experiments
    call it before any work."""
    return tuple((spec, load(spec)) for spec in check_specs(specs))


def fit_all(
    loaded: Sequence[tuple[MethodSpec, Any]], batch: Transitions, seed: int
) -> tuple[Added, ...]:
    """Fit every loaded method (:func:`load_all`) on ``batch``, each with its own
    stream (:func:`method_seed`)."""
    out = []
    for spec, method in loaded:
        rng = np.random.default_rng(method_seed(seed, spec.name, 0))
        method.fit(batch, rng=rng)
        out.append(Added(spec, method, seed))
    return tuple(out)


def add_method_argument(parser) -> None:
    """The prediction experiments' repeatable ``--method NAME=module:attribute``."""
    parser.add_argument(
        "--method",
        action="append",
        metavar="NAME=module:attribute",
        help="also score your own method under NAME (repeatable); module:attribute "
        "is a class or function giving an object with fit and predict, see "
        "tasks/methods.py (example: linear=tasks.methods:BayesianLinear)",
    )


class BayesianLinear:
    """A worked example, and a transfer baseline: per action ``a``, Δs is linear in
    the features ``x = (1, s, sin θ, cos θ)`` (θ the angle dimensions, which also
    stay in ``s``).

    ``fit``: per action, least squares on the batch data gives the weights ``W_a``
    (shape (p, D)) and the residual variance ``σ²[a,d]``.
    ``predict``: per action, the prior ``W ~ N(W_a, σ²/λ)`` column by column is
    updated on the setting's train transitions ``(X, Y)``:

        Ŵ = (XᵀX + λI)⁻¹ (XᵀY + λ W_a),
        mean = x Ŵ,   var[d] = σ²[a,d] (1 + x (XᵀX + λI)⁻¹ xᵀ).

    An action without train transitions predicts with its prior; one without
    batch transitions has ``W_a = 0`` and the batch's variance of Δs.

    Attributes:
        prior_strength: ``λ``, in transitions' worth (default 10).
    """

    def __init__(self, prior_strength: float = 10.0) -> None:
        if not (np.isfinite(prior_strength) and prior_strength > 0):
            raise ValueError(
                f"prior_strength: expected a finite number > 0, got {prior_strength!r}"
            )
        self.prior_strength = float(prior_strength)

    def features(self, states: Array) -> Array:
        """``x`` for each state, shape (n, p)."""
        states = np.asarray(states, dtype=float)
        angles = states[:, list(self.angle_dims)]
        return np.hstack(
            [np.ones((len(states), 1)), states, np.sin(angles), np.cos(angles)]
        )

    def fit(self, batch: Transitions, *, rng: np.random.Generator) -> None:
        del rng  # deterministic
        self.angle_dims = tuple(batch.angle_dims)
        x, y = self.features(batch.states), batch.deltas
        self.n_actions = int(batch.actions.max()) + 1
        p, D = x.shape[1], y.shape[1]
        self.weights = np.zeros((self.n_actions, p, D))
        self.noise = np.tile(np.var(y, axis=0) + 1e-12, (self.n_actions, 1))
        for a in range(self.n_actions):
            rows = batch.actions == a
            if rows.sum() > p:
                w, *_ = np.linalg.lstsq(x[rows], y[rows], rcond=None)
                self.weights[a] = w
                self.noise[a] = np.mean((y[rows] - x[rows] @ w) ** 2, axis=0) + 1e-12

    def predict(
        self,
        train: Transitions,
        states: Array,
        actions: Array,
        *,
        rng: np.random.Generator,
    ) -> tuple[Array, Array]:
        del rng  # deterministic
        x_train, y_train = self.features(train.states), train.deltas
        x = self.features(states)
        mean = np.zeros((len(states), y_train.shape[1]))
        var = np.zeros_like(mean)
        lam = self.prior_strength
        for a in np.unique(actions):
            rows, own = actions == a, train.actions == a
            if a >= self.n_actions:
                raise ValueError(f"actions: {a} is not an action of the batch data")
            X, Y = x_train[own], y_train[own]
            precision = X.T @ X + lam * np.eye(x.shape[1])
            w = np.linalg.solve(precision, X.T @ Y + lam * self.weights[a])
            mean[rows] = x[rows] @ w
            # x P⁻¹ xᵀ per row, with P⁻¹ applied by a solve
            lever = np.einsum(
                "np,pn->n", x[rows], np.linalg.solve(precision, x[rows].T)
            )
            var[rows] = self.noise[a] * (1.0 + lever[:, None])
        return mean, var


__all__ = [
    "BUILT_IN",
    "Added",
    "BayesianLinear",
    "MethodSpec",
    "add_method_argument",
    "check_specs",
    "fit_all",
    "load",
    "load_all",
    "method_seed",
    "parse_spec",
]
