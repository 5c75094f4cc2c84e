"""Is the acrobot transfer gap identification or model? A check on a finished run.

    python -m tasks.acrobot_identified runs/acrobot_swingup [--trials 10]

Reads a finished swing-up run (``config.json``, ``hipmdp_model.npz``,
``batch.npz``), refits its average model exactly as the run did, and runs the
transfer protocol (tasks/transfer.py) on the run's test settings for these variants:

- ``true``, ``average``, ``hipmdp``: the run's three methods;
- ``identified``: the HiP-MDP whose belief starts already filtered on
  ``--identify`` transitions of the test instance (gathered along a Sarsa agent's
  trajectories), instead of the prior. It plans with the instance's weights
  identified about as well as this model can, so its gap to ``true`` is what the
  model itself costs; ``hipmdp``'s gap to ``identified`` is what identifying the
  instance online costs;
- ``hipmdp_paper_filter``, ``identified_paper_filter``: the same two with the
  paper's filter (``HipMDP.update(..., model_error=False)``: the GP noise σ²
  alone), to compare the filters on the same trials;
- ``model_free``: the same agent with no planning at all (no simulated episodes
  before or between the real ones), so what planning on any model buys is the
  gap between it and ``true``;
- ``true_first``: the HiP-MDP whose initial value function comes from planning on
  the true simulator instead of its prior mean; after each real episode it filters
  and plans on the posterior-mean HiP-MDP as usual. Its gap to ``true`` is what
  the planning between episodes costs; ``hipmdp``'s gap to it is what the
  initial planning on the prior-mean model costs;
- ``hipmdp_replan``: the HiP-MDP, whose value function is discarded after the
  first real episode and planned again from scratch on the posterior-mean model,
  with as many simulated episodes as the initial planning (or ``--first-planning
  N``): the protocol with the first planning done after one episode has
  identified the instance (``TransferConfig.replan_after_first``). Its gap to
  ``hipmdp`` from the second episode on is what the first planning on the prior
  mean costs once the instance is identified online;
- ``average_energy``, ``hipmdp_energy``: the average model and the HiP-MDP, each
  planning on its predictions with the velocities rescaled so that every step
  changes the energy by the elbow torque's work
  (:class:`tasks.agents.EnergyConserving`) of the test instance (its true masses
  and lengths: information no learned model has); ``*_energy_nominal`` with the
  nominal acrobot's instead.

``--first-planning N`` gives every variant ``N`` simulated episodes after the first
real one instead of the run's ``planning_episodes`` (not the paper's protocol).
``--initial-planning N`` gives every variant ``N`` simulated episodes before the
first real one instead of the run's ``initial_planning_episodes`` (the paper does
not state this number; a check of how the comparison depends on it).
Every variant runs on the same (setting, trial) seeds, spawned from ``--seed``;
they differ from the run's own trial seeds, unless ``--run-seeds`` gives the
trials the run's own: then ``true``, ``average`` and ``hipmdp`` replay the run's
first ``--trials`` trials of each setting (a check that the code still does what
the run did). Prints the mean return per episode
with its standard error, the median and the share of episodes that ran to the step
limit (these heavy-tailed failures move the means most), and writes
``identified.json`` in the run folder: per variant the returns (trials × episodes),
the mean curve with 95% intervals, medians, step-limit shares, and paired
differences (each trial's mean return over its episodes, with 95% intervals)
against ``true`` and between the two filters.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

import hipmdp
from hipmdp import baselines
from hipmdp.data import is_real_number, wrap_angle
from tasks import transfer
from tasks.acrobot import AcrobotParams
from tasks.acrobot_swingup import run_streams, run_test_instances
from tasks.agents import ACROBOT, EnergyConserving, SimulatorModel
from tasks.experiment import (
    check_counts,
    check_integer,
    check_out_file,
    environment,
    fmt_bounds,
    inputs_checked,
    mean_ci,
    one_blas_thread,
    paired_difference,
    pool_map,
    printable_output,
    read_json_object,
    run_or_exit,
    run_parser,
    to_jsonable,
    trial_seeds,
    with_added_fields,
    write_json,
)
from tasks.prediction import gather_split

VARIANTS = (
    "true",
    "average",
    "hipmdp",
    "identified",
    "hipmdp_paper_filter",
    "identified_paper_filter",
    "model_free",
    "true_first",
    "hipmdp_replan",
    "average_energy",
    "hipmdp_energy",
    "average_energy_nominal",
    "hipmdp_energy_nominal",
)


class _Identified:
    """The fitted HiP-MDP with ``prior()`` replaced by a given belief (if not None)
    and ``update`` filtering with or without the model error."""

    def __init__(self, hip, belief, model_error: bool = True) -> None:
        self._hip, self._belief, self._model_error = hip, belief, model_error

    def prior(self):
        return self._hip.prior() if self._belief is None else self._belief

    def update(self, belief, data):
        return self._hip.update(belief, data, model_error=self._model_error)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._hip, name)


class _TrueFirst(_Identified):
    """The HiP-MDP whose prior belief, until the first update, predicts with the
    instance's true simulator (``mean_predictor``); every other belief predicts
    with the HiP-MDP. The prior is a real belief, so filtering starts from it."""

    def __init__(self, hip, params) -> None:
        super().__init__(hip, None)
        self._first = hip.prior()
        self._true = SimulatorModel(ACROBOT, params)

    def prior(self):
        return self._first

    def mean_predictor(self, belief):
        if belief is not self._first:
            return self._hip.mean_predictor(belief)

        def true_delta(states, actions):
            delta = self._true.predict(states, actions) - states
            dims = list(ACROBOT.angle_dims)
            delta[:, dims] = wrap_angle(delta[:, dims])
            return delta

        return true_delta


_STATE: dict[str, Any] = {}


def _init(config: transfer.TransferConfig, hip, average, beliefs) -> None:
    _STATE.update(config=config, hip=hip, average=average, beliefs=beliefs)


def _job(args) -> tuple[str, int, int, np.ndarray]:
    variant, setting, trial, params, seed = args
    model, config = _STATE["hip"], _STATE["config"]
    base, energy = variant, None  # e.g. hipmdp_energy_nominal: hipmdp, "nominal"
    for suffix, kind in (("_energy_nominal", "nominal"), ("_energy", "instance")):
        if variant.endswith(suffix):
            base, energy = variant.removesuffix(suffix), kind
            break
    if variant == "model_free":  # the true model's trial, with nothing planned
        config = dataclasses.replace(
            config, planning_episodes=0, initial_planning_episodes=0
        )
    elif variant == "true_first":
        model = _TrueFirst(model, params)
    elif variant == "hipmdp_replan":
        first = config.first_planning_episodes
        config = dataclasses.replace(
            config,
            replan_after_first=True,
            first_planning_episodes=(
                config.initial_planning_episodes if first is None else first
            ),
        )
    elif base not in ("true", "average"):
        paper = variant.endswith("_paper_filter")
        belief = None
        if variant.startswith("identified"):
            belief = _STATE["beliefs"]["paper" if paper else "model"][setting]
        model = _Identified(model, belief, model_error=not paper)
    wrapper = None
    if energy is not None:  # the constraint of the instance, or of the nominal one

        def wrapper(model, params):
            return EnergyConserving(
                model, AcrobotParams() if energy == "nominal" else params
            )

    # the trial reads its models from what set_models installed in this process
    transfer.set_models(ACROBOT, config, model, _STATE["average"], wrapper)
    method = {"average": "average", "true": "true", "model_free": "true"}.get(
        base, "hipmdp"
    )
    job = transfer.TrialJob(method, setting, trial, params, seed, False)
    return variant, setting, trial, transfer.run_trial(job).returns


class Results(NamedTuple):
    out: Path
    returns: dict[str, np.ndarray]
    summary: dict[str, Any]


def check_run(run: Path) -> None:
    """Raise FileNotFoundError unless ``run`` holds what the checks read of a
    swing-up run: its config, batch data and fitted model. A run still in its
    transfer trials (or killed there) has them all, complete (each is written
    whole, atomically, before the trials start), so the checks accept it."""
    for name in ("config.json", "hipmdp_model.npz", "batch.npz"):
        if not (run / name).is_file():
            raise FileNotFoundError(f"run: {run} has no {name}; is it a swing-up run?")


class RunFiles(NamedTuple):
    """What :func:`read_run` reads: ``config.json``, the HiP-MDP and the batch
    data."""

    config: dict[str, Any]
    hip: Any
    batch: hipmdp.Transitions


class FinishedRun(NamedTuple):
    """What :func:`load_run` reads: ``config.json``, the HiP-MDP, the average model
    and the batch data."""

    config: dict[str, Any]
    hip: Any
    average: Any
    batch: hipmdp.Transitions


def read_run(run: Path, seed: int | None = None) -> RunFiles:
    """A finished run's config, HiP-MDP and batch data, as its files hold them,
    and the config's settings for the average model checked (an error names the
    file): the checks' input, read before their work.

    ``seed``, a check's own: refused if it is the run's, whose first streams
    (``SeedSequence(seed).spawn``) the run drew its batch data and fit from, so
    the check's would repeat them for another purpose.

    The model must have been fitted on the batch data (:func:`check_model_data`):
    a ``batch.npz`` or ``hipmdp_model.npz`` copied from another run is refused.
    A model fitted before models recorded their data's digest is checked on its
    instance ids and number of transitions alone (another seed's run has the
    same ids and may have the same number)."""
    config = read_run_config(run)
    if seed is not None and seed == config.get("seed"):
        raise ValueError(
            f"seed: {seed} is the run's own seed (its streams made the run's batch "
            "data and fit; a check spawned from it would reuse them); choose another"
        )
    hip = hipmdp.load(run / "hipmdp_model.npz")
    batch = hipmdp.Transitions.load(run / "batch.npz")
    check_model_data(hip, batch, run / "hipmdp_model.npz", run / "batch.npz")
    try:  # the config is checked; what is left is its fit against the batch
        _average_settings(config, batch)  # (e.g. periodic kernels, no angle_dims)
    except ValueError as err:
        raise ValueError(
            f"{run / 'config.json'}: not a swing-up run's config: {err}"
        ) from err
    return RunFiles(config, hip, batch)


#: The fields of a swing-up run's config.json that the checks read.
RUN_CONFIG_FIELDS = (
    "seed", "fit", "average_n_max", "n_trials", "transfer", "test_masses",
)  # fmt: skip


def read_run_config(run: Path) -> dict[str, Any]:
    """``run``'s ``config.json``, checked to be a swing-up run's as far as the
    checks read it, before any work: an object with the ``RUN_CONFIG_FIELDS``,
    ``seed`` an integer >= 0, ``average_n_max`` and ``n_trials`` integers >= 1,
    ``fit`` and ``transfer`` objects of ``hipmdp.FitConfig`` and
    ``TransferConfig`` fields with valid values (an older run's missing fields
    take the values it ran with), ``test_masses`` a list of ``[m1, m2]`` masses
    > 0 and ``book_inertia``, if there, a boolean. Other fields are not read and
    not checked. Raises ValueError naming the file and the field (a file that is
    not JSON or not an object too)."""
    path = run / "config.json"
    config = read_json_object(path)
    try:
        _check_run_config(config)
    except ValueError as err:
        raise ValueError(f"{path}: not a swing-up run's config: {err}") from None
    return config


def _check_run_config(config: dict[str, Any]) -> None:
    missing = [name for name in RUN_CONFIG_FIELDS if name not in config]
    if missing:
        raise ValueError(f"{', '.join(missing)}: missing")
    check_integer("seed", config["seed"], 0)
    check_integer("average_n_max", config["average_n_max"], 1)
    check_integer("n_trials", config["n_trials"], 1)
    for name, value, kind in (
        ("fit", with_added_fields(config)["fit"], hipmdp.fitting.FitConfig),
        ("transfer", config["transfer"], transfer.TransferConfig),
    ):
        if not isinstance(value, dict):
            raise ValueError(
                f"{name}: expected an object of {kind.__name__} fields, got {value!r}"
            )
        unknown = sorted(set(value) - {f.name for f in dataclasses.fields(kind)})
        if unknown:
            raise ValueError(f"{name}: unknown {kind.__name__} fields {unknown}")
        try:
            kind(**value)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{name}: {err}") from None
    masses = config["test_masses"]
    if not isinstance(masses, list) or not masses:
        raise ValueError(f"test_masses: expected a list of [m1, m2], got {masses!r}")
    for i, pair in enumerate(masses):
        if not (
            isinstance(pair, list)
            and len(pair) == 2
            and all(is_real_number(m) and np.isfinite(m) and m > 0 for m in pair)
        ):
            raise ValueError(
                f"test_masses[{i}]: expected a pair [m1, m2] of masses > 0 (kg), "
                f"got {pair!r}"
            )
    book = config.get("book_inertia", False)  # runs before it had the default
    if not isinstance(book, bool):
        raise ValueError(f"book_inertia: expected true or false, got {book!r}")


def check_model_data(hip, batch: hipmdp.Transitions, model_file, batch_file) -> None:
    """Raise ValueError, naming both files, unless the model ``hip`` (read from
    ``model_file``) was fitted on ``batch`` (read from ``batch_file``): its
    training instance ids, number of transitions and the digest of the data's
    arrays (``info["data_sha256"]``, :meth:`hipmdp.Transitions.sha256`) must be
    the batch's. A model fitted before the digest was recorded is checked on
    the ids and number alone."""
    differs = f"{model_file} was not fitted on {batch_file}"
    advice = "; were the files copied from different runs?"
    fitted = np.sort(hip.instance_ids)  # the model's columns, in any order
    if not np.array_equal(fitted, batch.instance_ids):
        raise ValueError(
            f"{differs}: the model's training instances {fitted.tolist()} are not "
            f"the batch's {batch.instance_ids.tolist()}{advice}"
        )
    n = hip.info.get("n_transitions")
    if n is not None and n != len(batch):
        raise ValueError(
            f"{differs}: the model was fitted on {n} transitions, the batch holds "
            f"{len(batch)}{advice}"
        )
    recorded = hip.info.get("data_sha256")
    if recorded is not None and recorded != (digest := batch.sha256()):
        raise ValueError(
            f"{differs}: the SHA-256 of the model's data ({recorded}) is not that "
            f"of the batch's ({digest}){advice}"
        )


def _average_settings(config: dict[str, Any], batch: hipmdp.Transitions) -> dict:
    """:func:`average_model`'s arguments to ``baselines.batch_only``, from the
    run's config as the run derived them."""
    fit = hipmdp.FitConfig(**with_added_fields(config)["fit"])  # read_run checked
    return {
        "rng": np.random.default_rng(run_streams(config["seed"]).average),
        "n_max": config["average_n_max"],
        "periodic": fit.periodic_dims(batch),
    }


