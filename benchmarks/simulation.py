"""Simulation speed: raw `mujoco.mj_step` against our dm_control environments.

    python -m benchmarks.simulation [--steps 5000] [--repeats 7]

For each domain, measured side by side in one run on the same compiled model:

- raw: `mujoco.mj_step(model, data, n_sub_steps)` with the control set from the
  action table, i.e. exactly the physics of one environment step, nothing else;
- env: `env.step(a)` of `tasks.acrobot.swingup` / `tasks.cartpole.balance` with
  uniformly random actions, resetting when an episode ends (observations, reward,
  termination, action checks and resets included).

The two are measured in turn, `--repeats` times (the order alternating, raw
first, after one untimed warm-up of each). Prints the median control
steps per second of each (and raw MuJoCo physics steps per second) and the
median of the repeats' paired ratios env / raw: the fraction of raw speed the
environment keeps, with the ratios' range. (One timing per side gave ratios
0.80–1.02 on the acrobot over four runs on an idle machine.)
"""

from __future__ import annotations

# first, before numpy loads: one BLAS thread, headless MuJoCo (tasks/__init__.py)
import tasks  # noqa: F401

# isort: split

import argparse
import time

import mujoco
import numpy as np

from benchmarks.timing import paired
from tasks import acrobot, cartpole

DOMAINS = {"acrobot": acrobot.swingup, "cartpole": cartpole.balance}


def raw_steps_per_second(model, actions, n_steps, n_sub_steps, rng):
    """Control steps per second of plain `mj_step` calls."""
    data = mujoco.MjData(model)
    choices = rng.integers(len(actions), size=n_steps)
    start = time.perf_counter()
    for a in choices:
        data.ctrl[0] = actions[a]
        mujoco.mj_step(model, data, n_sub_steps)
    return n_steps / (time.perf_counter() - start)


def env_steps_per_second(env, n_actions, n_steps, rng):
    """Control steps per second of `env.step`, resets included."""
    choices = rng.integers(n_actions, size=n_steps)
    env.reset()
    start = time.perf_counter()
    for a in choices:
        if env.step(a).last():
            env.reset()
    return n_steps / (time.perf_counter() - start)


def paired_rates(env, module, n_steps: int, repeats: int, rng):
    """``repeats`` (raw, env) control-step rates measured in turn, the order
    alternating, after one untimed warm-up of each; two arrays."""
    model, n_sub = env.physics.model.ptr, module.N_SUB_STEPS
    sides = {
        "raw": lambda n: raw_steps_per_second(model, module.ACTIONS, n, n_sub, rng),
        "env": lambda n: env_steps_per_second(env, len(module.ACTIONS), n, rng),
    }
    rates = paired(
        {side: (lambda rate=rate: rate(n_steps)) for side, rate in sides.items()},
        repeats,
        warm_up={
            side: (lambda rate=rate: rate(n_steps // 10 + 1))
            for side, rate in sides.items()
        },
    )
    return rates["raw"], rates["env"]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.simulation", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--steps", type=int, default=5000, help="control steps")
    parser.add_argument("--repeats", type=int, default=7, help="paired measurements")
    args = parser.parse_args(argv)
    for name in ("steps", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    rng = np.random.default_rng(0)
    print(
        f"{args.steps} control steps per measurement, {args.repeats} paired "
        f"repeats (medians), mujoco {mujoco.__version__}"
    )
    header = f"{'domain':<9} {'sub':>3} {'raw mj_step/s':>14} {'raw ctrl/s':>11}"
    print(f"{header} {'env ctrl/s':>11} {'env/raw':>8} {'range':>11}")
    for name, factory in DOMAINS.items():
        env = factory(seed=0)
        module = acrobot if name == "acrobot" else cartpole
        n_sub = module.N_SUB_STEPS
        raws, envs = paired_rates(env, module, args.steps, args.repeats, rng)
        ratios = envs / raws
        raw, ours = float(np.median(raws)), float(np.median(envs))
        print(
            f"{name:<9} {n_sub:>3} {raw * n_sub:>14.0f} {raw:>11.0f} "
            f"{ours:>11.0f} {np.median(ratios):>8.2f} "
            f"{ratios.min():>5.2f}-{ratios.max():<5.2f}"
        )


if __name__ == "__main__":
    main()
