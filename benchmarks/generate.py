"""Data-generation speed: raw MuJoCo against our open-loop, random and Sarsa paths.

    python -m benchmarks.generate [--domain acrobot] [--repeats 3]

Measured side by side in one run, in MuJoCo steps (`mj_step` calls) per second:

- raw: `mujoco.mj_step(model, data, n)` per control step with the control set from
  the action table, on one compiled model (one core): the simulator alone;
- open-loop, 1 core: `tasks.generate.run_shard` on shards of the `open-loop` policy
  in this process — model compilation, `mujoco.rollout`, termination, `Transitions`
  and the shard's archive bytes included;
- open-loop, 2 workers: the same shards on a 2-process pool (`--workers 2`'s pool;
  started and warmed up before timing, so imports are not counted);
- random and sarsa, 1 core: `run_shard` with the `random` policy (dm_control
  `env.step` per control step) and the `sarsa` policy (an agent learning per
  instance, the paper's data).

Before timing, one open-loop shard is computed both in this process and on the
pool, and their archives are checked to be byte-identical
(``check_same_shards``): the two sides timed make the same data.

Also the bookkeeping per finished shard for a run of `--run-instances` instances
(default 90,000) in shards of `--instances`: rewriting the whole manifest, as
`tasks.generate` did after every shard until 2026-12-03, against appending one
line to `progress.jsonl`, as it does now (both atomic or flushed to disk, in a
temporary folder, interleaved); the manifest's size grows with the run, so the
first costs O(instances) per shard and the second O(1).

Each figure is the median of `--repeats` measurements, the kinds interleaved, so
load from other processes hits all of them alike; each is given per wall-clock
second and per CPU second of the processes doing the work (less sensitive to other
load). Prints the ratios: open-loop / raw per core (target ≥ 0.5), 2 workers /
1 core (target ≥ 1.8; wall-clock, and projected from CPU time: what 2 free cores
would give), random / raw and sarsa / raw.
"""

from __future__ import annotations

# first, before numpy loads: one BLAS thread, headless MuJoCo (tasks/__init__.py)
import tasks  # noqa: F401

# isort: split

import argparse
import concurrent.futures as cf
import dataclasses
import hashlib
import multiprocessing
import os
import time
from typing import NamedTuple

import mujoco
import numpy as np

from tasks import generate
from tasks.collect import get_domain
from tasks.experiment import printable_output
from tasks.rollout import MODULES


class Rate(NamedTuple):
    """MuJoCo steps per wall-clock second and per CPU second (CPU time of the
    processes that did the work: less sensitive to other load on the machine)."""

    wall: float
    cpu: float


def raw_rate(domain: str, n_control: int, *, rng) -> Rate:
    """Plain `mj_step(model, data, n)` calls with the control set each step."""
    module = MODULES[domain]
    model = module.make_model()
    data = mujoco.MjData(model)
    controls = module.ACTIONS[rng.integers(len(module.ACTIONS), size=n_control)]
    start, cpu = time.perf_counter(), time.process_time()
    for u in controls:
        data.ctrl[0] = u
        mujoco.mj_step(model, data, module.N_SUB_STEPS)
    steps = n_control * module.N_SUB_STEPS
    return Rate(
        steps / (time.perf_counter() - start), steps / (time.process_time() - cpu)
    )


def timed_run_shard(job: generate.ShardJob) -> tuple[int, float]:
    """`run_shard` in a worker: the shard's transitions and the CPU seconds used."""
    cpu = time.process_time()
    output = generate.run_shard(job)
    return output.counts["transitions"], time.process_time() - cpu


def jobs(args, policy: str, n_shards: int, first: int = 0) -> list[generate.ShardJob]:
    """`n_shards` shards of nominal instances (parameters do not change speed,
    but for a fast acrobot's finer step, `tasks.acrobot.sub_steps`)."""
    spec = get_domain(args.domain)
    values = dataclasses.astuple(spec.params_type())
    size = args.instances if policy != "sarsa" else 2
    return [
        generate.ShardJob(
            args.domain,
            policy,
            k,
            tuple(range(k * size, (k + 1) * size)),
            (values,) * size,
            args.episodes,
            args.max_steps,
            0,
            (1, 0, k),
        )
        for k in range(first, first + n_shards)
    ]