def average_model(config: dict[str, Any], batch: hipmdp.Transitions):
    """The run's average model, refitted exactly as the run fitted it (the same
    data, seed and size): seconds of work, so the checks call it after
    :func:`tasks.experiment.inputs_checked`."""
    return baselines.batch_only(batch, **_average_settings(config, batch))


def load_run(run: Path) -> FinishedRun:
    """A finished run's config, its HiP-MDP, its average model refitted exactly as
    the run fitted it (:func:`average_model`), and its batch data."""
    config, hip, batch = read_run(run)
    return FinishedRun(config, hip, average_model(config, batch), batch)


@one_blas_thread
def main(
    run: str | Path,
    *,
    variants: tuple[str, ...] = VARIANTS,
    trials: int = 10,
    episodes: int = 3,
    identify: int = 1000,
    first_planning: int | None = None,
    initial_planning: int | None = None,
    seed: int = 123,
    run_seeds: bool = False,
    workers: int = 2,
    progress: bool = True,
    out: str | Path | None = None,
) -> Results:
    """Run the check on the run folder ``run``; see the module docstring.
    ``out`` is the JSON file to write (default ``run / "identified.json"``).
    ``run_seeds``: the trials take the run's own (setting, trial) seeds instead of
    seeds spawned from ``seed`` (which then seeds only the identification data),
    so ``true``, ``average`` and ``hipmdp`` replay the run's first trials.
    ``first_planning``, ``initial_planning``: every variant's simulated episodes
    after the first real one and before it (None: the run's)."""
    machine = environment()  # the code and machine as the check starts
    run = Path(run)
    check_run(run)
    out_path = check_out_file(run / "identified.json" if out is None else out, [run])
    unknown = set(variants) - set(VARIANTS)
    if unknown or not variants or len(set(variants)) != len(variants):
        # a repeated variant ran its trials twice and counted them as more trials
        raise ValueError(
            f"variants: expected some of {VARIANTS}, each once, got {variants}"
        )
    check_counts(trials=trials, episodes=episodes, identify=identify, workers=workers)
    check_integer("seed", seed, 0)
    for name, value in (
        ("first_planning", first_planning),
        ("initial_planning", initial_planning),
    ):
        if value is not None and value < 0:
            raise ValueError(f"{name}: expected >= 0 or None, got {value}")
    config, hip, batch = read_run(run, seed)
    if run_seeds and trials > config["n_trials"]:
        raise ValueError(
            f"trials: expected at most the run's {config['n_trials']} trials per "
            f"setting with run_seeds, got {trials}"
        )
    instances = run_test_instances(config)
    protocol = dataclasses.replace(
        transfer.TransferConfig(**config["transfer"]), n_episodes=episodes
    )
    inputs_checked()  # the run read and checked; from here on, the work
    average = average_model(config, batch)
    if first_planning is not None:  # every variant: the comparison stays paired
        protocol = dataclasses.replace(protocol, first_planning_episodes=first_planning)
    if initial_planning is not None:
        protocol = dataclasses.replace(
            protocol, initial_planning_episodes=initial_planning
        )

    ss_trials, ss_identify = np.random.SeedSequence(seed).spawn(2)
    beliefs: dict[str, list] = {"model": [], "paper": []}
    if any(v.startswith("identified") for v in variants):
        for params_seed, params in zip(
            ss_identify.spawn(len(instances)), instances, strict=True
        ):
            split = gather_split(
                ACROBOT,
                params,
                identify,
                0,
                rng=np.random.default_rng(params_seed),
            )
            for key, model_error in (("model", True), ("paper", False)):
                beliefs[key].append(
                    hip.update(hip.prior(), split.train, model_error=model_error)
                )
    if run_seeds:  # the run's: tasks.acrobot_swingup.run_transfer's layout
        seeds = trial_seeds(
            run_streams(config["seed"]).trials, len(instances), config["n_trials"]
        )
    else:
        seeds = trial_seeds(ss_trials, len(instances), trials)
    jobs = [
        (v, i, t, params, seeds[i][t])
        for v in variants
        for i, params in enumerate(instances)
        for t in range(trials)
    ]
    done = pool_map(
        _job, jobs, workers=workers, desc="trials", progress=progress,
        initializer=_init, initargs=(protocol, hip, average, beliefs),
    )  # fmt: skip
    returns = {v: np.array([r for (vv, _, _, r) in done if vv == v]) for v in variants}
    out: dict[str, Any] = {
        "run": str(run),
        "test_instances": to_jsonable(instances),
        "seed": seed,
        "trial_seeds": "the run's" if run_seeds else "spawned from seed",
        "trials_per_setting": trials,
        "identify_transitions": identify,
        "first_planning_episodes": protocol.first_planning_episodes,
        "initial_planning_episodes": protocol.initial_planning_episodes,
        "returns": returns,
        "curves": {v: mean_ci(r, axis=0) for v, r in returns.items()},
        "median": {v: np.median(r, axis=0) for v, r in returns.items()},
        "step_limit_rate": {
            v: np.mean(r <= -protocol.max_steps, axis=0) for v, r in returns.items()
        },
    }
    if "true" in variants:
        out["paired_difference_to_true"] = {
            v: paired_difference(r, returns["true"])
            for v, r in returns.items()
            if v != "true"
        }
    pairs = [(v, f"{v}_paper_filter") for v in ("hipmdp", "identified")]
    out["paired_difference_model_error_minus_paper_filter"] = {
        v: paired_difference(returns[v], returns[paper])
        for v, paper in pairs
        if v in returns and paper in returns
    }
    out["environment"] = machine
    path = write_json(out_path, out)
    return Results(path, returns, out)


