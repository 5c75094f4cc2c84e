"""Export a sharded run's episodes to Minari's dataset format (Arrow storage).

    python -m tasks.minari_export runs/data --out runs/minari

Writes `OUT/<dataset_id>/data/` as Minari's `ArrowStorage` lays it out (Minari ≥ 0.5,
`data_format: "arrow"`), so `minari.MinariDataset("OUT/<dataset_id>/data")` reads it
(or copy `OUT/<dataset_id>` into Minari's datasets folder for `minari.load_dataset`):

- `data/metadata.json`: `dataset_id` (default `<domain>-<policy>-v0`),
  `minari_version` (`0.5.0`: one release, not a range; Minari looks it up in
  its `supported_dataset_versions`, e.g. 0.5.4 takes 0.4.0 to 0.5.4, and refused
  the `>=0.5.0` written until 2026-12-04), `data_format`, `total_episodes`,
  `total_steps`, and the observation space `Box(-inf, inf, (D,), float64)` and
  action space `Discrete(A)` serialised as Minari does; and, beside Minari's
  fields, the run's generating config (`hipmdp_manifest`) and what a step is
  (`hipmdp_task`: state names and units, angle dimensions wrapped to (-π, π],
  the action values and their unit, `dt` in seconds, the step limit);
- per episode `e`, `data/<e>/part-0.arrow` (an Arrow IPC file) with the columns
  `observations` (`T + 1` rows, `s_0 … s_T`), `actions`, `rewards`, `terminations`
  and `truncations` (`T` rows padded with one zero row, as Minari stores them);
- `data/<e>/metadata.json`: `id`, `total_steps`, and the episode's `instance` id
  and its `parameters` (`{name: value}`, from the run's manifest).

`terminations[-1]` is the task's terminal test on the last state (goal reached or
failure); otherwise the episode was cut by the step limit (`truncations[-1]`).

Needs `pyarrow` (installed with rerun-sdk, which the project already depends on);
Minari itself is not needed, and is not installed in the project's environment, so
the export is checked by reading it back the way Minari's `ArrowStorage` does
(`tests/test_minari_export.py`), not with Minari itself; by hand, Minari 0.5.4
(in a separate environment) read an export's 400 episodes on 2026-12-04. Every
shard is checked against its checksum before anything is written; the export is
built in a temporary folder and renamed into place (an error removes it, the next
export clears one a kill left); an existing dataset is never overwritten.
"""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hipmdp import shards
from hipmdp.data import ParameterTable, Transitions, atomic_folder
from tasks import acrobot, agents, cartpole
from tasks.collect import get_domain
from tasks.experiment import check_folder_out, path_argument, printable_output

Array = np.ndarray

# the first release with the Arrow layout; Minari checks this field by membership
# in its set of supported dataset versions, so it must be one release
MINARI_VERSION = "0.5.0"

#: What a step of each domain is, so that an export describes itself
#: (``hipmdp_task`` in ``data/metadata.json``; the modules' docstrings say more).
TASKS = {
    "acrobot": {
        "documentation": "tasks.acrobot",
        "state": list(acrobot.STATE_NAMES),
        "state_units": ["rad", "rad", "rad/s", "rad/s"],
        "angle_dims": list(acrobot.ANGLE_DIMS),
        "action": "elbow torque held for dt (N·m), by action index",
        "action_values": acrobot.ACTIONS.tolist(),
        "dt": acrobot.CONTROL_TIMESTEP,
    },
    "cartpole": {
        "documentation": "tasks.cartpole",
        "state": list(cartpole.STATE_NAMES),
        "state_units": ["m", "rad", "m/s", "rad/s"],
        "angle_dims": list(cartpole.ANGLE_DIMS),
        "action": "force on the cart held for dt (N), by action index",
        "action_values": cartpole.ACTIONS.tolist(),
        "dt": cartpole.CONTROL_TIMESTEP,
    },
}


