"""How do each model's errors compound? A check on a finished swing-up run.

    python -m tasks.acrobot_horizon runs/acrobot_swingup [--horizons 1 5 10 20]

Reads a finished swing-up run (``config.json``, ``hipmdp_model.npz``,
``batch.npz``), refits its average model exactly as the run did, and on each of the
run's test settings:

1. gathers ``--identify`` transitions along a Sarsa agent's trajectories and
   filters the HiP-MDP's belief on them (``identified``), as
   ``tasks.acrobot_identified`` does;
2. gathers held-out episodes along a second, independent Sarsa agent's
   trajectories (at least ``--evaluate`` transitions);
3. rolls each model ``k`` steps open loop from every held-out state, with the
   recorded actions (``hipmdp.planning.open_loop_errors``), and compares with the
   recorded state ``k`` steps on.

The models: ``average`` (one GP on all batch data), ``prior`` (the HiP-MDP at its
prior-mean weights, what its first planning uses) and ``identified``. A planner on a
model meets its compounded errors, not its one-step ones: this says whether the
HiP-MDP's model is worse than the average model anywhere a planner would notice.

Prints, per model and horizon, the root-mean-square error per state dimension
and the 99th percentile of its absolute value (the rare large errors a planner can
exploit), each averaged over the test settings, and writes ``horizon.json`` in the
run folder: ``rmse[model][k]`` and ``p99[model][k]``, shape (settings, D), the
settings, the horizons and the numbers of windows. All randomness is spawned from
``--seed``.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from tqdm.auto import tqdm

from hipmdp.planning import LearnedModel, open_loop_errors
from tasks import acrobot
from tasks.acrobot_identified import average_model, check_run, read_run
from tasks.acrobot_swingup import run_test_instances
from tasks.agents import ACROBOT
from tasks.experiment import (
    check_counts,
    check_integer,
    check_out_file,
    environment,
    inputs_checked,
    one_blas_thread,
    printable_output,
    run_or_exit,
    run_parser,
    to_jsonable,
    write_json,
)
from tasks.prediction import gather_split

MODELS = ("average", "prior", "identified")
# errors are in the predicted state s_{t+k}, not in a change
STATE_NAMES = acrobot.STATE_NAMES


class Results(NamedTuple):
    """The file written and its content."""

    out: Path
    summary: dict[str, Any]


@one_blas_thread
def main(
    run: str | Path,
    *,
    horizons: tuple[int, ...] = (1, 5, 10, 20),
    identify: int = 1000,
    evaluate: int = 500,
    seed: int = 321,
    progress: bool = True,
    out: str | Path | None = None,
) -> Results:
    """Run the check on the run folder ``run``; see the module docstring.
    ``out`` is the JSON file to write (default ``run / "horizon.json"``)."""
    machine = environment()  # the code and machine as the check starts
    run = Path(run)
    check_run(run)
    horizons = tuple(horizons)  # int() made 1.5 a horizon of 1
    if not horizons:
        raise ValueError("horizons: expected integers >= 1, got none")
    for i, k in enumerate(horizons):
        check_integer(f"horizons[{i}]", k, 1)
    horizons = tuple(int(k) for k in horizons)
    if len(set(horizons)) != len(horizons):
        raise ValueError(f"horizons: expected distinct integers, got {horizons}")
    check_counts(identify=identify, evaluate=evaluate)
    if max(horizons) > ACROBOT.max_steps:  # no window fits in an episode
        raise ValueError(
            f"horizons: expected at most {ACROBOT.max_steps} (the episodes' step "
            f"limit), got {max(horizons)}"
        )
    check_integer("seed", seed, 0)
    path = check_out_file(run / "horizon.json" if out is None else out, [run])
    config, hip, batch = read_run(run, seed)
    masses = [tuple(m) for m in config["test_masses"]]
    instances = run_test_instances(config)
    inputs_checked()  # the run read and checked; from here on, the work
    average = average_model(config, batch)
    rmse = {m: {k: [] for k in horizons} for m in MODELS}
    p99 = {m: {k: [] for k in horizons} for m in MODELS}
    windows = {k: [] for k in horizons}
    seeds = np.random.SeedSequence(seed).spawn(len(masses))
    for params, ss in tqdm(
        list(zip(instances, seeds, strict=True)), desc="settings", disable=not progress
    ):
        ss_identify, ss_evaluate = ss.spawn(2)
        train = gather_split(
            ACROBOT, params, identify, 0, rng=np.random.default_rng(ss_identify)
        ).train
        held_out = gather_split(
            ACROBOT, params, 0, evaluate, rng=np.random.default_rng(ss_evaluate)
        ).episodes
        models = {
            "average": LearnedModel(average, None, ACROBOT.angle_dims),
            "prior": LearnedModel(hip, hip.prior(), ACROBOT.angle_dims),
            "identified": LearnedModel(
                hip, hip.update(hip.prior(), train), ACROBOT.angle_dims
            ),
        }
        for name, model in models.items():
            errors = open_loop_errors(model, held_out, horizons)
            for k, err in errors.items():
                # no windows: every held-out episode ended within k steps (the goal)
                none = np.full(err.shape[1], np.nan)
                rmse[name][k].append(
                    np.sqrt(np.mean(err**2, axis=0)) if len(err) else none
                )
                p99[name][k].append(
                    np.percentile(np.abs(err), 99, axis=0) if len(err) else none
                )
                if name == MODELS[0]:  # the same windows for every model
                    windows[k].append(len(err))
    summary = {
        "run": str(run),
        "seed": seed,
        "identify_transitions": identify,
        "evaluate_transitions": evaluate,
        "test_masses": [list(m) for m in masses],
        "test_instances": to_jsonable(instances),
        "horizons": list(horizons),
        "dimensions": list(STATE_NAMES),
        "windows": {str(k): v for k, v in windows.items()},
        **{
            stat: {
                m: {str(k): np.array(v) for k, v in by_k.items()}
                for m, by_k in values.items()
            }
            for stat, values in (("rmse", rmse), ("p99", p99))
        },
        "environment": machine,
    }
    return Results(write_json(path, summary), summary)


def cli(argv: list[str] | None = None) -> int:
    printable_output()
    parser = run_parser("python -m tasks.acrobot_horizon", __doc__)
    parser.add_argument("--horizons", type=int, nargs="+", default=[1, 5, 10, 20])
    parser.add_argument("--identify", type=int, default=1000, help="transitions")
    parser.add_argument(
        "--evaluate", type=int, default=500, help="held-out transitions per setting"
    )
    parser.add_argument("--seed", type=int, default=321)
    parser.add_argument(
        "--out", default=None, help="the JSON file to write (default: RUN/horizon.json)"
    )
    args = parser.parse_args(argv)
    results = run_or_exit(parser, lambda: main(
        args.run, horizons=tuple(args.horizons), identify=args.identify,
        evaluate=args.evaluate, seed=args.seed, out=args.out,
        progress=not args.no_progress,
    ))  # fmt: skip
    s = results.summary
    n = len(s["test_masses"])
    head = f"{'model':>11} {'k':>3} " + " ".join(f"{d:>12}" for d in s["dimensions"])
    for stat, what in (("rmse", "RMS error"), ("p99", "99th percentile |error|")):
        print(f"{what} of the k-step open-loop prediction, mean over {n} settings")
        print(head)
        for k in s["horizons"]:
            with_windows = sum(w > 0 for w in s["windows"][str(k)])
            for m in MODELS:
                values = np.asarray(s[stat][m][str(k)], dtype=float)
                row = (  # over the settings with windows of length k
                    np.nanmean(values, axis=0) if with_windows else values[0]
                )
                print(f"{m:>11} {k:3d} " + " ".join(f"{x:12.3g}" for x in row))
            if with_windows < n:
                print(f"{'':>15}(k = {k}: windows on {with_windows} of {n} settings)")
    print(f"wrote {results.out}")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