def check_same_shards(batch, submits: dict) -> None:
    """Raise AssertionError unless every job of ``batch`` gives the same
    `run_shard` output (archive bytes, counts, diverged episodes) through each
    of ``submits`` (name: a function submitting `run_shard` for a job)."""
    for job in batch:
        outputs = {name: submit(job).result() for name, submit in submits.items()}
        (first, want), *others = outputs.items()
        for name, got in others:
            if got != want:
                raise AssertionError(
                    f"shard {job.index} ({job.policy}): {name} and {first} differ "
                    f"(archive sha256 {hashlib.sha256(got.data).hexdigest()[:12]} "
                    f"against {hashlib.sha256(want.data).hexdigest()[:12]})"
                )


def shard_rate(batch, submit) -> Rate:
    """Computing `batch` through `submit` (which runs `timed_run_shard`)."""
    n_sub = MODULES[batch[0].domain].N_SUB_STEPS
    start = time.perf_counter()
    outputs = [f.result() for f in [submit(job) for job in batch]]
    elapsed = time.perf_counter() - start
    steps = sum(n for n, _ in outputs) * n_sub
    return Rate(steps / elapsed, steps / sum(cpu for _, cpu in outputs))


def bookkeeping(
    n_instances: int, shard_size: int, repeats: int, where: str = "."
) -> dict[str, float]:
    """Median seconds to record one finished shard of a run of ``n_instances``:
    ``"manifest"``, the whole manifest rewritten; ``"progress"``, one line
    appended; both flushed to disk, in a temporary folder under ``where`` (the
    filesystem matters: on tmpfs a flush costs nothing). The manifest is the one
    ``tasks.generate`` plans for an acrobot run of that size."""
    import tempfile
    from pathlib import Path

    from hipmdp import shards

    config = generate.parse_config(
        ["--domain", "acrobot", "--instances", str(n_instances),
         "--shard-size", str(shard_size), "--out", where]
    )  # fmt: skip
    manifest = generate.plan(config)  # the run's own manifest, nothing finished
    entries = manifest["shards"]
    times: dict[str, list[float]] = {"manifest": [], "progress": []}
    with tempfile.TemporaryDirectory(dir=where) as tmp:
        for k in range(min(repeats, len(entries))):
            entries[k].update(
                sha256="0" * 64,
                counts={"episodes": 2, "transitions": 400, "diverged_episodes": 0},
            )
            for name, record in (
                ("manifest", lambda: shards.write_manifest(Path(tmp), manifest)),
                ("progress", lambda e=entries[k]: shards.append_progress(Path(tmp), e)),
            ):
                start = time.perf_counter()
                record()
                times[name].append(time.perf_counter() - start)
        size = (Path(tmp) / shards.MANIFEST).stat().st_size
    out = {name: float(np.median(v)) for name, v in times.items()}
    out["manifest_bytes"] = float(size)
    out["shards"] = float(len(entries))
    return out


def _filesystem(path: str) -> str:
    """The type of the filesystem holding ``path`` (Linux: from /proc/mounts),
    or "unknown"."""
    try:
        with open("/proc/mounts") as fh:
            mounts = [line.split() for line in fh]
    except OSError:
        return "unknown"
    real = os.path.realpath(path)
    best = max(
        (m for m in mounts if real == m[1] or real.startswith(m[1].rstrip("/") + "/")),
        key=lambda m: len(m[1]),
        default=None,
    )
    return best[2] if best else "unknown"


