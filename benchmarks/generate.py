"""Data-generation speed: raw MuJoCo against our open-loop, random and Sarsa paths.

    python benchmarks/generate.py [--domain acrobot] [--repeats 3]

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

Each figure is the median of `--repeats` measurements, the kinds interleaved, so
load from other processes hits all of them alike. Prints the ratios: open-loop /
raw per core (target ≥ 0.5), 2 workers / 1 core (target ≥ 1.8), sarsa / raw.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import dataclasses
import multiprocessing
import os
import time

import mujoco
import numpy as np

from tasks import generate
from tasks.collect import get_domain
from tasks.rollout import MODULES


def raw_steps_per_second(domain: str, n_control: int, *, rng) -> float:
    """MuJoCo steps per second of plain `mj_step(model, data, n)` calls."""
    module = MODULES[domain]
    model = module.make_model()
    data = mujoco.MjData(model)
    controls = module.ACTIONS[rng.integers(len(module.ACTIONS), size=n_control)]
    start = time.perf_counter()
    for u in controls:
        data.ctrl[0] = u
        mujoco.mj_step(model, data, module.N_SUB_STEPS)
    return n_control * module.N_SUB_STEPS / (time.perf_counter() - start)


def jobs(args, policy: str, n_shards: int, first: int = 0) -> list[generate.ShardJob]:
    """`n_shards` shards of nominal instances (parameters do not change speed)."""
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


def shard_steps_per_second(batch, submit) -> float:
    """MuJoCo steps per second of computing `batch` through `submit`."""
    n_sub = MODULES[batch[0].domain].N_SUB_STEPS
    start = time.perf_counter()
    outputs = [f.result() for f in [submit(job) for job in batch]]
    elapsed = time.perf_counter() - start
    return sum(o.counts["transitions"] for o in outputs) * n_sub / elapsed


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--domain", default="acrobot", choices=sorted(MODULES))
    parser.add_argument("--instances", type=int, default=16, help="per shard")
    parser.add_argument("--episodes", type=int, default=2, help="per instance")
    parser.add_argument("--max-steps", type=int, default=200)
    parser.add_argument("--raw-steps", type=int, default=5000, help="control steps")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    load = os.getloadavg()
    inline = generate.InlineExecutor()
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["tasks.generate"])
    results: dict[str, list[float]] = {}
    with cf.ProcessPoolExecutor(2, mp_context=context) as pool:
        # Warm up both workers (imports, first compile) before any timing.
        list(pool.map(generate.run_shard, jobs(args, "open-loop", 2, first=1000)))

        def in_process(job):
            return inline.submit(generate.run_shard, job)

        def in_pool(job):
            return pool.submit(generate.run_shard, job)

        for r in range(args.repeats):
            for name, value in [
                ("raw", raw_steps_per_second(args.domain, args.raw_steps, rng=rng)),
                (
                    "open-loop 1 core",
                    shard_steps_per_second(jobs(args, "open-loop", 1, r), in_process),
                ),
                (
                    "open-loop 2 workers",
                    shard_steps_per_second(
                        jobs(args, "open-loop", 4, 10 + 4 * r), in_pool
                    ),
                ),
                (
                    "random 1 core",
                    shard_steps_per_second(jobs(args, "random", 1, r), in_process),
                ),
                (
                    "sarsa 1 core",
                    shard_steps_per_second(jobs(args, "sarsa", 1, r), in_process),
                ),
            ]:
                results.setdefault(name, []).append(value)
    median = {name: float(np.median(v)) for name, v in results.items()}
    n_sub = MODULES[args.domain].N_SUB_STEPS
    print(
        f"{args.domain}: {n_sub} mj_step per control step; shards of "
        f"{args.instances} instances x {args.episodes} episodes x <= {args.max_steps} "
        f"steps (sarsa: 2 instances); median of {args.repeats}; "
        f"mujoco {mujoco.__version__}; load average before/after "
        f"{load[0]:.1f}/{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores "
        "(other processes make every figure noisy, the 2-worker one most)"
    )
    for name, value in median.items():
        spread = ", ".join(f"{v:.0f}" for v in results[name])
        print(f"  {name:<20} {value:>10.0f} mj_step/s   ({spread})")
    raw, one = median["raw"], median["open-loop 1 core"]
    two = median["open-loop 2 workers"]
    print(f"  open-loop 1 core / raw        {one / raw:5.2f}   (target >= 0.5)")
    print(f"  open-loop 2 workers / 1 core  {two / one:5.2f}   (target >= 1.8)")
    print(f"  random 1 core / raw           {median['random 1 core'] / raw:5.2f}")
    print(f"  sarsa 1 core / raw            {median['sarsa 1 core'] / raw:5.2f}")


if __name__ == "__main__":
    main()
