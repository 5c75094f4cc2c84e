"""Acrobot swing-up transfer (the paper's acrobot experiment), the main job.

    python -m tasks.acrobot_swingup                   # --preset quick, minutes
    python -m tasks.acrobot_swingup --preset paper    # 16 test settings x 30 trials

1. Batch data: on each of the 8 training mass settings, Sarsa(λ) agents with an
   order-5 Fourier basis learn the swing-up; every transition they see is kept.
2. Models: the HiP-MDP is fitted to the batch data; the average model is one GP on
   all of it.
3. Transfer (tasks/transfer.py): on each test setting, repeated trials of Sarsa with
   model-based planning on the HiP-MDP (belief filtered after each episode, planning
   on the posterior-mean model before the next), on the average model and on the
   true simulator — the same instances and seeds for all three.
4. One-step prediction (tasks/prediction.py): MSE of Δs per dimension for the
   HiP-MDP and the three GP baselines on the test settings, and the approximation
   floor on training settings.

Writes ``runs/<name>/``: config.json, metrics.json, report.md, learning_curves.png,
weights.png, acrobot.rrd (``RERUN=off`` skips it), hipmdp_model.npz (read it with
``hipmdp.load``), batch.npz (``hipmdp.Transitions.load``) and trials.npz (every
trial's returns and steps per episode, see :func:`trial_arrays`).
All randomness is spawned from ``--seed``.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

import hipmdp
from hipmdp import baselines
from hipmdp.data import atomic_write, npz_bytes
from tasks.acrobot import AcrobotParams, book_inertia
from tasks.agents import ACROBOT
from tasks.batch import gather_and_save
from tasks.experiment import (
    apply_common,
    by_preset,
    check_positive,
    check_run_fields,
    check_settings,
    common_parser,
    environment,
    first_episode_within,
    flag_error,
    margin_to_target,
    mean_ci,
    one_blas_thread,
    paired_difference,
    pool_map,
    printable_output,
    releases_run_folders,
    run_dir,
    stops_reported,
    to_jsonable,
    trial_seeds,
    write_json,
    writes_metrics,
    wrote_line,
)
from tasks.methods import (
    add_method_argument,
    check_specs,
    fit_all,
    load_all,
    must_pickle,
    provenance,
)
from tasks.prediction import (
    add_split_argument,
    check_split,
    score_settings,
    summarise,
)
from tasks.recording import resolve_record
from tasks.transfer import (
    METHODS,
    TransferConfig,
    TrialJob,
    run_trial,
    set_models,
    trial_label,
)

# The paper's settings (m1, m2); the test grid is DESIGN's corrected one.
TRAIN_MASSES = (
    (0.7, 0.7), (0.7, 1.3), (0.9, 0.7), (0.9, 1.1),
    (1.1, 0.9), (1.1, 1.3), (1.3, 0.7), (1.3, 1.3),
)  # fmt: skip
TEST_MASSES = tuple(
    (m1, m2) for m1 in (0.7, 0.9, 1.1, 1.3) for m2 in (0.7, 0.9, 1.1, 1.3)
)
# quick preset: four test settings that are not training settings, one per m1
QUICK_TEST_MASSES = ((0.7, 0.9), (0.9, 1.3), (1.1, 0.7), (1.3, 1.1))
# paired comparisons in metrics.json: "clearly ahead" is a paired interval above 0
PAIRS = (("hipmdp", "average"), ("hipmdp", "true"), ("average", "true"))


def run_methods(config: SwingupConfig) -> tuple[str, ...]:
    """The transfer's methods: the three of METHODS, then those added with
    ``--method`` (``config.methods``), by name."""
    return METHODS + tuple(spec.name for spec in check_specs(config.methods))


def run_pairs(config: SwingupConfig) -> tuple[tuple[str, str], ...]:
    """PAIRS, then for each added method: the HiP-MDP against it, it against the
    average model (transfer against none), and it against the true model."""
    added = run_methods(config)[len(METHODS) :]
    return PAIRS + tuple(
        p for m in added for p in (("hipmdp", m), (m, "average"), (m, "true"))
    )


DIM_NAMES = ("dtheta1", "dtheta2", "dtheta1_dot", "dtheta2_dot")


def setting_params(m1: float, m2: float, book: bool = False) -> AcrobotParams:
    """The swing-up's instance at link masses ``(m1, m2)`` kg, both links 1 m long
    (the paper's test and training settings vary the masses only).

    Each link's moment of inertia about its centre of mass follows its mass,
    ``I = m l²`` (DESIGN §6), or with ``book`` stays at the book's 1 kg·m²
    (``tasks.acrobot.book_inertia``).
    """
    if book:
        return book_inertia(m1, m2, 1.0, 1.0)
    return AcrobotParams(
        link_mass_1=m1, link_mass_2=m2, link_length_1=1.0, link_length_2=1.0
    )


def run_test_instances(config: dict[str, Any]) -> list[AcrobotParams]:
    """The test instances of a finished run, from its ``config.json`` as a dict
    (runs written before ``book_inertia`` existed had the default)."""
    book = config.get("book_inertia", False)
    return [setting_params(*mm, book) for mm in config["test_masses"]]


#: The most trials per method a run takes, over its test settings (a trial takes
#: seconds; the paper preset runs 480).
MAX_TRIALS = 100_000


@dataclasses.dataclass(frozen=True)
class SwingupConfig:
    """Everything a run depends on (written to config.json).

    Attributes:
        name: the run folder under ``runs/`` (unless ``out`` is given).
        preset: the preset these values came from.
        seed: the one seed every random stream is spawned from.
        train_masses, test_masses: (m1, m2) settings, kg; lengths stay 1 m.
        book_inertia: each link's moment of inertia about its centre of mass
            stays at the book's 1 kg·m² as its mass changes (``--book-inertia``),
            as in the book's equations with only the masses rewritten (the paper
            names the book's acrobot and the masses, not the inertias); by
            default it follows the mass, ``I = m l²`` (DESIGN §6).
        batch_repetitions, batch_episodes, batch_max_steps: Sarsa agents per
            training setting, episodes per agent, step limit of those episodes.
        fit: HiP-MDP settings.
        average_n_max: transitions per action in the average-model GP (also
            the prediction table's batch only); the table's batch + train takes
            at most 2,000 per action, the train transitions and batch ones for
            the rest (score_instance's default, where the cart-pole passes its
            average_n_max; README, "Experiments").
        n_trials: trials per test setting.
        transfer: sizes of the transfer protocol.
        mse_train, mse_test: transitions per instance for the prediction table.
        split: ``"random"`` (our reading of the paper's) or ``"time"``: how a
            test setting's transitions are split into train and test
            (``gather_split``).
        methods: your own methods, run in the transfer trials and (models, not
            policies) scored in the prediction tables beside the others, as
            ``"NAME=module:attribute"`` (``tasks.methods``).
        n_floor_settings: training settings scored for the approximation floor.
        final_window: the true model's "final" return is its mean over this many
            last episodes (an episode that fails at the step limit moves one
            episode's mean by tens of steps; see metrics.json's near_optimal_target).
        workers: processes for batch data and trials.
        record: write the rerun recording (``RERUN=off`` also disables it).
        progress: progress bars.
    """

    name: str = "acrobot_swingup"
    preset: str = "quick"
    seed: int = 0
    train_masses: tuple[tuple[float, float], ...] = TRAIN_MASSES
    test_masses: tuple[tuple[float, float], ...] = QUICK_TEST_MASSES
    book_inertia: bool = False
    # 2 agents per training setting: with 1, states the test agents reach fell
    # outside the batch data more often, where the HiP-MDP's weighted sum of
    # features extrapolates worse than one GP (its prior-mean model then started
    # planning behind the average model)
    batch_repetitions: int = 2
    batch_episodes: int = 20
    batch_max_steps: int = 500
    fit: hipmdp.FitConfig = hipmdp.FitConfig(
        n_support=500, n_sweeps=60, n_chains=1, progress=False
    )
    average_n_max: int = 1500
    # 12 trials of 6 episodes rather than 6 of 8 (about the same time): returns
    # are heavy-tailed (an episode that runs to the step limit is -500 against
    # ~-110), so the mean curves need the trials more than the episodes
    n_trials: int = 12
    transfer: TransferConfig = TransferConfig(
        n_episodes=6, planning_episodes=5, initial_planning_episodes=20
    )
    mse_train: int = 50
    mse_test: int = 50
    split: str = "random"
    methods: tuple[str, ...] = ()
    n_floor_settings: int = 2
    final_window: int = 3
    workers: int = 2
    record: bool = True
    progress: bool = True

    def __post_init__(self) -> None:
        check_run_fields(self)
        if not isinstance(self.transfer, TransferConfig):
            raise ValueError(
                f"transfer: expected a tasks.transfer.TransferConfig, "
                f"got {type(self.transfer).__name__}"
            )
        if not isinstance(self.book_inertia, bool):
            raise ValueError(
                f"book_inertia: expected a bool, got {self.book_inertia!r}"
            )
        check_settings(self, "train_masses", "test_masses", self.params, "(m1, m2)")
        check_positive(self, (
            "batch_repetitions", "batch_episodes", "batch_max_steps", "average_n_max",
            "n_trials", "mse_train", "mse_test", "workers", "final_window",
        ))  # fmt: skip
        check_split(self.split)
        check_specs(self.methods)
        n = len(self.test_masses) * self.n_trials
        if n > MAX_TRIALS:  # hung seeding them, after the batch data and fit
            raise ValueError(
                f"n_trials: expected at most {MAX_TRIALS:,} trials per method over "
                f"the {len(self.test_masses)} test settings, got {n:,}"
            )
        if self.final_window > self.transfer.n_episodes:
            raise ValueError(
                f"final_window: expected <= transfer.n_episodes "
                f"({self.transfer.n_episodes}), got {self.final_window}"
            )
        if not 0 <= self.n_floor_settings <= len(self.train_masses):
            raise ValueError(
                f"n_floor_settings: expected 0..{len(self.train_masses)}, "
                f"got {self.n_floor_settings}"
            )

    def params(self, m1: float, m2: float) -> AcrobotParams:
        """The instance at link masses ``(m1, m2)`` with this run's inertias."""
        return setting_params(m1, m2, self.book_inertia)


#: Every file a run writes in its folder (glob patterns); `main` deletes a
#: previous run's before it starts (`tasks.experiment.run_dir`).
ARTEFACTS = (
    "config.json", "batch.npz", "hipmdp_model.npz", "trials.npz", "metrics.json",
    "report.md", "learning_curves.png", "weights.png", "acrobot.rrd",
)  # fmt: skip

PRESETS: dict[str, SwingupConfig] = {
    "quick": SwingupConfig(),  # 4 settings x 12 trials: 2-8 minutes on two cores
    "paper": SwingupConfig(
        preset="paper",
        test_masses=TEST_MASSES,
        batch_repetitions=5,
        batch_episodes=30,
        fit=hipmdp.FitConfig(n_support=1000, n_sweeps=250, n_chains=3, progress=False),
        average_n_max=3000,
        n_trials=30,
        transfer=TransferConfig(
            n_episodes=20, planning_episodes=5, initial_planning_episodes=50
        ),
        n_floor_settings=8,
    ),
}


class RunStreams(NamedTuple):
    """The run's random streams, spawned in this order from its one seed: batch
    data, HiP-MDP fit, average model, transfer trials, prediction table. The
    checks on a finished run (``tasks.acrobot_refit``, ``load_run``) take theirs
    from here to redo exactly what the run did."""

    batch: np.random.SeedSequence
    fit: np.random.SeedSequence
    average: np.random.SeedSequence
    trials: np.random.SeedSequence
    mse: np.random.SeedSequence


def run_streams(seed: int) -> RunStreams:
    """:class:`RunStreams` of the run with seed ``seed`` (fresh objects: spawning
    from them gives the run's own children)."""
    return RunStreams(*np.random.SeedSequence(seed).spawn(len(RunStreams._fields)))


class Results(NamedTuple):
    """What ``main`` returns: the run folder and the metrics written there."""

    out: Path
    metrics: dict[str, Any]


def run_transfer(
    config, hip, average, ss: np.random.SeedSequence, added: tuple = ()
) -> list:
    """Every (method, test setting, trial) trial, the ``added`` methods'
    (``tasks.methods.Added``) too; the seeds depend on (setting, trial) only.
    Setting 0, trial 0 is traced for the recording."""
    seeds = trial_seeds(ss, len(config.test_masses), config.n_trials)
    jobs = [
        TrialJob(
            method=method,
            setting=i,
            trial=t,
            params=config.params(*masses),
            seed=seeds[i][t],
            record=config.record and i == 0 and t == 0,
        )
        for i, masses in enumerate(config.test_masses)
        for t in range(config.n_trials)
        for method in run_methods(config)
    ]
    return pool_map(
        run_trial, jobs, workers=config.workers, desc="transfer trials",
        progress=config.progress, initializer=set_models,
        initargs=(ACROBOT, config.transfer, hip, average, None, added),
        label=trial_label,
    )  # fmt: skip


def prediction_table(config, hip, average, batch, ss, added=()) -> dict[str, Any]:
    """The one-step MSE table on test settings (table 0 of the ``added``
    methods' keys), and the floor on training ones (table 1)."""
    groups = {
        "test": config.test_masses,
        "floor": config.train_masses[: config.n_floor_settings],
    }
    out, train = {}, set(config.train_masses)
    for table, ((label, masses), seed) in enumerate(
        zip(groups.items(), ss.spawn(2), strict=True)
    ):
        scores = score_settings(
            ACROBOT, [hip], average, batch, [config.params(*mm) for mm in masses],
            n_train=config.mse_train, n_test=config.mse_test, seed=seed,
            split=config.split, desc=f"prediction ({label})",
            progress=config.progress, added=added, table=table,
        )  # fmt: skip
        seen = [tuple(mm) in train for mm in masses]
        out[label] = summarise(scores, DIM_NAMES, seen) if scores else None
    return out


@one_blas_thread
@releases_run_folders
def main(config: SwingupConfig, out: str | os.PathLike | None = None) -> Results:
    """Run the whole experiment and write its artefacts; see the module docstring."""
    from tasks import swingup_report

    started = time.perf_counter()
    config = resolve_record(config)  # RERUN=off: no recording, and config.json says so
    machine = environment()  # the code and machine as the run starts
    # a bad one fails here, before any work
    loaded = load_all(config.methods, policies=True)
    if loaded:  # which code the added methods are
        machine["methods"] = provenance(loaded)
    path = run_dir(out, config.name, ARTEFACTS)
    write_json(path / "config.json", config)
    ss_batch, ss_fit, ss_avg, ss_trials, ss_mse = run_streams(config.seed)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    train = [config.params(*mm) for mm in config.train_masses]
    batch = gather_and_save(
        "acrobot", train, path / "batch.npz",
        config=config, seed=ss_batch, progress=config.progress,
    )  # fmt: skip
    timings["batch_data"] = time.perf_counter() - t0

    t0 = time.perf_counter()  # first, so that a method that breaks does so early
    added = fit_all(
        loaded, batch, config.seed, n_actions=ACROBOT.n_actions,
        pickled=must_pickle(config.workers), transfer=True,
    )  # fmt: skip
    timings["added_methods"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    fit_config = dataclasses.replace(config.fit, progress=config.progress)
    hip = hipmdp.fit(batch, fit_config, rng=np.random.default_rng(ss_fit))
    hip.save(path / "hipmdp_model.npz")
    timings["fit"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    average = baselines.batch_only(
        batch,
        rng=np.random.default_rng(ss_avg),
        n_max=config.average_n_max,
        periodic=config.fit.periodic_dims(batch),
    )
    timings["average_model"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    trials = run_transfer(config, hip, average, ss_trials, added)
    timings["transfer"] = time.perf_counter() - t0
    # now, so that the trials outlive a failure in the prediction table (an added
    # method's predict on more transitions than its try's)
    arrays = trial_arrays(config, trials)
    atomic_write(
        path / "trials.npz", lambda fh: fh.write(npz_bytes(arrays)), clean=True
    )

    t0 = time.perf_counter()
    models = tuple(a for a in added if not a.is_policy)  # policies do not predict
    mse = prediction_table(config, hip, average, batch, ss_mse, models)
    timings["prediction"] = time.perf_counter() - t0

    metrics = transfer_metrics(config, trials)
    metrics.update(
        mse=mse["test"]["mse"],
        loglik_difference=mse["test"]["loglik_difference"],
        coverage=mse["test"]["coverage"],
        mse_ratio_per_setting=mse["test"]["mse_ratio_per_setting"],
        test_settings_seen=mse["test"]["seen"],
        unseen=mse["test"]["unseen"],
        per_setting_mse=mse["test"]["per_setting_mse"],
        per_setting_loglik=mse["test"]["per_setting_loglik"],
        approximation_floor=mse["floor"]["mse"] if mse["floor"] else None,
        n_latent_features=int(hip.n_features) - 1,
        z=hip.z.astype(int).tolist(),
        training_weights=np.asarray(hip.weights).tolist(),
        n_batch_transitions=len(batch),
    )
    with writes_metrics(path, metrics, timings, started, machine):
        swingup_report.write_artefacts(path, config, metrics, trials, hip)
    swingup_report.write_report(path, config, metrics)
    return Results(path, to_jsonable(metrics))


def trial_arrays(config: SwingupConfig, trials: list) -> dict[str, np.ndarray]:
    """Every trial's episodes, for statistics metrics.json does not hold.

    ``returns`` and ``steps``: shape (methods, settings, trials, episodes), in the
    order of ``methods`` and ``test_masses`` ((m1, m2) per setting, kg). Read with
    ``np.load("trials.npz")`` (no pickle).
    """
    methods = run_methods(config)
    shape = (len(methods), len(config.test_masses), config.n_trials)
    returns = np.full((*shape, config.transfer.n_episodes), np.nan)
    steps = np.zeros(returns.shape, dtype=np.int64)
    for r in trials:
        index = (methods.index(r.method), r.setting, r.trial)
        returns[index], steps[index] = r.returns, r.steps
    if np.isnan(returns).any():
        raise ValueError("trials: expected one result per (method, setting, trial)")
    return {
        "methods": np.array(methods),
        "test_masses": np.array(config.test_masses, dtype=np.float64),
        "returns": returns,
        "steps": steps,
    }


def transfer_metrics(config: SwingupConfig, trials: list) -> dict[str, Any]:
    """Per-episode mean returns with intervals, and episodes to near-optimal.

    Also the same on per-episode medians: the means are heavy-tailed (an episode
    that runs to the step limit moves a mean by tens of steps), the medians are not.
    """
    curves, per_method, at_limit, all_steps = {}, {}, {}, {}
    methods, pairs = run_methods(config), run_pairs(config)
    for method in methods:
        runs = sorted(
            (r for r in trials if r.method == method),
            key=lambda r: (r.setting, r.trial),
        )
        per_method[method] = np.array([r.returns for r in runs])
        settings = np.array([r.setting for r in runs])  # the same for every method
        curves[method] = mean_ci(per_method[method], axis=0)
        all_steps[method] = np.array([r.steps for r in runs])
        # by step count, as dm_control ends it: an episode that reaches the goal
        # on its last allowed step is a step-limit end there too (discount 1)
        at_limit[method] = np.mean(
            all_steps[method] >= config.transfer.max_steps, axis=0
        )
    target = float(np.mean(curves["true"]["mean"][-config.final_window :]))
    episodes_to = {
        m: first_episode_within(curves[m]["mean"], target, margin=0.1) for m in methods
    }
    medians = {m: np.median(r, axis=0) for m, r in per_method.items()}
    target_median = float(np.mean(medians["true"][-config.final_window :]))
    episodes_to_median = {
        m: first_episode_within(medians[m], target_median, margin=0.1) for m in methods
    }
    return {
        "episodes_to_near_optimal": episodes_to,
        "near_optimal_target": {
            "true_model_final_mean_return": target,
            "final_window": config.final_window,
            "margin": 0.1,
        },
        "median_returns": medians,
        "episodes_to_near_optimal_median": episodes_to_median,
        "true_model_final_median_return": target_median,
        "returns": {
            m: {k: np.atleast_1d(v) for k, v in c.items() if k != "n"}
            | {"n_trials": c["n"]}
            for m, c in curves.items()
        },
        # the per-trial return differences on the same (setting, trial): a
        # mean over several episodes, paired, so far less noisy than the curves
        "paired_difference": {
            f"{a} - {b}": paired_difference(
                per_method[a], per_method[b], groups=settings
            )
            for a, b in pairs
        },
        # per trial and episode, the return minus the 10% threshold of the true
        # model's final return on the same trial: the target's verdict with an
        # interval (above 0: within 10%)
        "margin_to_target": {
            m: margin_to_target(
                per_method[m], per_method["true"], config.final_window, margin=0.1
            )
            for m in methods
        },
        "step_limit_rate": at_limit,
        "step_limit_split": step_limit_split(
            [per_method[m] for m in methods],
            [all_steps[m] for m in methods],
            config.transfer.max_steps,
            methods,
            pairs,
        ),
        "paired_difference_per_setting": per_setting_differences(config, trials),
        "test_belief_means": {
            str(i): np.mean(
                [
                    r.weight_means[-1]
                    for r in trials
                    if r.method == "hipmdp" and r.setting == i
                ],
                axis=0,
            ).tolist()
            for i in range(len(config.test_masses))
        },  # fmt: skip
    }


def step_limit_split(
    returns: np.ndarray,
    steps: np.ndarray,
    max_steps: int,
    methods: tuple[str, ...] = METHODS,
    pairs: tuple[tuple[str, str], ...] = PAIRS,
) -> dict[str, Any]:
    """How much of each mean return, and of each pair's gap, is the episodes that
    ran to the step limit.

    returns, steps: shape (methods, ...) in the order of ``methods`` (as in
    ``trials.npz``), every episode of every trial. With ``p`` a method's share of
    episodes at the limit and ``μ_<`` its mean return over the others,

        mean = (1 - p) μ_< + p · mean(returns at the limit),

    and a pair's gap ``mean_a - mean_b`` splits into ``below_limit = μ_<,a - μ_<,b``
    (the episodes that reached the goal) and the rest, ``limit = gap -
    below_limit`` (the failures). Returns ``{"methods": {m: {"share_at_limit",
    "mean_return", "mean_return_below_limit"}}, "pairs": {"a - b": {"gap",
    "below_limit", "limit"}}}``.
    """
    returns, steps = np.asarray(returns, dtype=float), np.asarray(steps)
    if returns.shape != steps.shape or len(returns) != len(methods):
        raise ValueError(
            f"returns, steps: expected equal shapes ({len(methods)}, ...), got "
            f"{returns.shape} and {steps.shape}"
        )
    out: dict[str, Any] = {"methods": {}, "pairs": {}}
    for i, m in enumerate(methods):
        below = steps[i] < max_steps
        out["methods"][m] = {
            "share_at_limit": float(1.0 - below.mean()),
            "mean_return": float(returns[i].mean()),
            "mean_return_below_limit": float(returns[i][below].mean())
            if below.any()
            else None,
        }
    for a, b in pairs:
        if a not in out["methods"] or b not in out["methods"]:
            continue
        ma, mb = out["methods"][a], out["methods"][b]
        gap = ma["mean_return"] - mb["mean_return"]
        below_a, below_b = (x["mean_return_below_limit"] for x in (ma, mb))
        below = None if None in (below_a, below_b) else below_a - below_b
        out["pairs"][f"{a} - {b}"] = {
            "gap": gap,
            "below_limit": below,
            "limit": None if below is None else gap - below,
        }
    return out


def per_setting_differences(config: SwingupConfig, trials: list) -> dict[str, Any]:
    """``paired_difference``'s all-episodes interval on each test setting alone:
    ``{"a - b": [{"masses": (m1, m2), "mean", "low", "high", "n"}, ...]}`` in the
    order of ``test_masses``; where one method gains and the others do not."""
    returns: dict[tuple[str, int], list] = {}
    for r in sorted(trials, key=lambda r: r.trial):
        returns.setdefault((r.method, r.setting), []).append(r.returns)
    out = {}
    for a, b in run_pairs(config):
        rows = []
        for i, masses in enumerate(config.test_masses):
            d = paired_difference(np.array(returns[a, i]), np.array(returns[b, i]))
            rows.append({"masses": list(masses), **d["all_episodes"]})
        out[f"{a} - {b}"] = rows
    return out


def parse_args(argv: list[str] | None = None) -> tuple[SwingupConfig, str | None]:
    parser = common_parser(
        "python -m tasks.acrobot_swingup", __doc__, PRESETS, "runs/acrobot_swingup"
    )
    parser.add_argument(
        "--trials", type=int, default=None,
        help=f"trials per setting (default {by_preset(PRESETS, 'n_trials')})",
    )  # fmt: skip
    parser.add_argument(
        "--episodes", type=int, default=None,
        help=f"real episodes (default {by_preset(PRESETS, 'transfer.n_episodes')})",
    )  # fmt: skip
    parser.add_argument(
        "--book-inertia",
        action="store_true",
        help="keep each link's moment of inertia at the book's 1 kg m^2 as its "
        "mass changes (default: it follows the mass, I = m l^2)",
    )
    add_split_argument(parser)
    add_method_argument(parser, policies=True)
    args = parser.parse_args(argv)
    preset = PRESETS[args.preset]
    transfer = final_window = None
    if args.episodes is not None:
        try:
            transfer = dataclasses.replace(preset.transfer, n_episodes=args.episodes)
        except ValueError as err:
            parser.error(flag_error(err))
        # the target is the true model's mean over the last 3 episodes, or over
        # all of them in a shorter run
        final_window = min(preset.final_window, args.episodes)
    config = apply_common(
        parser,
        args,
        preset,
        n_trials=args.trials,
        transfer=transfer,
        artefacts=ARTEFACTS,
        policies=True,
        final_window=final_window,
        book_inertia=args.book_inertia or None,
        split=args.split,
        methods=args.method and tuple(args.method),
    )
    return config, args.out


def cli(argv: list[str] | None = None) -> int:
    printable_output()
    config, out = parse_args(argv)
    with stops_reported("python -m tasks.acrobot_swingup", out, config.name):
        results = main(config, out)
    from tasks import swingup_report

    print(wrote_line(results.out, "acrobot.rrd"))
    for line in swingup_report.summary_lines(results.metrics):
        print(line)
    print(f"tables and plain-language results: {results.out / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
