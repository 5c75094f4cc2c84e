"""Your own method in the benchmark: one-step prediction, and swing-up control.

Both prediction tables (``tasks.cartpole_prediction`` and the one of
``tasks.acrobot_swingup``) score, beside the HiP-MDP and the three GP baselines, any
method named with ``--method NAME=module:attribute``. It sees exactly what the
HiP-MDP sees, on the same test settings and the same train/test splits, and its
scores go into every table and into ``metrics.json`` under ``NAME``. In the
acrobot's transfer trials it is a fourth model to plan on, beside the true model,
the average model and the HiP-MDP (``tasks.transfer``).

A method is an object with two methods (``attribute`` is a class or a function
that takes no arguments and returns one):

- ``fit(batch, *, rng)``: called once, on the batch data of the training
  instances (a ``hipmdp.Transitions`` whose ``instances`` tell them apart).
- ``adapt(train, *, rng) -> predictor``: called once per test setting, with the
  setting's train transitions (the ones the HiP-MDP filters its belief on). The
  predictor's ``predict(states, actions) -> (mean, var)`` gives the Gaussian
  predictive mean and variance of ``Δs = s' - s`` at states (n, D) and actions
  (n,), each shape (n, D), the variance > 0; it is called on the held-out test
  transitions' inputs. Angle changes are measured as ``Transitions.deltas``
  measures them. (The GP baselines have this shape: ``batch only`` adapts to
  nothing and returns itself; ``train only`` returns a GP fitted on ``train``.)

In a transfer trial, the agent plans on ``s' = s + mean`` (angles wrapped) of the
method adapted to the trial's real transitions so far (none before the first real
episode; instance id 0), as the HiP-MDP plans on its belief filtered on them:
``adapt`` runs before the first planning and after every real episode but the last
(no planning follows it). Planning calls ``predict`` with one state at a time, so
it should be cheap; a predictor with ``predict_mean(states, actions) -> mean`` has
that called instead (``hipmdp.planning.LearnedModel``).

**A policy instead of a model.** The acrobot's transfer trials also take a method
that acts itself, with its own learning and planning (model-free, meta-RL,
a policy trained offline on the batch data, a planner of your own): an object
with ``fit(batch, *, rng)`` as above and, instead of ``adapt``,

- ``agent(*, rng) -> agent``: called once per trial, for a fresh agent. The
  agent's ``act(state) -> action`` picks an action index (``0 .. A-1``, the
  domain's action table) for the state (D,); ``observe(state, action, reward,
  next_state, terminal)`` is called after every real step (``terminal``: the
  episode ended at the goal; the last step of an episode cut by the step limit
  has ``terminal`` False); ``end_episode()``, if the agent has it, after every
  real episode.

It runs the trial's real episodes on the same instance, from the same initial
states as the built-in methods, and its returns go into every control table,
curve and pair. It has no one-step predictions, so it is not in the prediction
tables, and ``tasks.cartpole_prediction`` refuses it. :class:`SarsaPolicy` is
a complete example: the built-in Sarsa(λ) agent with no model at all.

Each ``fit``, ``adapt`` and ``agent`` gets its own ``rng``, spawned from the run's
seed and the method's name only (:func:`method_seed`), and copies of the data:
adding or removing a method changes no other method's numbers, and the same seed
gives the same scores. :class:`BayesianLinear` is a complete example of a model.

Symbols: ``a`` action, ``d`` state dimension, ``x`` features of a state.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import importlib
import inspect
import multiprocessing
import operator
import os
import pickle
import re
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from hipmdp.data import Transitions, gaussian_loglik
from hipmdp.sarsa import epsilon_greedy, init_state, reset_traces, sarsa_update
from tasks.agents import DOMAINS, Domain
from tasks.prediction import PREDICTION_METHODS, entity
from tasks.transfer import LABELS as TRANSFER_LABELS
from tasks.transfer import METHODS as TRANSFER_METHODS

Array = np.ndarray

#: The methods of the prediction tables and of the transfer trials; an added
#: method may not take these names.
BUILT_IN = (*PREDICTION_METHODS, *(m for m in TRANSFER_METHODS if m != "hipmdp"))
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
    # the built-in names, as recordings and reports say them, in any case: a
    # report with two "HiP-MDP" rows would be ambiguous
    reserved = {*BUILT_IN, *map(entity, BUILT_IN), *TRANSFER_LABELS.values()}
    reserved = {r.lower() for r in reserved}
    for p in parsed:
        if p.name.lower() in reserved:
            raise ValueError(
                f"methods: {p.name!r} is (or is recorded or reported as) a built-in "
                "method; choose another name"
            )
        # in any case, as the built-in names above
        same = [n for n in names if n.lower() == p.name.lower()]
        if len(same) > 1:
            spellings = ", ".join(map(repr, sorted(set(same))))
            raise ValueError(
                f"methods: the name {p.name!r} is given more than once ({spellings})"
            )
        twins = [n for n in names if n != p.name and _crc(n) == _crc(p.name)]
        if twins:  # their streams would coincide (method_seed)
            raise ValueError(
                f"methods: the names {p.name!r} and {twins[0]!r} would share a "
                "random stream; rename one"
            )
    return parsed


def _crc(name: str) -> int:
    return zlib.crc32(name.encode())


def is_policy(method: Any) -> bool:
    """Whether a loaded method is a policy (its class has an ``agent`` method),
    not a model. The class, not the object: a model whose object has a callable
    attribute ``agent`` (a network's submodule, say) stays a model."""
    return callable(getattr(type(method), "agent", None))


def load(spec: MethodSpec) -> Any:
    """Import ``spec.module``, find ``spec.attribute``, call it with no arguments
    and check that the result has ``fit`` and either ``adapt`` (a model) or
    ``agent`` (a policy), not both, each taking the arguments the run will pass
    it (the keyword ``rng`` among them).
    Raise ValueError, naming the spec, if any step fails. Returns the object."""
    where = f"methods: {spec.name}={spec.module}:{spec.attribute}"
    try:
        module = importlib.import_module(spec.module)
    except ImportError as err:
        # the spec's top-level module or package not found: say where Python
        # looks, the usual fix. A package that is found but lacks the module
        # (a mistyped name: the folder is on the path already), or a module
        # that is there but imports a missing one, is named as it is.
        missing = (
            isinstance(err, ModuleNotFoundError)
            and err.name == spec.module.partition(".")[0]
        )
        hint = (
            "; Python looks in the working directory and on PYTHONPATH: run from "
            "the folder that holds it, or add that folder to PYTHONPATH"
            if missing
            else ""
        )
        raise ValueError(
            f"{where}: cannot import {spec.module!r} ({err}){hint}"
        ) from None
    except Exception as err:  # the user's module failed as it ran
        raise ValueError(
            f"{where}: importing {spec.module!r} raised {type(err).__name__}: {err}"
        ) from err
    if not hasattr(module, spec.attribute):
        raise ValueError(
            f"{where}: {spec.module!r} has no class or function {spec.attribute!r}"
        )
    factory = getattr(module, spec.attribute)
    if not callable(factory):
        raise ValueError(
            f"{where}: {spec.module}.{spec.attribute} is not callable (type "
            f"{type(factory).__name__}); expected a class or function"
        )
    try:
        method = factory()
    except Exception as err:  # the user's code: say which call failed, keep the cause
        raise ValueError(
            f"{where}: calling {spec.attribute}() with no arguments raised "
            f"{type(err).__name__}: {err}"
        ) from err
    has = {m for m in ("fit", "adapt") if callable(getattr(method, m, None))}
    has |= {"agent"} if is_policy(method) else set()
    kind = (
        f"{where}: expected an object with fit and adapt (a model) or with fit and "
        f"agent (a policy), {type(method).__name__} has"
    )
    lacks = [] if "fit" in has else ["fit"]
    lacks += [] if has & {"adapt", "agent"} else ["adapt or agent"]
    if lacks:
        # an agent on the object but not its class is not read as a policy
        hint = (
            "; its agent is an attribute of the object, and a policy's agent "
            "must be a method of its class"
            if "adapt or agent" in lacks and callable(getattr(method, "agent", None))
            else ""
        )
        raise ValueError(f"{kind} no {' and no '.join(lacks)}{hint}")
    if {"adapt", "agent"} <= has:
        raise ValueError(f"{kind} both adapt and agent")
    for name in sorted(has):  # as the run will call them
        try:
            signature = inspect.signature(getattr(method, name))
        except (TypeError, ValueError):  # none to read (a builtin): the call tells
            continue
        try:
            signature.bind(*_ARGUMENTS[name], rng=None)
        except TypeError:
            args = _ARGUMENTS[name]
            raise ValueError(
                f"{where}: {type(method).__name__}.{name}{signature} cannot take "
                f"the run's call {name}({', '.join((*args, 'rng=rng'))}); expected "
                f"{name}({', '.join((*args, '*', 'rng'))}) (or **kwargs)"
            ) from None
    return method


#: The positional arguments of each method of a loaded method; each also gets
#: the keyword ``rng``.
_ARGUMENTS = {"fit": ("batch",), "adapt": ("train",), "agent": ()}


def provenance(loaded: Sequence[tuple[MethodSpec, Any]]) -> dict[str, Any]:
    """Which code each loaded method (:func:`load_all`) ran, for a run's
    ``environment``: per name, its ``module`` (the spec's), its ``class``
    (``module.qualname`` of the built object's type, where its code is), that
    class's source ``file`` (absolute) and the file's ``sha256``, and the
    ``version`` of the installed distribution whose files hold that file. Any of
    the last three is None if it cannot be told (no source file, a file in the
    working directory, a shadowed install). Only the class's own file is hashed,
    not the modules it imports. Bookkeeping: it never raises for a method that
    loaded."""
    out = {}
    for spec, method in loaded:
        cls = type(method)
        try:
            file = os.path.abspath(inspect.getfile(cls))
            digest = hashlib.sha256(Path(file).read_bytes()).hexdigest()
        except (TypeError, OSError):  # built-in, zip-imported, "<string>" ...
            file = digest = None
        out[spec.name] = {
            "module": spec.module,
            "class": f"{cls.__module__}.{cls.__qualname__}",
            "file": file,
            "sha256": digest,
            "version": _version_holding(file, cls.__module__),
        }
    return out


def _version_holding(file: str | None, module: str) -> str | None:
    """The version of the installed distribution among whose files ``file`` is
    (looked for among those that provide ``module``'s top-level package)."""
    if file is None:
        return None
    try:
        names = metadata.packages_distributions().get(module.partition(".")[0], [])
        for name in dict.fromkeys(names):
            dist = metadata.distribution(name)
            where = (Path(dist.locate_file(f)) for f in dist.files or ())
            # a relative location (some editable installs) would be read against
            # the working directory: not evidence of where the file is
            files = {os.path.realpath(p) for p in where if p.is_absolute()}
            if os.path.realpath(file) in files:
                return dist.version
    except Exception:  # a broken installation's metadata: say nothing
        return None
    return None


def method_seed(seed: int, name: str, *key: int) -> np.random.SeedSequence:
    """The stream of method ``name`` in a run with seed ``seed``: the seed's
    descendant with spawn key ``(METHOD_STREAM, crc32(name), *key)``. ``fit`` gets
    key ``(0,)``; ``adapt`` on setting ``i`` of prediction table ``g`` gets
    ``(1, g, i)``; the trials of :func:`fit_all` ``(1, 2)`` and ``(1, 2, 1)``; a
    transfer trial's ``adapt`` after ``e`` real episodes of trial ``t`` on setting
    ``i`` ``(1, 3, i, t, e)``; a policy's ``agent`` in :func:`fit_all` ``(1, 2,
    2)``, and for trial ``t`` on setting ``i`` ``(1, 4, i, t)``."""
    return np.random.SeedSequence(seed, spawn_key=(METHOD_STREAM, _crc(name), *key))


@contextlib.contextmanager
def _users_call(where: str) -> Iterator[None]:
    """Run the user's code; an error it raises keeps its type and traceback, with
    a note saying which method's which call raised it."""
    try:
        yield
    except Exception as err:
        err.add_note(f"(in {where}, added with --method)")
        raise


def _copy(data: Transitions) -> Transitions:
    """An independent copy of ``data``: what a method does to its arguments cannot
    reach the run's own arrays."""
    return data.take(np.arange(len(data)))


class Added(NamedTuple):
    """A fitted added method of a run: its spec, the object and the run's seed."""

    spec: MethodSpec
    method: Any
    seed: int

    @property
    def name(self) -> str:
        return self.spec.name

    def adapt(self, train: Transitions, key: tuple[int, ...]) -> Any:
        """The method's predictor for an instance with transitions ``train`` (a
        copy is passed), checked to have ``predict``. ``key``: as
        :func:`method_seed` says."""
        rng = np.random.default_rng(method_seed(self.seed, self.name, 1, *key))
        where = f"method {self.name}: adapt"
        with _users_call(where):
            predictor = self.method.adapt(_copy(train), rng=rng)
        if not callable(getattr(predictor, "predict", None)):
            raise ValueError(
                f"{where} must return an object with predict(states, actions), "
                f"got {type(predictor).__name__}"
            )
        return predictor

    def predict(
        self, train: Transitions, test: Transitions, key: tuple[int, ...]
    ) -> tuple[Array, Array]:
        """The (mean, var) of Δs on ``test`` of the method adapted to ``train``
        (:meth:`adapt`, on a :meth:`fresh_copy` of the fitted object, as every
        transfer trial gets: an ``adapt`` that changes the object cannot carry one
        setting's data into the next), checked as :meth:`checked_predict` says."""
        fresh = self._replace(method=self.fresh_copy())
        return self.checked_predict(fresh.adapt(train, key), test)

    def checked_predict(self, predictor: Any, test: Transitions) -> tuple[Array, Array]:
        """``predictor.predict`` on copies of ``test``'s inputs, checked: real and
        finite, shapes (n, D), var > 0, and a finite log-likelihood of ``test``."""
        where = f"method {self.name}: predict"
        with _users_call(where):
            out = predictor.predict(test.states.copy(), test.actions.copy())
        if not (isinstance(out, tuple | list) and len(out) == 2):
            raise ValueError(
                f"{where} must return (mean, var), got {type(out).__name__}"
            )
        shape = test.states.shape
        checked = []
        for label, x in zip(("mean", "var"), out, strict=True):
            if np.iscomplexobj(x):
                raise ValueError(f"{where}'s {label} is complex, expected real")
            try:
                x = np.asarray(x, dtype=float)
            except (TypeError, ValueError) as err:
                raise ValueError(
                    f"{where}'s {label} is not an array of numbers ({err})"
                ) from None
            if x.shape != shape:
                raise ValueError(
                    f"{where}'s {label} has shape {x.shape}, expected {shape}"
                )
            if not np.all(np.isfinite(x)):
                raise ValueError(f"{where}'s {label} is not finite")
            checked.append(x)
        mean, var = checked
        if not np.all(var > 0):
            raise ValueError(f"{where}'s var must be > 0")
        with np.errstate(over="ignore"):
            squared = (mean - test.deltas) ** 2
        if not np.all(np.isfinite(squared)):
            raise ValueError(
                f"{where}'s mean is so far off that its squared error is not finite"
            )
        with np.errstate(over="ignore", divide="ignore"):
            loglik = gaussian_loglik(test.deltas, mean, var)
        if not np.isfinite(loglik):
            raise ValueError(
                f"{where}'s var is so small that the log-likelihood of the test "
                "transitions is not finite"
            )
        return mean, var

    def fresh_copy(self) -> Any:
        """``copy.deepcopy`` of the fitted object: where each trial starts."""
        with _users_call(f"method {self.name}: copy.deepcopy of the fitted object"):
            return copy.deepcopy(self.method)

    @property
    def is_policy(self) -> bool:
        """Whether the method is a policy (see the module docstring)."""
        return is_policy(self.method)

    def agent(self, key: tuple[int, ...]) -> Any:
        """A fresh agent of a policy, checked to have ``act`` and ``observe``.
        ``key``: as :func:`method_seed` says."""
        rng = np.random.default_rng(method_seed(self.seed, self.name, 1, *key))
        where = f"method {self.name}: agent"
        with _users_call(where):
            agent = self.method.agent(rng=rng)
        missing = [
            m for m in ("act", "observe") if not callable(getattr(agent, m, None))
        ]
        if missing:
            raise ValueError(
                f"{where} must return an object with act(state) and observe(state, "
                f"action, reward, next_state, terminal); {type(agent).__name__} has "
                f"no {' and no '.join(missing)}"
            )
        return agent

    def act(self, agent: Any, state: Array, n_actions: int) -> int:
        """``agent.act`` on a copy of ``state``, checked to be an action index
        ``0 .. n_actions - 1``."""
        where = f"method {self.name}: act"
        with _users_call(where):
            action = agent.act(np.array(state, dtype=float))
        try:
            index = operator.index(action)
        except TypeError:
            raise ValueError(
                f"{where} must return an action index (an integer), got "
                f"{action!r} ({type(action).__name__})"
            ) from None
        if isinstance(action, bool) or not 0 <= index < n_actions:
            raise ValueError(
                f"{where} must return an action index 0..{n_actions - 1}, "
                f"got {action!r}"
            )
        return index

    def observe(
        self, agent: Any, state: Array, action: int, reward: float,
        next_state: Array, terminal: bool,
    ) -> None:  # fmt: skip
        """``agent.observe(state, action, reward, next_state, terminal)``, with
        copies of the states."""
        with _users_call(f"method {self.name}: observe"):
            agent.observe(
                np.array(state, dtype=float), int(action), float(reward),
                np.array(next_state, dtype=float), bool(terminal),
            )  # fmt: skip

    def end_episode(self, agent: Any) -> None:
        """``agent.end_episode()``, if the agent has it."""
        if callable(getattr(agent, "end_episode", None)):
            with _users_call(f"method {self.name}: end_episode"):
                agent.end_episode()


def load_all(
    specs: Sequence[str], policies: bool = False
) -> tuple[tuple[MethodSpec, Any], ...]:
    """``(spec, load(spec))`` for every ``NAME=module:attribute`` of ``specs``;
    raise ValueError if any is malformed or cannot be loaded (:func:`load`), or
    is a policy unless ``policies`` is True (an experiment with transfer
    trials). Experiments call it before any work."""
    loaded = tuple((spec, load(spec)) for spec in check_specs(specs))
    for spec, method in loaded:
        if not policies and is_policy(method):
            raise ValueError(
                f"methods: {spec.name}={spec.module}:{spec.attribute} is a policy "
                "(it has agent, not adapt): a prediction table needs a model's "
                "predictions; only tasks.acrobot_swingup runs policies"
            )
    return loaded


#: Transitions of the batch that :func:`fit_all`'s trial prediction trains and
#: tests on (each).
TRIAL_SIZE = 10


def fit_all(
    loaded: Sequence[tuple[MethodSpec, Any]],
    batch: Transitions,
    seed: int,
    n_actions: int | None = None,
    pickled: bool = False,
    transfer: bool = False,
) -> tuple[Added, ...]:
    """Fit every loaded method (:func:`load_all`) on a copy of ``batch``, each with
    its own stream (:func:`method_seed`), then try it as the runs will use it, so
    that a method that breaks does so before the run's long stages (the
    experiments call this as soon as the batch data are gathered):

    - adapted to the first ``TRIAL_SIZE`` batch transitions, predicting the next
      ``TRIAL_SIZE`` (key ``(2,)``), as in a prediction table;
    - with ``transfer`` (an experiment with transfer trials) also adapted to no
      transitions, predicting one state (key ``(2, 1)``), as a transfer trial's
      first planning does; with ``predict_mean``, that must agree with
      ``predict``'s mean (``numpy.allclose``), as planning calls it. Without
      transfer trials no method is adapted to no transitions, so none is tried
      so.

    An error in a try has a note saying how many transitions the method was
    adapted to.

    A policy instead gets one agent (key ``(2, 2)``) that acts on the first
    batch state (an action ``0 .. n_actions - 1``: ``n_actions`` must be given
    if there is a policy), observes the first transition and ends the episode.
    The tries run on a copy of the fitted object, so the object returned is as
    ``fit`` left it. With ``pickled`` (:func:`must_pickle`), the fitted object
    must also pickle, as worker processes will receive it that way.
    """
    out = []
    trial_train = batch.take(np.arange(min(TRIAL_SIZE, len(batch))))
    trial_test = batch.take(
        np.arange(len(trial_train), min(2 * TRIAL_SIZE, len(batch)))
    )
    for spec, method in loaded:
        rng = np.random.default_rng(method_seed(seed, spec.name, 0))
        with _users_call(f"method {spec.name}: fit"):
            method.fit(_copy(batch), rng=rng)
        added = Added(spec, method, seed)
        if pickled:  # as the worker processes will receive it
            with _users_call(f"method {spec.name}: pickle.dumps of the fitted object"):
                pickle.dumps(method)
        # the tries run on a copy: what they leave on the object (a policy whose
        # agent is the object itself, say) is not where every trial starts
        trying = added._replace(method=added.fresh_copy())
        if added.is_policy:
            if n_actions is None:
                raise ValueError(
                    f"n_actions: needed to try the policy {spec.name}, got None"
                )
            _check_policy(trying, batch, n_actions)
        else:
            with _adapted_to(spec.name, len(trial_train)):
                trying.predict(trial_train, trial_test, (2,))
            if transfer:
                with _adapted_to(spec.name, 0):
                    _check_planning(trying, batch)
        out.append(added)
    return tuple(out)


@contextlib.contextmanager
def _adapted_to(name: str, n: int) -> Iterator[None]:
    """:func:`fit_all`'s try of method ``name`` adapted to ``n`` transitions: an
    error raised in it gets a note saying so."""
    try:
        yield
    except Exception as err:
        err.add_note(f"(in the try of method {name} after adapt on {n} transitions)")
        raise


def must_pickle(workers: int) -> bool:
    """Whether ``workers`` processes receive the fitted methods pickled: with
    more than one, unless they are forked (``multiprocessing``'s start method,
    ``fork`` by default on Linux before Python 3.14)."""
    return workers > 1 and multiprocessing.get_start_method() != "fork"


def _check_policy(added: Added, batch: Transitions, n_actions: int) -> None:
    """:func:`fit_all`'s try of a policy: one step of one agent."""
    agent = added.agent((2, 2))
    if len(batch):
        added.act(agent, batch.states[0], n_actions)
        added.observe(  # the batch's transition from that state, a true one
            agent, batch.states[0], batch.actions[0],
            0.0 if batch.rewards is None else batch.rewards[0],
            batch.next_states[0], False,
        )  # fmt: skip
    added.end_episode(agent)


def _check_planning(added: Added, batch: Transitions) -> None:
    """:func:`fit_all`'s second try: no transitions, one state."""
    none, one = batch.take(np.arange(0)), batch.take(np.arange(min(1, len(batch))))
    predictor = added.adapt(none, (2, 1))
    mean, _ = added.checked_predict(predictor, one)
    if callable(getattr(predictor, "predict_mean", None)):
        where = f"method {added.name}: predict_mean"
        with _users_call(where):
            fast = np.asarray(
                predictor.predict_mean(one.states.copy(), one.actions.copy()), float
            )
        if fast.shape != mean.shape:
            raise ValueError(
                f"{where} gives shape {fast.shape}, expected {mean.shape} as "
                "predict's mean: planning calls predict_mean, which must give "
                "shape (n, D) for n states"
            )
        if not np.allclose(fast, mean):
            raise ValueError(
                f"{where} gives {fast.tolist()}, predict's mean {mean.tolist()}; "
                "planning calls predict_mean, so the two must agree"
            )


def add_method_argument(parser, policies: bool = False) -> None:
    """The experiments' repeatable ``--method NAME=module:attribute``; with
    ``policies``, the help says that a policy is taken too."""
    policy = (
        " or with fit and agent (a policy, e.g. sarsa=tasks.methods:SarsaPolicy)"
        if policies
        else ""
    )
    parser.add_argument(
        "--method",
        action="append",
        metavar="NAME=module:attribute",
        help="also score your own method under NAME (repeatable); module:attribute "
        "is a class or function giving an object with fit and adapt (a model, "
        f"e.g. linear=tasks.methods:BayesianLinear){policy}; see tasks/methods.py",
    )


class BayesianLinear:
    """A worked example, and a transfer baseline: per action ``a``, Δs is linear in
    the features ``x = (1, s, sin θ, cos θ)`` (θ the angle dimensions, which also
    stay in ``s``).

    ``fit``: per action, least squares on the batch data gives the weights ``W_a``
    (shape (p, D)) and the residual variance ``σ²[a,d]`` (plus 1e-12, so that a
    noise-free batch still gives a variance > 0). The residuals are pooled over
    the training instances, so ``σ²`` holds their spread as well as the noise
    within one: the intervals stay wide however many train transitions a
    setting has.
    ``adapt``: per action, the prior ``W ~ N(W_a, σ²/λ)`` column by column is
    updated on the setting's train transitions ``(X, Y)``, and the predictor
    (:class:`LinearPredictor`) gives

        Ŵ = (XᵀX + λI)⁻¹ (XᵀY + λ W_a),
        mean = x Ŵ,   var[d] = σ²[a,d] (1 + x (XᵀX + λI)⁻¹ xᵀ).

    An action without train transitions predicts with its prior. An action with
    no more batch transitions than features (p) has ``W_a = 0`` and the
    variance of Δs over the whole batch.

    Attributes:
        prior_strength: ``λ``: the prior counts as ``λ`` transitions whose
            features have unit size in every direction (the features are not
            rescaled; default 10).
    """

    def __init__(self, prior_strength: float = 10.0) -> None:
        if not (np.isfinite(prior_strength) and prior_strength > 0):
            raise ValueError(
                f"prior_strength: expected a finite number > 0, got {prior_strength!r}"
            )
        self.prior_strength = float(prior_strength)

    def features(self, states: Array) -> Array:
        """``x`` for each state, shape (n, p)."""
        return _features(states, self.angle_dims)

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

    def adapt(self, train: Transitions, *, rng: np.random.Generator) -> LinearPredictor:
        """The posterior given ``train``, per action (the prior for an action
        ``train`` lacks)."""
        del rng  # deterministic
        if not hasattr(self, "weights"):
            raise ValueError("BayesianLinear: call fit before adapt")
        x, y = self.features(train.states), train.deltas
        lam, p = self.prior_strength, self.weights.shape[1]
        weights, covariance = np.empty_like(self.weights), []
        for a in range(self.n_actions):
            own = train.actions == a
            X, Y = x[own], y[own]
            precision = X.T @ X + lam * np.eye(p)  # P, per unit of σ²
            weights[a] = np.linalg.solve(precision, X.T @ Y + lam * self.weights[a])
            covariance.append(np.linalg.inv(precision))
        return LinearPredictor(
            self.angle_dims, weights, np.array(covariance), self.noise
        )


@dataclass(frozen=True)
class LinearPredictor:
    """:class:`BayesianLinear` adapted to an instance: per action ``a``, the
    posterior mean ``Ŵ[a]`` (p, D), ``P⁻¹[a] = (XᵀX + λI)⁻¹`` (p, p) and ``σ²[a]``
    (D,)."""

    angle_dims: tuple[int, ...]
    weights: Array
    covariance: Array
    noise: Array

    def predict(self, states: Array, actions: Array) -> tuple[Array, Array]:
        """``mean = x Ŵ[a]``, ``var[d] = σ²[a,d] (1 + x P⁻¹[a] xᵀ)``, each (n, D)."""
        x = _features(states, self.angle_dims)
        actions = np.asarray(actions)
        if actions.size and (actions.min() < 0 or actions.max() >= len(self.weights)):
            raise ValueError(
                f"actions: expected 0..{len(self.weights) - 1} (the batch data's), "
                f"got {actions.min()}..{actions.max()}"
            )
        mean = np.einsum("np,npd->nd", x, self.weights[actions])
        lever = np.einsum("np,npq,nq->n", x, self.covariance[actions], x)
        return mean, self.noise[actions] * (1.0 + lever[:, None])


class SarsaPolicy:
    """A worked example of a policy, and a reference: the built-in agent (Sarsa(λ)
    with the domain's Fourier basis and hyperparameters, ``tasks.agents``)
    learning on the instance alone. It plans nothing and leaves the batch unused:
    what the transfer has to beat. Its agent acts and learns exactly as
    ``tasks.agents.run_episode`` does, step for step and draw for draw.

    Args:
        domain: a key of ``tasks.agents.DOMAINS`` (default ``"acrobot"``); the
            attribute ``domain`` holds that ``Domain``.
    """

    def __init__(self, domain: str = "acrobot") -> None:
        if domain not in DOMAINS:
            raise ValueError(f"domain: expected one of {list(DOMAINS)}, got {domain!r}")
        self.domain = DOMAINS[domain]

    def fit(self, batch: Transitions, *, rng: np.random.Generator) -> None:
        del batch, rng  # learns on the instance alone

    def agent(self, *, rng: np.random.Generator) -> SarsaAgent:
        return SarsaAgent(self.domain, rng)


class SarsaAgent:
    """:class:`SarsaPolicy`'s agent: fresh weights ``q₀``; ``observe`` picks the
    next action (ε-greedy from ``rng``) and makes the Sarsa(λ) update on it, and
    ``act`` returns that action; the traces are reset after each episode. As the
    trials call it, ``observe``'s ``state`` is the state ``act`` (or the last
    ``observe``) saw, so each state's features ``φ`` are computed once."""

    def __init__(self, domain: Domain, rng: np.random.Generator) -> None:
        self.basis, self.config, self.rng = domain.basis(), domain.sarsa, rng
        self.step_sizes = self.config.alpha * self.basis.step_scale
        self.state = init_state(
            domain.n_actions, self.basis.n_features, domain.initial_value
        )
        # the next state's features and the action chosen there
        self._phi: Array | None = None
        self._next: int | None = None

    def _choose(self, phi: Array) -> int:
        q = self.state.weights @ phi
        return epsilon_greedy(q, self.config.epsilon, rng=self.rng)

    def act(self, state: Array) -> int:
        if self._next is None:  # an episode's first state
            self._phi = self.basis(state)
            self._next = self._choose(self._phi)
        return self._next

    def observe(self, state, action, reward, next_state, terminal) -> None:
        phi, phi_next = self._phi, self.basis(next_state)
        self._phi, self._next = phi_next, self._choose(phi_next)
        self.state = sarsa_update(
            self.state, phi, action, reward, None if terminal else phi_next,
            self._next, self.step_sizes, self.config,
        ).state  # fmt: skip

    def end_episode(self) -> None:
        self.state = reset_traces(self.state)
        self._phi = self._next = None


def _features(states: Array, angle_dims: tuple[int, ...]) -> Array:
    """``x = (1, s, sin θ, cos θ)`` for each state, shape (n, p)."""
    states = np.asarray(states, dtype=float)
    angles = states[:, list(angle_dims)]
    return np.hstack(
        [np.ones((len(states), 1)), states, np.sin(angles), np.cos(angles)]
    )


__all__ = [
    "BUILT_IN",
    "Added",
    "BayesianLinear",
    "LinearPredictor",
    "MethodSpec",
    "SarsaAgent",
    "SarsaPolicy",
    "add_method_argument",
    "check_specs",
    "fit_all",
    "is_policy",
    "load",
    "load_all",
    "method_seed",
    "must_pickle",
    "parse_spec",
    "provenance",
]
