"""How much of a learned model's error on fast states is not knowing the instance?

    python -m tasks.acrobot_batch_errors runs/acrobot_swingup [--fast 10]

Reads a finished swing-up run (``config.json``, ``hipmdp_model.npz``,
``batch.npz``), refits its average model exactly as the run did, and predicts every
batch transition of each training instance ``b`` with

- ``own``: the HiP-MDP at ``b``'s own fitted weights (``HipMDP.weights[:, b]``),
  the best this fit can do for an instance it has identified;
- ``prior``: the HiP-MDP at its prior-mean weights ``μ_w``, what its first
  planning uses before any data;
- ``average``: the one GP on all batch data.

It prints, per instance, the RMS error of the predicted velocity changes (Δθ̇₁,
Δθ̇₂, rad/s) on the fast states (``|θ̇₂| ≥ --fast`` rad/s) and on the rest, and
writes ``RUN/batch_errors.json`` (or ``--out FILE``): ``rmse[model]["fast"|"slow"]``,
shape (instances, 2), the instance ids and masses, and each instance's share of
fast states. The errors are in-sample (these transitions fitted the models), so
they are a floor on what a new instance sees; the gap between ``own`` and
``prior`` is what identifying the instance can recover, and ``own`` what a better
fit has left to gain.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

import hipmdp
from tasks.acrobot_identified import average_model, check_run, read_run
from tasks.experiment import (
    check_out_file,
    environment,
    inputs_checked,
    one_blas_thread,
    printable_output,
    run_or_exit,
    run_parser,
    write_json,
)

MODELS = ("own", "prior", "average")


class Results(NamedTuple):
    """What ``main`` returns: the file written and its contents."""

    out: Path
    summary: dict[str, Any]


def _rmse(err: np.ndarray, rows: np.ndarray) -> list[float]:
    """RMS of the velocity columns of ``err`` (n, 4) over ``rows``; NaN if none."""
    if not rows.any():
        return [float("nan")] * 2
    return np.sqrt(np.mean(err[rows, 2:] ** 2, axis=0)).tolist()


@one_blas_thread
def main(run: str | Path, *, fast: float = 10.0, out: str | Path | None = None):
    """Run the check on the run folder ``run``; see the module docstring."""
    machine = environment()  # the code and machine as the check starts
    run = Path(run)
    check_run(run)
    if not (np.isfinite(fast) and fast > 0):
        raise ValueError(f"fast: expected a finite number > 0 (rad/s), got {fast}")
    out_path = check_out_file(run / "batch_errors.json" if out is None else out, [run])
    config, hip, batch = read_run(run)
    inputs_checked()  # the run read; from here on, the work
    average = average_model(config, batch)
    K = hip.n_features - 1
    rmse: dict[str, dict[str, list]] = {m: {"fast": [], "slow": []} for m in MODELS}
    shares, parameters = [], []
    table = hipmdp.data.ParameterTable.load(run / "batch.npz")
    # the same for every instance: built once
    shared = {
        "prior": hip.mean_predictor(hip.prior()),
        "average": average.mean_predictor(),
    }
    for col, b in enumerate(hip.instance_ids):
        data = batch.select(instances=[int(b)])
        own = hip.mean_predictor(hipmdp.Belief(hip.weights[1:, col], np.eye(K)))
        predictors = {"own": own, **shared}
        preds = {m: predictors[m](data.states, data.actions) for m in MODELS}
        is_fast = np.abs(data.states[:, 3]) >= fast
        for m in MODELS:
            err = preds[m] - data.deltas
            rmse[m]["fast"].append(_rmse(err, is_fast))
            rmse[m]["slow"].append(_rmse(err, ~is_fast))
        shares.append(float(is_fast.mean()))
        parameters.append(table.values[list(table.instances).index(int(b))].tolist())
    summary = {
        "run": str(run),
        "fast": float(fast),
        "instance_ids": [int(b) for b in hip.instance_ids],
        "parameters": list(table.names),
        "instance_parameters": parameters,
        "fast_share": shares,
        "dimensions": ["dtheta1_dot", "dtheta2_dot"],
        "rmse": rmse,
        "environment": machine,
    }
    return Results(write_json(out_path, summary), summary)


def cli(argv: list[str] | None = None) -> int:
    printable_output()
    parser = run_parser("python -m tasks.acrobot_batch_errors", __doc__, progress=False)
    parser.add_argument("--fast", type=float, default=10.0, help="rad/s (default 10)")
    parser.add_argument(
        "--out", default=None, help="the JSON file (default: RUN/batch_errors.json)"
    )
    args = parser.parse_args(argv)
    results = run_or_exit(parser, lambda: main(args.run, fast=args.fast, out=args.out))
    s = results.summary
    print(
        f"RMS error of (Δθ̇₁, Δθ̇₂) in rad/s on each training instance's batch "
        f"transitions, |θ̇₂| ≥ {s['fast']:g} (fast) and below (slow); parameters "
        + ", ".join(s["parameters"])
    )
    print(f"{'instance':>8} {'parameters':>30} {'fast %':>6} " + "".join(
        f"{m + ' ' + band:>16}" for m in MODELS for band in ("fast", "slow")
    ))  # fmt: skip
    for i, b in enumerate(s["instance_ids"]):
        cells = "".join(
            "{:>16}".format("{:.3f}, {:.3f}".format(*s["rmse"][m][band][i]))
            for m in MODELS
            for band in ("fast", "slow")
        )
        p = ", ".join(f"{x:g}" for x in s["instance_parameters"][i])
        print(f"{b:>8} {p:>30} {100 * s['fast_share'][i]:6.1f} {cells}")
    print(f"wrote {results.out}")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
