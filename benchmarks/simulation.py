"""Simulation speed: raw `mujoco.mj_step` against our dm_control environments.

    python -m benchmarks.simulation [--steps 5000] [--repeats 7]

For each domain, measured side by side in one run on the same compiled model:

- raw: `mujoco.mj_step(model, data, n_sub_steps)` with the control set from the
  action table, i.e. exactly the physics of one environment step, nothing else;
- env: `env.step(a)` of `tasks.acrobot.swingup` / `tasks.cartpole.balance` with
  uniformly random actions, resetting when an episode ends (observations, reward,
  termination, action checks and resets included).

Before timing, the two are checked to be the same physics
(``check_same_physics``): from the environment's reset state, the same actions
through both give bit-identical `qpos` and `qvel`. The two are measured in turn,
`--repeats` times (the order alternating, raw
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
from tasks.experiment import printable_output

#: Per domain: its environment factory and its module (`ACTIONS`, `N_SUB_STEPS`).
DOMAINS = {
    "acrobot": (acrobot.swingup, acrobot),
    "cartpole": (cartpole.balance, cartpole),
}


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


def check_same_physics(env, module, n_steps: int, rng) -> None:
    """Raise AssertionError unless ``n_steps`` random actions through
    ``env.step`` and through the raw side's `mj_step(model, data, N_SUB_STEPS)`
    with ``data.ctrl`` from ``module.ACTIONS`` give bit-identical `qpos` and
    `qvel` after every step, both starting from the environment's reset state
    (again after each reset): the raw side times exactly the environment's
    physics."""
    physics = env.physics
    model = physics.model.ptr
    data = mujoco.MjData(model)
    last = True
    for n, a in enumerate(rng.integers(len(module.ACTIONS), size=n_steps), 1):
        if last:
            env.reset()
            data.qpos[:], data.qvel[:] = physics.data.qpos, physics.data.qvel
            data.act[:], data.time = physics.data.act, physics.data.time
        last = env.step(a).last()
        data.ctrl[0] = module.ACTIONS[a]
        mujoco.mj_step(model, data, module.N_SUB_STEPS)
        for name in ("qpos", "qvel"):
            env_value, raw_value = getattr(physics.data, name), getattr(data, name)
            if not np.array_equal(env_value, raw_value):
                raise AssertionError(
                    f"{module.__name__}: env.step and raw mj_step differ in "
                    f"{name} after step {n} (action {a}): {env_value} against "
                    f"{raw_value}"
                )


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
    printable_output()
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
        f"repeats (medians), mujoco {mujoco.__version__}; env.step checked "
        "bit-identical to raw mj_step first"
    )
    header = f"{'domain':<9} {'sub':>3} {'raw mj_step/s':>14} {'raw ctrl/s':>11}"
    print(f"{header} {'env ctrl/s':>11} {'env/raw':>8} {'range':>11}")
    for name, (factory, module) in DOMAINS.items():
        env = factory(seed=0)
        n_sub = module.N_SUB_STEPS
        check_same_physics(env, module, args.steps, rng)
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