def main(argv=None) -> None:
    printable_output()
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.generate", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--domain", default="acrobot", choices=sorted(MODULES))
    parser.add_argument("--instances", type=int, default=16, help="per shard")
    parser.add_argument("--episodes", type=int, default=2, help="per instance")
    parser.add_argument("--max-steps", type=int, default=200)
    parser.add_argument("--raw-steps", type=int, default=5000, help="control steps")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--run-instances", type=int, default=90_000,
        help="instances of the run whose bookkeeping is measured",
    )  # fmt: skip
    parser.add_argument(
        "--dir", default=".",
        help="where the bookkeeping is measured (default: here; not a tmpfs)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    load = os.getloadavg()
    inline = generate.InlineExecutor()
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["tasks.generate"])
    results: dict[str, list[Rate]] = {}
    with cf.ProcessPoolExecutor(2, mp_context=context) as pool:
        # Warm up both workers (imports, first compile) before any timing.
        list(pool.map(timed_run_shard, jobs(args, "open-loop", 2, first=1000)))
        check_same_shards(
            jobs(args, "open-loop", 1, first=2000),
            {
                "in process": lambda job: inline.submit(generate.run_shard, job),
                "in the pool": lambda job: pool.submit(generate.run_shard, job),
            },
        )

        def in_process(job):
            return inline.submit(timed_run_shard, job)

        def in_pool(job):
            return pool.submit(timed_run_shard, job)

        # and this process too: its first in-process shard was the slow one
        # (0.93 against 0.96 in later repeats)
        shard_rate(jobs(args, "open-loop", 1, 1000), in_process)

        for r in range(args.repeats):
            for name, value in [
                ("raw", raw_rate(args.domain, args.raw_steps, rng=rng)),
                (
                    "open-loop 1 core",
                    shard_rate(jobs(args, "open-loop", 1, r), in_process),
                ),
                (
                    "open-loop 2 workers",
                    shard_rate(jobs(args, "open-loop", 4, 10 + 4 * r), in_pool),
                ),
                (
                    "random 1 core",
                    shard_rate(jobs(args, "random", 1, r), in_process),
                ),
                (
                    "sarsa 1 core",
                    shard_rate(jobs(args, "sarsa", 1, r), in_process),
                ),
            ]:
                results.setdefault(name, []).append(value)
    wall = {name: float(np.median([r.wall for r in v])) for name, v in results.items()}
    cpu = {name: float(np.median([r.cpu for r in v])) for name, v in results.items()}
    n_sub = MODULES[args.domain].N_SUB_STEPS
    print(
        f"{args.domain}: {n_sub} mj_step per control step; shards of "
        f"{args.instances} instances x {args.episodes} episodes x <= {args.max_steps} "
        f"steps (sarsa: 2 instances); median of {args.repeats}; "
        f"mujoco {mujoco.__version__}; load average before/after "
        f"{load[0]:.1f}/{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores "
        "(other processes make every figure noisy, the 2-worker one most); an "
        "open-loop shard checked byte-identical in this process and in the pool"
    )
    print(f"  {'mj_step/s':<20} {'wall':>10} {'per CPU s':>10}   (wall per repeat)")
    for name in results:
        spread = ", ".join(f"{r.wall:.0f}" for r in results[name])
        print(f"  {name:<20} {wall[name]:>10.0f} {cpu[name]:>10.0f}   ({spread})")
    one, two = "open-loop 1 core", "open-loop 2 workers"
    print(f"  {'ratios':<32} {'wall':>6} {'CPU':>6}")
    for label, top, bottom, target in [
        ("open-loop 1 core / raw", one, "raw", "   (target >= 0.5)"),
        ("random 1 core / raw", "random 1 core", "raw", ""),
        ("sarsa 1 core / raw", "sarsa 1 core", "raw", ""),
    ]:
        print(
            f"  {label:<32} {wall[top] / wall[bottom]:>6.2f} "
            f"{cpu[top] / cpu[bottom]:>6.2f}{target}"
        )
    print(
        f"  {'open-loop 2 workers / 1 core':<32} {wall[two] / wall[one]:>6.2f} "
        f"{2 * cpu[two] / cpu[one]:>6.2f}   (target >= 1.8)"
    )
    print(
        f"  the 2 workers got {wall[two] / cpu[two]:.2f} CPUs on average; the CPU "
        "column is 2 x (2-worker rate per CPU second) / (1-core rate per CPU "
        "second): the scaling with 2 free cores, if the per-CPU rate holds"
    )
    n_book = max(args.repeats, 5)  # each repeat is one shard: cheap
    book = bookkeeping(args.run_instances, args.instances, n_book, args.dir)
    n_shards = int(book["shards"])
    print(
        f"recording a finished shard, a run of {args.run_instances} instances in "
        f"{n_shards} shards of {args.instances} (manifest "
        f"{book['manifest_bytes'] / 1e6:.1f} MB; median of {n_book}; "
        f"in {os.path.abspath(args.dir)}, on {_filesystem(args.dir)}):"
    )
    print(
        f"  rewrite the manifest (until 2026-12-03) {book['manifest'] * 1e3:9.2f} ms"
        f"  -> {book['manifest'] * n_shards / 60:.1f} min over the run"
    )
    print(
        f"  append a progress line (now)           {book['progress'] * 1e3:9.2f} ms"
        f"  -> {book['progress'] * n_shards / 60:.2f} min over the run"
    )
    print(f"  ratio {book['manifest'] / book['progress']:.0f}x")


if __name__ == "__main__":
    main()
