"""Simulation speed: raw `mujoco.mj_step` against our dm_control environments.

    python -m benchmarks.simulation [--steps 5000]

For each domain, measured side by side in one run on the same compiled model:

- raw: `mujoco.mj_step(model, data, n_sub_steps)` with the control set from the
  action table, i.e. exactly the physics of one environment step, nothing else;
- env: `env.step(a)` of `tasks.acrobot.swingup` / `tasks.cartpole.balance` with
  uniformly random actions, resetting when an episode ends (observations, reward,
  termination, action checks and resets included).

Prints control steps per second for both (and raw MuJoCo physics steps per second)
and the ratio env / raw: the fraction of raw speed the environment keeps.
"""

from __future__ import annotations

# first, before numpy loads: one BLAS thread, headless MuJoCo (tasks/__init__.py)
import tasks  # noqa: F401

# isort: split

import argparse
import time

import mujoco
import numpy as np

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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.simulation", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--steps", type=int, default=5000, help="control steps")
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    rng = np.random.default_rng(0)
    print(f"{args.steps} control steps per measurement, mujoco {mujoco.__version__}")
    header = f"{'domain':<9} {'sub':>3} {'raw mj_step/s':>14} {'raw ctrl/s':>11}"
    print(f"{header} {'env ctrl/s':>11} {'env/raw':>8}")
    for name, factory in DOMAINS.items():
        env = factory(seed=0)
        module = acrobot if name == "acrobot" else cartpole
        n_sub = module.N_SUB_STEPS
        model = env.physics.model.ptr
        raw = raw_steps_per_second(model, module.ACTIONS, args.steps, n_sub, rng)
        ours = env_steps_per_second(env, len(module.ACTIONS), args.steps, rng)
        print(
            f"{name:<9} {n_sub:>3} {raw * n_sub:>14.0f} {raw:>11.0f} "
            f"{ours:>11.0f} {ours / raw:>8.2f}"
        )


if __name__ == "__main__":
    main()