def export(run: str | Path, out: str | Path, *, dataset_id: str | None = None) -> Path:
    """Write the episodes of the finished run in `run` as a Minari dataset.

    Args:
        run: a run directory (or its `manifest.json`) from `tasks.generate`.
        out: the folder to hold `<dataset_id>/data/`.
        dataset_id: Minari's `[namespace/]name-vN` (`DATASET_ID`); with a
            namespace the dataset is `out/<namespace>/<name-vN>`, as Minari
            stores namespaced datasets.

    Returns:
        The `data` folder written.

    Raises:
        ValueError: if `dataset_id` is not a Minari id, `out` cannot be a
            folder, the run is not complete or a shard fails its checksum, or if
            `out/<dataset_id>` exists already (nothing is written then).
    """
    if dataset_id is not None:
        check_dataset_id(dataset_id)
    check_folder_out(Path(out), "--out")
    dataset = shards.Dataset(run)
    if not dataset.complete:
        raise ValueError(
            f"{dataset.directory} is not a finished run; --resume it first"
        )
    config = dataset.manifest["config"]
    domain = config["domain"]
    dataset_id = dataset_id or f"{domain}-{config['policy']}-v0"
    target = Path(out) / dataset_id
    if target.exists():
        raise ValueError(f"{target} exists; choose another --out or dataset id")
    spec = get_domain(domain)
    max_steps = step_limit(domain, config["max_steps"])
    table = dataset.parameters
    dataset.verify()  # every shard, before anything is written
    with atomic_folder(target) as building:
        _export(dataset, building / "data", dataset_id, spec, max_steps, table)
    return target / "data"


def _export(dataset, data: Path, dataset_id: str, spec, max_steps: int, table):
    """Write the Minari folder `data` (see `export`)."""
    import pyarrow as pa

    domain = dataset.manifest["config"]["domain"]
    data.mkdir()
    episode, steps = 0, 0
    for entry in dataset.manifest["shards"]:
        transitions = dataset.load(instances=entry["instances"])
        for start, stop, terminal in episode_ends(
            transitions, table, domain, max_steps
        ):
            b = int(transitions.instances[start])
            columns = _episode_columns(transitions, start, stop, terminal)
            folder = data / str(episode)
            folder.mkdir()
            batch = pa.RecordBatch.from_pydict(columns)
            with pa.OSFile(str(folder / "part-0.arrow"), "wb") as sink:
                with pa.ipc.new_file(sink, batch.schema) as writer:
                    writer.write_batch(batch)
            _write_json(
                folder / "metadata.json",
                {
                    "id": episode,
                    "total_steps": int(stop - start),
                    "instance": b,
                    "parameters": table.row(b),
                },
            )
            episode, steps = episode + 1, steps + int(stop - start)
    _write_json(
        data / "metadata.json",
        {
            "dataset_id": dataset_id,
            "minari_version": MINARI_VERSION,
            "data_format": "arrow",
            "total_episodes": episode,
            "total_steps": steps,
            "observation_space": json.dumps(
                {
                    "type": "Box",
                    "dtype": "float64",
                    "shape": [spec.state_dim],
                    "low": [-np.inf] * spec.state_dim,
                    "high": [np.inf] * spec.state_dim,
                }
            ),
            "action_space": json.dumps(
                {"type": "Discrete", "dtype": "int64", "start": 0, "n": spec.n_actions}
            ),
            "hipmdp_manifest": dataset.manifest["config"],
            "hipmdp_task": TASKS[domain] | {"max_steps": max_steps},
        },
    )


#: Minari's dataset id (``minari.dataset.minari_dataset.DATASET_ID_RE``, Minari
#: 0.5): an optional namespace of two or more characters (nested with ``/``), a
#: name and, required here as ``parse_dataset_id`` needs it, a version.
DATASET_ID = re.compile(r"(?:[-_\w][-_\w/]*[-_\w]+/)?[-_\w]+-v\d+")