def cli(argv: list[str] | None = None) -> int:
    printable_output()
    parser = run_parser("python -m tasks.acrobot_identified", __doc__)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    parser.add_argument("--trials", type=int, default=10, help="trials per setting")
    parser.add_argument("--episodes", type=int, default=3, help="real episodes")
    parser.add_argument("--identify", type=int, default=1000, help="transitions")
    parser.add_argument(
        "--first-planning",
        type=int,
        default=None,
        help="simulated episodes after the first real one, for every variant "
        "(default: the run's planning episodes, as after every other)",
    )
    parser.add_argument(
        "--initial-planning",
        type=int,
        default=None,
        help="simulated episodes before the first real one, for every variant "
        "(default: the run's initial planning episodes)",
    )
    parser.add_argument("--seed", type=int, default=123)
    parser.add_argument(
        "--run-seeds",
        action="store_true",
        help="the trials take the run's own seeds (true, average and hipmdp then "
        "replay the run's first trials); --seed seeds only the identification",
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--out",
        default=None,
        help="the JSON file to write (default: RUN/identified.json)",
    )
    args = parser.parse_args(argv)
    results = run_or_exit(parser, lambda: main(
        args.run, variants=tuple(args.variants), trials=args.trials,
        episodes=args.episodes, identify=args.identify,
        first_planning=args.first_planning,
        initial_planning=args.initial_planning, seed=args.seed,
        run_seeds=args.run_seeds, workers=args.workers, out=args.out,
        progress=not args.no_progress,
    ))  # fmt: skip
    for v, r in results.returns.items():
        if len(r) > 1:
            se = r.std(axis=0, ddof=1) / np.sqrt(len(r))
            cells = ", ".join(
                f"{m:.1f} ± {s:.1f}" for m, s in zip(r.mean(axis=0), se, strict=True)
            )
            what = f"mean ± s.e. per episode, {len(r)} trials"
        else:  # no standard error of one sample ("± 0.0" read as certainty)
            cells = ", ".join(f"{m:.1f}" for m in r[0])
            what = "per episode, one trial: no standard error"
        print(f"{v:>23}: {cells}   ({what})")
    for key, what in (("median", "median"), ("step_limit_rate", "step-limit share")):
        for v, x in results.summary[key].items():
            cells = ", ".join(f"{c:.3g}" for c in x)
            print(f"{v:>23}: {cells}   ({what} per episode)")
    pairs = [("paired_difference_to_true", "true")]
    pairs += [("paired_difference_model_error_minus_paper_filter", "paper filter")]
    for key, other in pairs:
        for v, d in results.summary.get(key, {}).items():
            a = d["all_episodes"]
            print(
                f"{v:>23} - {other}: {a['mean']:+.1f} "
                f"{fmt_bounds(a['low'], a['high'], lambda x: f'{x:.1f}')}"
                "   (paired, over all episodes)"
            )
    print(f"wrote {results.out}")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
