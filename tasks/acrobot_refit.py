"""Refit a finished swing-up run's HiP-MDP with other fit settings (an ablation).

    python -m tasks.acrobot_refit runs/acrobot_swingup runs/refit --fit n_smooth=4000

Reads a finished swing-up run (``config.json``, ``batch.npz``), changes the named
fields of its ``FitConfig`` (``--fit name=value ...``; see ``hipmdp.FitConfig``), and
fits the HiP-MDP again on the same batch data with the run's own fit stream (the
same ``--seed`` spawn as ``tasks.acrobot_swingup``), so that only the changed
settings differ. It writes the folder ``OUT`` in the layout the checks read:

- ``batch.npz``, a copy of the run's;
- ``hipmdp_model.npz``, the refitted model;
- ``config.json``, the run's config with the new fit settings.

The folder appears whole, once the fit and its files are done (they are written
into a hidden ``.OUT.<random>.tmp`` beside it, then renamed): a failed or killed
refit leaves no ``OUT`` behind, and the same command can run again.

``tasks.acrobot_energy``, ``tasks.acrobot_identified`` and ``tasks.acrobot_horizon``
then run on ``OUT`` exactly as on the run; their average model is refitted as the
run did, with the new ``FitConfig.periodic`` if that was changed. The transfer
experiment itself is not rerun: for its numbers, run ``tasks.acrobot_swingup`` with
the settings changed in its preset.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

import hipmdp
from hipmdp.data import atomic_folder, atomic_write, check_empty_folder
from hipmdp.fitting import check_batch
from tasks.acrobot_identified import check_run, read_run_config
from tasks.acrobot_swingup import run_streams
from tasks.experiment import (
    check_folder_out,
    environment,
    inputs_checked,
    one_blas_thread,
    printable_output,
    run_or_exit,
    run_parser,
    with_added_fields,
    write_json,
)

_FIELDS = {f.name: f for f in dataclasses.fields(hipmdp.FitConfig)}


class Results(NamedTuple):
    """What ``main`` returns: the folder written, the fit settings changed (as
    given; the whole new FitConfig is ``config.json``'s ``fit``), the fit's
    seconds and the refitted model."""

    out: Path
    fit: dict[str, Any]
    seconds: float
    model: hipmdp.HipMDP


def parse_fit(items: list[str]) -> dict[str, Any]:
    """``["name=value", ...]`` as FitConfig changes: integers, numbers and
    ``true``/``false`` by the field's type. Raises ValueError naming the item."""
    changes: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or name not in _FIELDS or name == "progress":
            known = ", ".join(n for n in _FIELDS if n != "progress")
            raise ValueError(
                f"--fit {item!r}: expected name=value with name in {known}"
            )
        kind = type(_FIELDS[name].default)
        try:
            if kind is bool:
                if text.lower() not in ("true", "false"):
                    raise ValueError
                value: Any = text.lower() == "true"
            else:
                value = kind(text)
        except ValueError:
            raise ValueError(
                f"--fit {item!r}: expected a {kind.__name__} value for {name}"
            ) from None
        changes[name] = value
    return changes


@one_blas_thread
def main(
    run: str | Path,
    out: str | Path,
    fit: dict[str, Any],
    *,
    progress: bool = True,
) -> Results:
    """Refit ``run``'s HiP-MDP with ``fit`` (FitConfig field changes) into ``out``;
    see the module docstring."""
    machine = environment()  # the code and machine as the check starts
    run, out = Path(run), Path(out)
    check_run(run)
    if out.resolve() == run.resolve():
        raise ValueError(f"out: expected a folder other than the run ({run})")
    check_folder_out(out)
    check_empty_folder(out, "out")
    config = read_run_config(run)  # an error names the file and the field
    # every check happens here, before any work (FitConfig validates the values)
    old = with_added_fields(config)["fit"]  # as the run fitted
    fit_config = hipmdp.FitConfig(**{**old, **fit, "progress": progress})
    config["fit"] = {**dataclasses.asdict(fit_config), "progress": False}
    config["refit"] = {"from": str(run), "changes": fit, "environment": machine}

    batch = hipmdp.Transitions.load(run / "batch.npz")  # an error names the file
    data = (run / "batch.npz").read_bytes()  # copied as it is, once fitted
    ss_fit = run_streams(config["seed"]).fit  # as the run did
    check_batch(batch, fit_config)  # e.g. more support points than states
    inputs_checked()
    t0 = time.perf_counter()
    model = hipmdp.fit(batch, fit_config, rng=np.random.default_rng(ss_fit))
    seconds = time.perf_counter() - t0
    # out appears whole or not at all: a failed or killed fit or save leaves no
    # folder that would refuse the same command again
    with atomic_folder(out) as tmp:
        atomic_write(tmp / "batch.npz", lambda fh: fh.write(data))
        model.save(tmp / "hipmdp_model.npz")
        write_json(tmp / "config.json", config)
    return Results(out, fit, seconds, model)


def cli(argv: list[str] | None = None) -> int:
    printable_output()
    parser = run_parser("python -m tasks.acrobot_refit", __doc__)
    parser.add_argument("out", help="the new run folder (absent or empty)")
    parser.add_argument(
        "--fit", nargs="+", default=[], metavar="NAME=VALUE",
        help="FitConfig fields to change, e.g. n_smooth=4000 periodic=true",
    )  # fmt: skip
    args = parser.parse_args(argv)
    progress = not args.no_progress
    results = run_or_exit(
        parser, lambda: main(args.run, args.out, parse_fit(args.fit), progress=progress)
    )
    m = results.model
    print(
        f"fitted in {results.seconds:.0f} s: {m.n_features} features, "
        f"{len(m.support)} support points, log joint {m.info['best_log_joint']:.4g}"
    )
    print(f"wrote {results.out}")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
