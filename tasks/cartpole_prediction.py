"""Cartpole one-step prediction on new instances (the paper's Table 1 protocol).

    python -m tasks.cartpole_prediction                  # --preset quick, minutes
    python -m tasks.cartpole_prediction --preset paper   # 25 test settings, 5 runs

1. Batch data: on each of the 7 training (pole mass, pole half-length) settings,
   Sarsa(λ) agents with an order-3 Fourier basis learn to balance (paper: 5
   repetitions × 30 episodes × ≤300 steps); every transition is kept.
2. The HiP-MDP is fitted ``n_runs`` times independently (the paper's repeated MCMC
   runs); the average model is one GP on all batch data.
3. On each test setting (the paper preset's 5 × 5 grid; quick: 3 × 3): 50 train
   and 50 held-out test transitions along Sarsa trajectories; MSE of Δs per
   dimension and test log-likelihood for the HiP-MDP (belief filtered on the 50
   train transitions) and the batch-only, train-only and batch + train GPs
   (tasks/prediction.py).

The paper lists (0.3, 0.4) twice among its seven training settings; we keep the list
as printed (two training instances with the same parameters).

Writes ``runs/<name>/``: config.json, metrics.json (``mse[method][dimension]``),
report.md, weights.png, cartpole.rrd (``RERUN=off`` skips it), the fitted models
``hipmdp_run<r>.npz`` and batch.npz.
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
from tasks.agents import CARTPOLE
from tasks.batch import gather_and_save
from tasks.cartpole import CartpoleParams
from tasks.experiment import (
    apply_common,
    by_preset,
    check_positive,
    check_run_fields,
    check_settings,
    common_parser,
    environment,
    one_blas_thread,
    printable_output,
    releases_run_folders,
    run_dir,
    stops_reported,
    to_jsonable,
    write_json,
    writes_metrics,
    wrote_line,
)
from tasks.methods import (
    add_method_argument,
    check_specs,
    fit_all,
    load_all,
    provenance,
)
from tasks.prediction import (
    add_split_argument,
    best_baseline,
    check_split,
    score_settings,
    summarise,
)
from tasks.recording import resolve_record

TRAIN_SETTINGS = (
    (0.1, 0.4), (0.3, 0.4), (0.15, 0.45), (0.2, 0.55),
    (0.25, 0.5), (0.3, 0.4), (0.3, 0.6),
)  # fmt: skip
TEST_SETTINGS = tuple(
    (m, l) for m in (0.1, 0.15, 0.2, 0.25, 0.3) for l in (0.4, 0.45, 0.5, 0.55, 0.6)
)
QUICK_TEST_SETTINGS = tuple((m, l) for m in (0.1, 0.2, 0.3) for l in (0.4, 0.5, 0.6))
# the state is (qpos, qvel) = (x, θ, ẋ, θ̇)
DIM_NAMES = ("dx", "dtheta", "dx_dot", "dtheta_dot")


def _params(pole_mass: float, pole_half_length: float) -> CartpoleParams:
    return CartpoleParams(
        cart_mass=1.0, pole_mass=pole_mass, pole_half_length=pole_half_length
    )


@dataclasses.dataclass(frozen=True)
class PredictionConfig:
    """Everything a run depends on (written to config.json).

    Attributes:
        train_settings, test_settings: (pole mass kg, pole half-length m) pairs.
        batch_repetitions, batch_episodes, batch_max_steps: Sarsa agents per
            training setting, episodes per agent, their step limit.
        n_runs: independent HiP-MDP fits (paper: 5).
        fit: HiP-MDP settings per run.
        average_n_max: transitions per action in the batch GPs.
        n_train, n_test: transitions per test setting (paper: 50 and 50).
        gather_episodes: Sarsa episodes gathered per test setting.
        split: ``"random"`` (our reading of the paper's) or ``"time"``: how a
            test setting's transitions are split into train and test
            (``gather_split``).
        methods: your own methods, scored beside the others, as
            ``"NAME=module:attribute"`` (``tasks.methods``).
        workers: processes for the batch data.
    """

    name: str = "cartpole_prediction"
    preset: str = "quick"
    seed: int = 0
    train_settings: tuple[tuple[float, float], ...] = TRAIN_SETTINGS
    test_settings: tuple[tuple[float, float], ...] = QUICK_TEST_SETTINGS
    batch_repetitions: int = 2
    batch_episodes: int = 15
    batch_max_steps: int = 300
    n_runs: int = 2
    fit: hipmdp.FitConfig = hipmdp.FitConfig(
        n_support=300, n_sweeps=60, n_chains=1, progress=False
    )
    average_n_max: int = 1000
    n_train: int = 50
    n_test: int = 50
    gather_episodes: int = 3
    split: str = "random"
    methods: tuple[str, ...] = ()
    workers: int = 2
    record: bool = True
    progress: bool = True

    def __post_init__(self) -> None:
        check_run_fields(self)
        check_split(self.split)
        check_specs(self.methods)
        check_settings(
            self, "train_settings", "test_settings", _params, "(mass, half-length)"
        )
        check_positive(self, (
            "batch_repetitions", "batch_episodes", "batch_max_steps", "n_runs",
            "average_n_max", "n_train", "n_test", "gather_episodes", "workers",
        ))  # fmt: skip


#: Every file a run writes in its folder (glob patterns); `main` deletes a
#: previous run's before it starts (`tasks.experiment.run_dir`).
ARTEFACTS = (
    "config.json", "batch.npz", "hipmdp_run*.npz", "metrics.json", "report.md",
    "weights.png", "cartpole.rrd",
)  # fmt: skip

PRESETS = {
    "quick": PredictionConfig(),
    "paper": PredictionConfig(
        preset="paper",
        test_settings=TEST_SETTINGS,
        batch_repetitions=5,
        batch_episodes=30,
        n_runs=5,
        fit=hipmdp.FitConfig(n_support=750, n_sweeps=250, n_chains=1, progress=False),
        average_n_max=3000,
    ),
}


class Results(NamedTuple):
    """The run folder and the metrics written there."""

    out: Path
    metrics: dict[str, Any]


@one_blas_thread
@releases_run_folders
def main(config: PredictionConfig, out: str | os.PathLike | None = None) -> Results:
    """Run the experiment and write its artefacts; see the module docstring."""
    from tasks import prediction_report

    started = time.perf_counter()
    config = resolve_record(config)  # RERUN=off: no recording, and config.json says so
    machine = environment()  # the code and machine as the run starts
    loaded = load_all(config.methods)  # a bad one fails here, before any work
    if loaded:  # which code the added methods are
        machine["methods"] = provenance(loaded)
    path = run_dir(out, config.name, ARTEFACTS)
    write_json(path / "config.json", config)
    ss_batch, ss_fit, ss_avg, ss_test = np.random.SeedSequence(config.seed).spawn(4)
    seconds: dict[str, float] = {}

    t0 = time.perf_counter()
    batch = gather_and_save(
        "cartpole", [_params(*p) for p in config.train_settings], path / "batch.npz",
        config=config, seed=ss_batch, progress=config.progress,
    )  # fmt: skip
    seconds["batch_data"] = time.perf_counter() - t0

    t0 = time.perf_counter()  # first, so that a method that breaks does so early
    added = fit_all(loaded, batch, config.seed)
    seconds["added_methods"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    fit_config = dataclasses.replace(config.fit, progress=config.progress)
    hips = []
    for r, s in enumerate(ss_fit.spawn(config.n_runs)):
        hips.append(hipmdp.fit(batch, fit_config, rng=np.random.default_rng(s)))
        hips[-1].save(path / f"hipmdp_run{r}.npz")
    seconds["fit"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    average = baselines.batch_only(
        batch,
        rng=np.random.default_rng(ss_avg),
        n_max=config.average_n_max,
        periodic=config.fit.periodic_dims(batch),
    )
    seconds["average_model"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    splits: list = []
    scores = score_settings(
        CARTPOLE, hips, average, batch,
        [_params(*p) for p in config.test_settings],
        n_train=config.n_train, n_test=config.n_test, seed=ss_test,
        split=config.split, desc="test settings", progress=config.progress,
        added=added, n_episodes=config.gather_episodes,
        n_max=config.average_n_max, splits=splits,
    )  # fmt: skip
    seconds["prediction"] = time.perf_counter() - t0

    train = set(config.train_settings)
    table = summarise(
        scores, DIM_NAMES, [tuple(p) in train for p in config.test_settings]
    )
    unseen = table["unseen"]
    metrics: dict[str, Any] = {
        "mse": table["mse"],
        "loglik_difference": table["loglik_difference"],
        "coverage": table["coverage"],
        "mse_ratio_to_best_baseline": _ratios(table["mse"]),
        # the 5th child of the run's SeedSequence (spawn(4) above took 4): a
        # stream of its own, which leaves the others as they were
        "mse_ratio_to_best_baseline_interval": ratio_intervals(
            table["per_setting_mse"],
            table["mse"],
            rng=np.random.default_rng(
                np.random.SeedSequence(config.seed, spawn_key=(4,))
            ),
        ),
        "mse_ratio_per_setting": table["mse_ratio_per_setting"],
        "test_settings_seen": table["seen"],
        "unseen": unseen
        and {**unseen, "mse_ratio_to_best_baseline": _ratios(unseen["mse"])},
        "per_setting_mse": table["per_setting_mse"],
        "per_setting_loglik": table["per_setting_loglik"],
        "n_latent_features": [int(h.n_features) - 1 for h in hips],
        "z": [h.z.astype(int).tolist() for h in hips],
        "training_weights": [np.asarray(h.weights).tolist() for h in hips],
        "test_belief_means": [
            h.update(h.prior(), s.train).mean.tolist() for h in hips[:1] for s in splits
        ],
        "n_batch_transitions": len(batch),
    }
    with writes_metrics(path, metrics, seconds, started, machine):
        prediction_report.write_artefacts(path, config, metrics, hips[0], splits)
    prediction_report.write_report(path, config, metrics)
    return Results(path, to_jsonable(metrics))


#: Resamples of the test settings behind the ratio's bootstrap interval.
N_BOOTSTRAP = 10_000


def ratio_intervals(
    per_setting_mse: dict,
    mse: dict,
    *,
    rng: np.random.Generator,
    baselines: dict[str, str] | None = None,
) -> dict[str, dict[str, Any] | None]:
    """A 95% percentile-bootstrap interval for each ratio of means of
    `_ratios`: the test settings resampled with replacement (the setting as
    the unit, the methods paired on it), the best baseline kept as chosen on
    all of them. Also the share of resamples whose ratio is >= 1, which says
    how firmly "lower than the best baseline" holds. A ratio of means has no
    t-interval, and a few settings can carry most of a mean MSE.

    per_setting_mse: method -> (settings, dimensions) MSEs, in DIM_NAMES order.
    baselines: dimension -> the baseline to divide by, where it is not the best
        (`tasks.seed_spread` holds one baseline across seeds); the resamples are
        drawn as without it, so a dimension's interval does not depend on the
        others' baselines.
    """
    hip = np.asarray(per_setting_mse["hipmdp"], dtype=float)
    n = hip.shape[0]
    idx = rng.integers(n, size=(N_BOOTSTRAP, n))
    out: dict[str, dict[str, Any] | None] = {}
    for j, d in enumerate(DIM_NAMES):
        name = (baselines or {}).get(d) or best_baseline(mse, d)
        best = np.asarray(per_setting_mse[name], dtype=float)[:, j]
        den = best[idx].mean(axis=1)
        if n < 2 or np.any(den <= 0):
            out[d] = None
            continue
        ratio = hip[idx, j].mean(axis=1) / den
        low, high = np.percentile(ratio, [2.5, 97.5])
        out[d] = {
            "low": float(low),
            "high": float(high),
            "share_at_least_1": float(np.mean(ratio >= 1.0)),
            "n_settings": int(n),
            "n_resamples": N_BOOTSTRAP,
        }
    return out


def _ratios(mse: dict) -> dict[str, float]:
    """HiP-MDP MSE over the best baseline's, per dimension (< 1: HiP-MDP better)."""
    out = {}
    for d in DIM_NAMES:
        best = mse[best_baseline(mse, d)][d]["mean"]
        out[d] = float(mse["hipmdp"][d]["mean"] / best) if best > 0 else None
    return out


def parse_args(argv: list[str] | None = None) -> tuple[PredictionConfig, str | None]:
    parser = common_parser(
        "python -m tasks.cartpole_prediction", __doc__, PRESETS,
        "runs/cartpole_prediction",
    )  # fmt: skip
    parser.add_argument(
        "--runs", type=int, default=None,
        help=f"HiP-MDP fits (default {by_preset(PRESETS, 'n_runs')})",
    )  # fmt: skip
    add_split_argument(parser)
    add_method_argument(parser)
    args = parser.parse_args(argv)
    config = apply_common(
        parser, args, PRESETS[args.preset], artefacts=ARTEFACTS, n_runs=args.runs,
        split=args.split, methods=args.method and tuple(args.method),
    )  # fmt: skip
    return config, args.out


def cli(argv: list[str] | None = None) -> int:
    printable_output()
    config, out = parse_args(argv)
    with stops_reported("python -m tasks.cartpole_prediction", out, config.name):
        results = main(config, out)
    from tasks import prediction_report

    print(wrote_line(results.out, "cartpole.rrd"))
    for line in prediction_report.summary_lines(results.metrics):
        print(line)
    print(f"tables and plain-language results: {results.out / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