def check_dataset_id(dataset_id: str) -> None:
    """Raise ValueError unless ``dataset_id`` is a Minari id (:data:`DATASET_ID`)
    whose parts are folders inside ``out`` (no empty part)."""
    if not DATASET_ID.fullmatch(dataset_id) or "" in dataset_id.split("/"):
        raise ValueError(
            "--dataset-id: expected Minari's [namespace/]name-vN, of letters, "
            f"digits, '_' and '-' (e.g. acrobot-random-v0), got {dataset_id!r}"
        )


def step_limit(domain: str, max_steps: int | None) -> int:
    """A run's step limit: ``max_steps``, or the task's where it is None (a
    manifest's ``config["max_steps"]`` when ``--max-steps`` was not given)."""
    return agents.DOMAINS[domain].max_steps if max_steps is None else max_steps


def episode_ends(
    transitions: Transitions,
    table: ParameterTable,
    domain: str,
    max_steps: int | None = None,
) -> list[tuple[int, int, bool]]:
    """``(start, stop, terminal)`` of each episode in ``transitions`` (ended by
    its ``dones``): ``terminal`` if its last next state ends the task of its own
    instance (its parameters from ``table``: the acrobot's goal height, say,
    depends on its link lengths), else the episode was truncated.

    ``max_steps`` is the run's step limit, None the task's (:func:`step_limit`)."""
    spec = get_domain(domain)
    max_steps = step_limit(domain, max_steps)
    ends = np.flatnonzero(transitions.dones) + 1
    out = []
    for start, stop in zip(np.r_[0, ends[:-1]], ends, strict=True):
        params = spec.params_type(**table.row(int(transitions.instances[start])))
        task = agents.DOMAINS[domain].planning_task(params, max_steps)
        last = transitions.next_states[stop - 1]
        out.append((int(start), int(stop), bool(task.terminal(last[None])[0])))
    return out


def _episode_columns(transitions, start: int, stop: int, terminal: bool) -> dict:
    """Minari's Arrow columns for transitions `[start, stop)`: `T + 1` rows each."""
    import pyarrow as pa

    n = stop - start
    observations = np.concatenate(
        [transitions.states[start:stop], transitions.next_states[stop - 1 : stop]]
    )
    ends = np.zeros(n + 1, dtype=bool)
    terminations, truncations = ends.copy(), ends.copy()
    (terminations if terminal else truncations)[n - 1] = True
    width = observations.shape[1]
    return {
        "observations": pa.FixedSizeListArray.from_arrays(
            observations.reshape(-1), type=pa.list_(pa.float64(), list_size=width)
        ),
        "actions": pa.array(np.r_[transitions.actions[start:stop], 0], pa.int32()),
        "rewards": pa.array(np.r_[transitions.rewards[start:stop], 0.0]),
        "terminations": pa.array(terminations),
        "truncations": pa.array(truncations),
    }


def _write_json(path: Path, content: dict) -> None:
    path.write_text(json.dumps(content, indent=1) + "\n")


def main(argv: Sequence[str] | None = None) -> Path:
    printable_output()
    parser = argparse.ArgumentParser(
        prog="python -m tasks.minari_export",
        description=__doc__.splitlines()[0],
        epilog="Needs pyarrow (installed with rerun-sdk, or: pip install -e "
        "'.[minari]'); Minari itself is not needed. Writes OUT/<dataset id>/data/, "
        "which minari.MinariDataset reads.",
    )
    parser.add_argument("run", type=Path, help="run directory of tasks.generate")
    parser.add_argument(
        "--out", type=path_argument, required=True,
        help="parent folder of the dataset: it is written to OUT/<dataset id>/",
    )  # fmt: skip
    parser.add_argument(
        "--dataset-id", default=None,
        help="Minari's dataset id, [namespace/]name-vN (default: "
        "<domain>-<policy>-v0)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    try:
        path = export(args.run, args.out, dataset_id=args.dataset_id)
    except (ValueError, FileNotFoundError, ImportError) as error:
        parser.error(str(error))
    except OSError as error:  # a full disk, a permission: not a usage error
        parser.exit(1, f"{parser.prog}: error: {error}\n")
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    main()
