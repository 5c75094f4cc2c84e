"""Do the learned models make the swing-up look easier than it is? A check on a
finished swing-up run.

    python -m tasks.acrobot_energy runs/acrobot_swingup [--trials 2]

Reads a finished swing-up run (``config.json``, ``hipmdp_model.npz``,
``batch.npz``), refits its average model exactly as the run did, and on each of the
run's test settings, for ``--trials`` trials (seeds spawned from ``--seed``):

1. **Promised and delivered.** A fresh agent plans the run's
   ``initial_planning_episodes`` simulated episodes on each model, as the transfer
   protocol's first planning does (tasks/transfer.py), then runs ``--real``
   real episodes on the instance, each from the planned agent and learning as the
   protocol's first real episode does (one episode is too noisy a measure: a few
   run to the step limit). The models: ``true`` (the
   instance's simulator), ``average`` (one GP on all batch data), ``prior`` (the
   HiP-MDP at its prior-mean weights, what its first planning uses),
   ``identified`` (the HiP-MDP filtered on ``--identify`` transitions of the
   instance, as ``tasks.acrobot_identified`` does) and, with ``--noise σ``,
   ``noisy`` (the simulator with zero-mean Gaussian noise of standard deviation σ
   rad/s added to both predicted velocities: a model whose errors have no bias).
   Two more locate the harm, each the prior-mean HiP-MDP with the simulator's
   exact predictions in part of the state space: ``exact_fast`` where
   ``|θ̇₂| ≥ --fast`` rad/s (default 8: about a tenth of the true planner's
   states, where the learned models err most), ``exact_slow`` everywhere else.
   Three more ask whether the energy the models' errors add is the harm: the
   average model (``average_energy``) and the prior-mean HiP-MDP
   (``prior_energy``) with their predicted velocities rescaled so that each
   step's energy changes by the elbow torque's work
   (:class:`tasks.agents.EnergyConserving`, with the instance's true masses and
   lengths: information no learned model has), and ``prior_energy_nominal``
   with the nominal acrobot's. ``exact_fast_angles``
   and ``exact_fast_velocities`` take only the angles, or only the velocities,
   of the simulator's prediction where ``|θ̇₂| ≥ --fast``, and the prior-mean
   HiP-MDP's for the rest. ``train_sampled`` plans each simulated episode on
   the HiP-MDP at one training instance's fitted weights, drawn for it
   (:class:`SampledWeights`): planning over instances instead of on their mean.
   ``--models`` runs a subset (``true`` always). Recorded: the mean steps of the
   last ``--last`` simulated episodes (what the model promised) and the mean steps
   of the real episodes (what the agent got).
2. **Energy.** On a sample of ``--states`` of the (state, action) pairs the
   ``true`` planner visited (where a good swing-up goes), each learned model's
   one-step prediction ``ŝ'`` against the simulator's ``s'``: the error in
   mechanical energy ``E(ŝ') − E(s')`` (``tasks.acrobot.energy``) and its parts.
   With ``ε = ŝ'_q̇ − s'_q̇`` the velocity error and ``M`` the inertia matrix at
   ``s'``, the kinetic part is ``εᵀ M q̇' + ½ εᵀ M ε``: the first term has the
   sign of the error's projection on the momentum ``M q̇'``, the second is
   positive for any error, so velocity errors that do not favour either sign
   still add energy on average (the positional part is the rest). Beside them,
   the simulator's own energy change per step and, in bands of ``|θ̇₂|``: the
   RMS velocity errors (per trial, then averaged over trials), the share of
   visited states, the band's share of ``½ εᵀ M ε`` summed over all states, and
   the median distance from its states to the nearest batch state (normalised
   units, :class:`BatchDistance`): how thin the data the models learnt from are
   there. Last, the share of ``½ εᵀ M ε`` on the steps at the elbow's wrap
   ``θ₂ = ±π`` (:func:`elbow_wrap`), where the models' kernels, on wrapped
   angles, split one neighbourhood in two.

Prints the means over trials with 95% intervals and writes ``energy.json`` in the
run folder: per model the promised and delivered steps (settings × trials), the
energy terms (settings × trials), the banded errors, and summaries (the paired
``delivered_minus_true`` is in steps: above 0 is worse than the simulator's agent).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from hipmdp.filter import Belief
from hipmdp.planning import LearnedModel, PlanResult, plan
from hipmdp.sarsa import init_state
from tasks import acrobot, agents
from tasks.acrobot_identified import average_model, check_run, read_run
from tasks.acrobot_swingup import run_test_instances
from tasks.agents import ACROBOT, SimulatorModel, run_episode
from tasks.experiment import (
    check_counts,
    check_integer,
    check_out_file,
    environment,
    fmt_ci,
    inputs_checked,
    mean_ci,
    one_blas_thread,
    pool_map,
    printable_output,
    run_or_exit,
    run_parser,
    to_jsonable,
    trial_seeds,
    write_json,
)
from tasks.prediction import gather_split
from tasks.transfer import TransferConfig

MODELS = (
    "true",
    "average",
    "prior",
    "identified",
    "noisy",
    "exact_fast",
    "exact_slow",
    "average_energy",
    "prior_energy",
    "prior_energy_nominal",
    "exact_fast_angles",
    "exact_fast_velocities",
    "train_sampled",
)
LEARNED = MODELS[1:]
DEFAULT_MODELS = ("true", "average", "prior", "identified")
TERMS = ("total", "linear", "quadratic", "positional", "true_gain")
BANDS = (0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 14.0, np.inf)  # |θ̇₂| in rad/s


class NoisySimulator:
    """The instance's simulator with zero-mean Gaussian noise of standard
    deviation ``sd`` rad/s added to each predicted velocity (a random stream of its
    own): errors of a given size without any bias."""

    def __init__(self, simulator: SimulatorModel, sd: float, rng) -> None:
        self._simulator, self._sd, self._rng = simulator, sd, rng

    def predict(self, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
        out = self._simulator.predict(states, actions)
        out[:, 2:] += self._sd * self._rng.standard_normal(out[:, 2:].shape)
        return out


class Split:
    """``fast`` where the state's ``|θ̇₂| ≥ threshold`` rad/s, ``slow`` elsewhere
    (two dynamics models, each asked only for its own rows)."""

    def __init__(self, slow, fast, threshold: float) -> None:
        self._slow, self._fast, self._threshold = slow, fast, threshold

    def predict(self, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
        states = np.asarray(states, dtype=np.float64)
        fast = np.abs(states[:, 3]) >= self._threshold
        out = np.empty_like(states)
        for model, rows in ((self._fast, fast), (self._slow, ~fast)):
            if rows.any():
                out[rows] = model.predict(states[rows], np.asarray(actions)[rows])
        return out


class Columns:
    """``model``'s predictions with the ``columns`` of ``exact``'s on the rows whose
    state has ``|θ̇₂| ≥ threshold`` rad/s (``exact`` is asked for those rows only)."""

    def __init__(self, model, exact, threshold: float, columns: slice) -> None:
        self._model, self._exact = model, exact
        self._threshold, self._columns = threshold, columns

    def predict(self, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
        states = np.asarray(states, dtype=np.float64)
        out = np.array(self._model.predict(states, actions), dtype=np.float64)
        fast = np.abs(states[:, 3]) >= self._threshold
        if fast.any():
            exact = self._exact.predict(states[fast], np.asarray(actions)[fast])
            out[np.flatnonzero(fast), self._columns] = exact[:, self._columns]
        return out


class SampledWeights:
    """The HiP-MDP at one training instance's fitted weights, drawn afresh for
    every simulated episode (``draw``): planning over the instances the model was
    fitted on instead of on their mean. ``predict`` draws for every call (the
    one-step errors of a drawn model)."""

    def __init__(self, hip, rng: np.random.Generator) -> None:
        self._hip, self._rng = hip, rng

    def draw(self) -> LearnedModel:
        weights = self._hip.weights  # (K, instances), row 0 the constant 1
        w = weights[1:, self._rng.integers(weights.shape[1])]
        belief = Belief(w, np.eye(len(w)))  # mean w: planning reads the mean only
        return LearnedModel(self._hip, belief, ACROBOT.angle_dims)

    def predict(self, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
        return self.draw().predict(states, actions)


PLAN_FIELDS = ("steps", "returns", "reached")


def _plan(state, basis, model, task, starts, n_episodes: int, rng) -> PlanResult:
    """:func:`hipmdp.planning.plan`; on a :class:`SampledWeights` model, one
    episode at a time on a model drawn for it (the same start-state and
    exploration draws as ``plan`` makes for ``n_episodes`` in one call)."""
    if not isinstance(model, SampledWeights):
        return plan(
            state, basis, ACROBOT.sarsa, model, task, starts, n_episodes, rng=rng
        )
    results = []
    for _ in range(n_episodes):
        results.append(
            plan(state, basis, ACROBOT.sarsa, model.draw(), task, starts, 1, rng=rng)
        )
        state = results[-1].state
    return PlanResult(
        state,
        *(np.concatenate([getattr(r, k) for r in results]) for k in PLAN_FIELDS),
    )


class BatchDistance:
    """Distance from states to the nearest batch state, in the Fourier basis's
    normalised units: angles over π (wrapped: a periodic box), θ̇₁ over 4π and θ̇₂
    over 9π rad/s (tasks.agents.ACROBOT's box)."""

    def __init__(self, batch_states: np.ndarray) -> None:
        from scipy.spatial import cKDTree

        scale = np.array(ACROBOT.high)
        self._scale = scale
        # angles in [0, 2) with period 2; velocities shifted into a box too wide
        # to wrap
        self._shift = np.array([1.0, 1.0, 1e3, 1e3])
        self._box = np.array([2.0, 2.0, 1e7, 1e7])
        self._tree = cKDTree(self._normalise(batch_states), boxsize=self._box)

    def _normalise(self, states: np.ndarray) -> np.ndarray:
        x = np.asarray(states, dtype=np.float64) / self._scale + self._shift
        x[:, :2] = np.mod(x[:, :2], 2.0)
        x[:, :2][x[:, :2] >= 2.0] = 0.0  # mod of a tiny negative rounds up to 2
        return x

    def __call__(self, states: np.ndarray) -> np.ndarray:
        """Distances, shape ``(N,)``, for ``states`` ``(N, 4)``."""
        return self._tree.query(self._normalise(states))[0]


def _bands(states: np.ndarray) -> np.ndarray:
    """The :data:`BANDS` index of each state's ``|θ̇₂|``, shape ``(N,)``."""
    return np.digitize(np.abs(states[:, 3]), BANDS[1:-1])


def _kinetic_error(
    predicted: np.ndarray, true_next: np.ndarray, params: acrobot.AcrobotParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``ε`` ``(N, 2)``, ``M(s')`` ``(N, 2, 2)`` and ``½ εᵀ M ε`` ``(N,)``."""
    eps = predicted[:, 2:] - true_next[:, 2:]
    mass = acrobot.mass_matrix(true_next, params)
    return eps, mass, 0.5 * np.einsum("ni,nij,nj->n", eps, mass, eps)


def band_medians(values: np.ndarray, states: np.ndarray) -> np.ndarray:
    """Median of ``values`` ``(N,)`` per ``|θ̇₂|`` band of ``states`` (NaN where
    a band is empty), shape ``(B,)``."""
    band = _bands(states)
    out = np.full(len(BANDS) - 1, np.nan)
    for b in range(len(BANDS) - 1):
        if np.any(band == b):
            out[b] = np.median(values[band == b])
    return out


class _Recorder:
    """A dynamics model that keeps every (state, action) batch it was asked."""

    def __init__(self, model) -> None:
        self.model, self.states, self.actions = model, [], []

    def predict(self, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
        self.states.append(np.array(states))
        self.actions.append(np.array(actions))
        return self.model.predict(states, actions)


def energy_terms(
    predicted: np.ndarray,
    true_next: np.ndarray,
    states: np.ndarray,
    params: acrobot.AcrobotParams,
) -> dict[str, float]:
    """Mean energy error of one-step predictions and its parts (module docstring).

    Args:
        predicted: ``ŝ'``, true_next: ``s'``, states: ``s``, each shape ``(N, 4)``.
        params: the instance.

    Returns:
        ``{"total": mean E(ŝ') − E(s'), "linear": mean εᵀ M q̇', "quadratic": mean
        ½ εᵀ M ε, "positional": total − linear − quadratic, "true_gain": mean
        E(s') − E(s)}`` in J per step.
    """
    eps, mass, quadratic = _kinetic_error(predicted, true_next, params)
    true_energy = acrobot.energy(true_next, params)
    total = acrobot.energy(predicted, params) - true_energy
    linear = np.einsum("ni,nij,nj->n", eps, mass, true_next[:, 2:])
    gain = true_energy - acrobot.energy(states, params)
    out = {
        "total": float(np.mean(total)),
        "linear": float(np.mean(linear)),
        "quadratic": float(np.mean(quadratic)),
        "true_gain": float(np.mean(gain)),
    }
    out["positional"] = out["total"] - out["linear"] - out["quadratic"]
    return out


def banded_errors(
    predicted: np.ndarray,
    true_next: np.ndarray,
    states: np.ndarray,
    params: acrobot.AcrobotParams,
) -> dict[str, np.ndarray]:
    """RMS velocity errors per ``|θ̇₂|`` band of the state (:data:`BANDS`).

    Returns ``{"share": (B,), "rmse": (B, 2), "kinetic_share": (B,),
    "wrap_share", "wrap_kinetic_share"}``: the share of states in each band,
    their RMS errors in ``(θ̇₁, θ̇₂)``, and the band's share of the summed
    ``½ εᵀ M ε`` (the energy velocity errors add whatever their sign; ``M`` at
    ``true_next``, of instance ``params``); then the same two shares for the steps
    at the elbow's wrap (:func:`elbow_wrap`), over all bands. A band no state fell
    in has shares 0 and RMS NaN.
    """
    band = _bands(states)
    err, _, quadratic = _kinetic_error(predicted, true_next, params)
    total = max(quadratic.sum(), np.finfo(float).tiny)
    share = np.zeros(len(BANDS) - 1)
    kinetic = np.zeros(len(BANDS) - 1)
    rmse = np.full((len(BANDS) - 1, 2), np.nan)
    for b in range(len(BANDS) - 1):
        inside = band == b
        share[b] = inside.mean()
        kinetic[b] = quadratic[inside].sum() / total
        if inside.any():
            rmse[b] = np.sqrt(np.mean(err[inside] ** 2, axis=0))
    wrap = elbow_wrap(states, true_next)
    return {
        "share": share,
        "rmse": rmse,
        "kinetic_share": kinetic,
        "wrap_share": float(wrap.mean()),
        "wrap_kinetic_share": float(quadratic[wrap].sum() / total),
    }


NEAR_WRAP = 0.6  # rad from θ₂ = ±π


def elbow_wrap(states: np.ndarray, true_next: np.ndarray) -> np.ndarray:
    """Whether each step starts within :data:`NEAR_WRAP` rad of the elbow's wrap
    ``θ₂ = ±π`` or crosses it (``|θ₂' − θ₂| > π`` before wrapping the difference):
    where the models' kernels, on the wrapped angle, see one neighbourhood as two
    ends of the interval. Shape ``(N,)``."""
    near = np.pi - np.abs(states[:, 1]) < NEAR_WRAP
    return near | (np.abs(true_next[:, 1] - states[:, 1]) > np.pi)


_STATE: dict[str, Any] = {}


def _init(settings, hip, average, beliefs, options) -> None:
    _STATE.update(
        settings=settings, hip=hip, average=average, beliefs=beliefs, **options
    )


def _build_models(
    names, setting: int, params, simulator, ss_noise, ss_weights
) -> dict[str, Any]:
    """The dynamics models ``names`` for test setting ``setting`` (instance
    ``params``, its ``simulator``), from what :func:`_init` installed; ``noisy``
    and ``train_sampled`` draw from ``ss_noise`` and ``ss_weights``."""
    hip, fast = _STATE["hip"], _STATE["fast"]
    dims = ACROBOT.angle_dims
    prior = LearnedModel(hip, hip.prior(), dims)
    build = {  # only the asked models are built; exact_* share the prior-mean one
        "true": lambda: _Recorder(simulator),
        "average": lambda: LearnedModel(_STATE["average"], None, dims),
        "prior": lambda: prior,
        "identified": lambda: LearnedModel(hip, _STATE["beliefs"][setting], dims),
        "noisy": lambda: NoisySimulator(
            simulator, _STATE["noise"], np.random.default_rng(ss_noise)
        ),
        "exact_fast": lambda: Split(prior, simulator, fast),
        "exact_slow": lambda: Split(simulator, prior, fast),
        "average_energy": lambda: agents.EnergyConserving(
            LearnedModel(_STATE["average"], None, dims), params
        ),
        "prior_energy": lambda: agents.EnergyConserving(prior, params),
        "prior_energy_nominal": lambda: agents.EnergyConserving(
            prior, acrobot.AcrobotParams()
        ),
        "exact_fast_angles": lambda: Columns(prior, simulator, fast, slice(0, 2)),
        "exact_fast_velocities": lambda: Columns(prior, simulator, fast, slice(2, 4)),
        "train_sampled": lambda: SampledWeights(hip, np.random.default_rng(ss_weights)),
    }
    return {name: build[name]() for name in names}


def _job(args) -> tuple[int, int, dict[str, Any]]:
    setting, trial, seed = args
    params = _STATE["settings"][setting]
    # the i-th child does not depend on how many are spawned: ss_weights is new
    ss_env, ss_starts, ss_plan, ss_noise, ss_sample, ss_weights = (
        np.random.SeedSequence(seed[0], spawn_key=seed[1]).spawn(6)
    )
    transfer = _STATE["transfer"]
    start_env = ACROBOT.make_env(params, seed=np.random.default_rng(ss_starts))
    starts = np.array(
        [start_env.reset().observation["state"] for _ in range(transfer.n_start_states)]
    )
    task = ACROBOT.planning_task(params, transfer.planning_max_steps)
    basis = ACROBOT.basis()
    simulator = SimulatorModel(ACROBOT, params)
    names = _STATE["models"]
    models = _build_models(names, setting, params, simulator, ss_noise, ss_weights)
    out: dict[str, Any] = {"promised": {}, "delivered": {}}
    for name in names:
        # every model: the same start states, exploration stream and real instance
        rng = np.random.default_rng(ss_plan)
        state = init_state(ACROBOT.n_actions, basis.n_features, ACROBOT.initial_value)
        result = _plan(
            state, basis, models[name], task, starts,
            transfer.initial_planning_episodes, rng,
        )  # fmt: skip
        env = ACROBOT.make_env(
            params,
            seed=np.random.default_rng(ss_env),
            max_steps=transfer.max_steps,
        )
        real = [
            run_episode(env, basis, ACROBOT.sarsa, result.state, rng=rng)
            for _ in range(_STATE["real"])
        ]  # each from the planned agent, on the instance's next reset
        out["promised"][name] = float(np.mean(result.steps[-_STATE["last"] :]))
        out["delivered"][name] = float(np.mean([e.actions.shape[0] for e in real]))
    visited = np.concatenate(models["true"].states)
    actions = np.concatenate(models["true"].actions)
    rng = np.random.default_rng(ss_sample)
    keep = rng.choice(len(visited), min(_STATE["n_states"], len(visited)), False)
    visited, actions = visited[keep], actions[keep]
    true_next = simulator.predict(visited, actions)
    out["batch_distance"] = band_medians(_STATE["batch_distance"](visited), visited)
    out["energy"], out["bands"] = {}, {}
    for name in names:
        if name == "true":
            continue
        predicted = models[name].predict(visited, actions)
        out["energy"][name] = energy_terms(predicted, true_next, visited, params)
        out["bands"][name] = banded_errors(predicted, true_next, visited, params)
    return setting, trial, out


class Results(NamedTuple):
    """The file written and its content."""

    out: Path
    summary: dict[str, Any]


@one_blas_thread
def main(
    run: str | Path,
    *,
    trials: int = 2,
    models: tuple[str, ...] | None = None,
    identify: int = 1000,
    noise: float | None = None,
    fast: float = 8.0,
    n_states: int = 3000,
    last: int = 10,
    real: int = 5,
    seed: int = 456,
    workers: int = 2,
    progress: bool = True,
    out: str | Path | None = None,
) -> Results:
    """Run the check on the run folder ``run``; see the module docstring.
    ``out`` is the JSON file to write (default ``run / "energy.json"``)."""
    machine = environment()  # the code and machine as the check starts
    run = Path(run)
    check_run(run)
    # the names are the command line's
    check_counts(
        trials=trials,
        identify=identify,
        states=n_states,
        last=last,
        real=real,
        workers=workers,
    )
    check_integer("seed", seed, 0)
    path = check_out_file(run / "energy.json" if out is None else out, [run])
    if noise is not None and not (np.isfinite(noise) and noise > 0):
        raise ValueError(f"noise: expected a positive finite σ in rad/s, got {noise}")
    if not (np.isfinite(fast) and fast > 0):
        raise ValueError(f"fast: expected a positive finite |θ̇₂| in rad/s, got {fast}")
    if models is None:  # the four models, and the noisy one if it has a σ
        models = DEFAULT_MODELS + (("noisy",) if noise is not None else ())
    unknown = sorted(set(models) - set(MODELS))
    names = [m for m in MODELS if m in models]  # in MODELS' order
    if unknown or "true" not in models or len(names) < 2:
        raise ValueError(
            f"models: expected 'true' and some of {MODELS[1:]}, got {tuple(models)}"
            + (f" (unknown: {', '.join(unknown)})" if unknown else "")
        )
    if ("noisy" in names) != (noise is not None):
        raise ValueError(
            "noise: expected a σ (--noise) exactly when the models include 'noisy', "
            f"got noise={noise} with models {tuple(names)}"
        )
    config, hip, batch = read_run(run, seed)
    transfer = TransferConfig(**config["transfer"])
    if last > transfer.initial_planning_episodes:
        raise ValueError(
            f"last: expected <= the run's initial_planning_episodes "
            f"({transfer.initial_planning_episodes}), got {last}"
        )
    settings = run_test_instances(config)
    inputs_checked()  # the run read and checked; from here on, the work
    average = average_model(config, batch)
    batch_distance = BatchDistance(batch.states)
    ss_trials, ss_identify = np.random.SeedSequence(seed).spawn(2)
    beliefs = []
    for ss, params in zip(ss_identify.spawn(len(settings)), settings, strict=True):
        if "identified" not in names:
            break
        train = gather_split(
            ACROBOT, params, identify, 0, rng=np.random.default_rng(ss)
        ).train
        beliefs.append(hip.update(hip.prior(), train))
    seeds = trial_seeds(ss_trials, len(settings), trials)
    jobs = [(i, t, seeds[i][t]) for i in range(len(settings)) for t in range(trials)]
    options = dict(
        transfer=transfer,
        models=names,
        noise=noise,
        fast=fast,
        n_states=n_states,
        last=last,
        real=real,
        batch_distance=batch_distance,
    )
    done = pool_map(
        _job, jobs, workers=workers, desc="trials", progress=progress,
        initializer=_init, initargs=(settings, hip, average, beliefs, options),
    )  # fmt: skip
    shape = (len(settings), trials)

    def gather(get) -> np.ndarray:
        first = np.asarray(get(done[0][2]))
        out = np.empty(shape + first.shape)
        for i, t, o in done:
            out[i, t] = get(o)
        return out

    promised = {m: gather(lambda o, m=m: o["promised"][m]) for m in names}
    delivered = {m: gather(lambda o, m=m: o["delivered"][m]) for m in names}
    learned = [m for m in names if m != "true"]
    energy = {
        m: {k: gather(lambda o, m=m, k=k: o["energy"][m][k]) for k in TERMS}
        for m in learned
    }
    band_rmse = {m: gather(lambda o, m=m: o["bands"][m]["rmse"]) for m in learned}
    band_share = gather(lambda o: o["bands"][learned[0]]["share"])
    band_distance = gather(lambda o: o["batch_distance"])
    kinetic_share = {
        m: gather(lambda o, m=m: o["bands"][m]["kinetic_share"]) for m in learned
    }
    wrap_share = gather(lambda o: o["bands"][learned[0]]["wrap_share"])
    wrap_kinetic = {
        m: gather(lambda o, m=m: o["bands"][m]["wrap_kinetic_share"]) for m in learned
    }

    def flat(x: np.ndarray) -> np.ndarray:
        return x.reshape(-1, *x.shape[2:])

    summary: dict[str, Any] = {
        "run": str(run),
        "seed": seed,
        "trials_per_setting": trials,
        "identify_transitions": identify,
        "noise": noise,
        "fast": fast,
        "n_states": n_states,
        "last": last,
        "real_episodes": real,
        "test_masses": [list(m) for m in config["test_masses"]],
        "test_instances": to_jsonable(settings),
        "models": names,
        "promised_steps": promised,
        "delivered_steps": delivered,
        "promised_steps_mean": {m: mean_ci(flat(v)) for m, v in promised.items()},
        "delivered_steps_mean": {m: mean_ci(flat(v)) for m, v in delivered.items()},
        "delivered_minus_promised": {
            m: mean_ci(flat(delivered[m] - promised[m])) for m in names
        },
        "delivered_minus_true": {
            m: mean_ci(flat(delivered[m] - delivered["true"])) for m in learned
        },
        "energy_terms": energy,
        "energy_terms_mean": {
            m: {k: mean_ci(flat(v)) for k, v in terms.items()}
            for m, terms in energy.items()
        },
        "bands_theta2_dot": [list(BANDS[:-1]), list(BANDS[1:])],
        "band_share": flat(band_share).mean(axis=0),
        "band_batch_distance": _nanmean(flat(band_distance)),
        "band_rmse": {m: _nanmean(flat(v)) for m, v in band_rmse.items()},
        "band_kinetic_share": {
            m: flat(v).mean(axis=0) for m, v in kinetic_share.items()
        },
        "elbow_wrap_share": float(wrap_share.mean()),
        "elbow_wrap_kinetic_share": {
            m: mean_ci(flat(v)) for m, v in wrap_kinetic.items()
        },
        "environment": machine,
    }
    return Results(write_json(path, summary), summary)


def _nanmean(x: np.ndarray) -> np.ndarray:
    """Mean over axis 0 of the finite entries; NaN where there are none."""
    finite = np.isfinite(x)
    count = finite.sum(axis=0)
    total = np.where(finite, x, 0.0).sum(axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def cli(argv: list[str] | None = None) -> int:
    printable_output()
    parser = run_parser("python -m tasks.acrobot_energy", __doc__)
    parser.add_argument("--trials", type=int, default=2, help="trials per setting")
    parser.add_argument(
        "--models",
        nargs="+",
        default=None,
        help=f"'true' and some of {', '.join(MODELS[1:])} (default: "
        f"{', '.join(DEFAULT_MODELS)}, and noisy with --noise)",
    )
    parser.add_argument("--identify", type=int, default=1000, help="transitions")
    parser.add_argument(
        "--noise", type=float, default=None, help="σ of the noisy simulator, rad/s"
    )
    parser.add_argument(
        "--fast", type=float, default=8.0, help="|θ̇₂| of exact_fast/slow, rad/s"
    )
    parser.add_argument("--states", type=int, default=3000, help="states sampled")
    parser.add_argument("--last", type=int, default=10, help="planning episodes")
    parser.add_argument("--real", type=int, default=5, help="real episodes")
    parser.add_argument("--seed", type=int, default=456)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--out", default=None, help="the JSON file to write (default: RUN/energy.json)"
    )
    args = parser.parse_args(argv)
    results = run_or_exit(parser, lambda: main(
        args.run, trials=args.trials, models=args.models,
        identify=args.identify, noise=args.noise,
        fast=args.fast,
        n_states=args.states, last=args.last, real=args.real,
        seed=args.seed,
        workers=args.workers, out=args.out,
        progress=not args.no_progress,
    ))  # fmt: skip
    s = results.summary
    n = s["promised_steps_mean"]["true"]["n"]
    print(f"steps to the goal, mean [95% interval] over {n} trials")
    print(f"{'model':>11} {'promised':>24} {'delivered':>24} {'delivered - true':>24}")
    for m in s["models"]:
        diff = s["delivered_minus_true"].get(m)
        print(
            f"{m:>11} {fmt_ci(s['promised_steps_mean'][m]):>24} "
            f"{fmt_ci(s['delivered_steps_mean'][m]):>24} "
            f"{fmt_ci(diff, signed=True) if diff else '':>24}"
        )
    print("energy error of one-step predictions on the true planner's states, J/step")
    print(f"{'model':>11} " + " ".join(f"{k:>24}" for k in TERMS))
    for m, terms in s["energy_terms_mean"].items():
        cells = " ".join(f"{fmt_ci(terms[k], signed=True):>24}" for k in TERMS)
        print(f"{m:>11} {cells}")
    print(
        "RMS velocity errors (θ̇₁, θ̇₂) in rad/s by |θ̇₂| band, and the band's "
        "share of ½ εᵀ M ε"
    )
    for b, (lo, hi) in enumerate(zip(*s["bands_theta2_dot"], strict=True)):
        cells = "  ".join(
            f"{m} {r[b][0]:.3g}, {r[b][1]:.3g} ({s['band_kinetic_share'][m][b]:.0%})"
            for m, r in s["band_rmse"].items()
        )
        print(
            f"  {lo:>4g}-{hi:<4g} share {s['band_share'][b]:.3f} "
            f"batch distance {s['band_batch_distance'][b]:.3f}  {cells}"
        )
    print(
        f"steps at the elbow's wrap (within {NEAR_WRAP} rad of θ₂ = ±π, or across "
        f"it): {s['elbow_wrap_share']:.1%} of the states; their share of ½ εᵀ M ε:"
    )
    for m, d in s["elbow_wrap_kinetic_share"].items():
        print(f"{m:>11} {fmt_ci(d)}")
    print(f"wrote {results.out}")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
