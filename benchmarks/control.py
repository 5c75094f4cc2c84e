"""Control throughput: Sarsa(λ) steps per second on the real task and on models.

Measured side by side in one run, on one instance (nominal unless ``--param``):

- raw simulator: ``env.step`` with uniformly random actions, no learning;
- action selection: ``φ(s)`` and ``argmax_a θ_a · φ(s)`` for one state;
- Sarsa on the real task: :func:`tasks.agents.learn` (env step + features + update);
- Sarsa planning on the true model (:class:`tasks.agents.SimulatorModel`);
- Sarsa planning on a learned model: a "batch only" baseline GP
  (``hipmdp.baselines.batch_only``, one GP per (action, dimension) on the
  transitions the real-task agent saw) through :class:`hipmdp.planning.LearnedModel`:
  (a) forced through its full ``predict`` (mean and variance; the variance costs
  ``O(n²)`` per state), one episode at a time; (b) through its ``predict_mean``
  (``K(s, X) α``, ``O(n)`` per state, one kernel call per (action, dimension)); (c)
  through its ``mean_predictor`` (the same means, every dimension of an action in
  one :class:`hipmdp.kernels.KernelMeans` call: what ``LearnedModel`` uses when a
  model has it), one episode at a time and ``--parallel`` episodes in lockstep.
  (The HiP-MDP itself needs a multi-instance fit; this benchmark does not fit one:
  ``benchmarks/model.py`` times its ``predict_mean`` against its
  ``mean_predictor``.)

Every rate is also printed as a ratio to the raw simulator's steps/s. The planning
episodes start from the real episodes' initial states.

    python -m benchmarks.control --domain acrobot
"""

from __future__ import annotations

# first, before numpy loads: one BLAS thread, headless MuJoCo (tasks/__init__.py)
import tasks  # noqa: F401

# isort: split

import argparse
import time
from collections.abc import Callable

import numpy as np
from tqdm.auto import tqdm

from hipmdp.baselines import GPBaseline, batch_only
from hipmdp.planning import LearnedModel, plan
from hipmdp.sarsa import epsilon_greedy
from tasks.agents import DOMAINS, SimulatorModel, learn


class FullPredict:
    """Hides a model's ``predict_mean`` so that planning goes through its full
    ``predict`` (mean and variance)."""

    def __init__(self, model: GPBaseline) -> None:
        self.model = model

    def predict(self, states: np.ndarray, actions: np.ndarray):
        return self.model.predict(states, actions)


class MeanOnly(FullPredict):
    """Hides a model's ``mean_predictor`` so that planning calls its
    ``predict_mean`` (one kernel evaluation per (action, dimension) per call)."""

    def predict_mean(self, states: np.ndarray, actions: np.ndarray):
        return self.model.predict_mean(states, actions)


def timed(fn: Callable[[], int]) -> tuple[int, float]:
    """Run ``fn`` (returning a step count); return (steps, seconds)."""
    start = time.perf_counter()
    steps = fn()
    return steps, time.perf_counter() - start


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.control", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--domain", choices=sorted(DOMAINS), default="acrobot")
    parser.add_argument(
        "--episodes", type=int, default=20, help="real Sarsa episodes to learn from"
    )
    parser.add_argument(
        "--raw-steps", type=int, default=3000, help="random-action env steps timed"
    )
    parser.add_argument(
        "--plan-episodes", type=int, default=10, help="simulated episodes per model"
    )
    parser.add_argument(
        "--model-steps",
        type=int,
        default=200,
        help="step limit of simulated episodes on the GP models (keeps the run short)",
    )
    parser.add_argument(
        "--parallel", type=int, default=5, help="lockstep episodes on the GP model"
    )
    parser.add_argument(
        "--gp-size", type=int, default=500, help="GP transitions per action (n_max)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    domain = DOMAINS[args.domain]
    progress = not args.no_progress
    rng = np.random.default_rng(args.seed)
    basis = domain.basis()
    rates: dict[str, float] = {}

    env = domain.make_env(None, seed=args.seed)

    def raw() -> int:
        env.reset()
        for _ in tqdm(range(args.raw_steps), desc="raw env", disable=not progress):
            if env.step(int(rng.integers(domain.n_actions))).last():
                env.reset()
        return args.raw_steps

    n, dt = timed(raw)
    rates["raw simulator (env.step)"] = n / dt

    states = rng.uniform(basis.low, basis.high, size=(2000, basis.state_dim))
    weights = rng.normal(size=(domain.n_actions, basis.n_features))

    def select() -> int:
        for s in states:
            epsilon_greedy(weights @ basis(s), 0.0, rng=rng)
        return len(states)

    n, dt = timed(select)
    rates["action selection (phi + argmax)"] = n / dt

    result = None

    def real() -> int:
        nonlocal result
        env = domain.make_env(None, seed=args.seed)
        result = learn(env, domain, args.episodes, rng=rng, progress=progress)
        return int(result.steps.sum())

    n, dt = timed(real)
    rates["Sarsa on the real task"] = n / dt
    starts = result.transitions.states[
        np.concatenate([[0], np.flatnonzero(result.transitions.dones[:-1]) + 1])
    ]
    task = domain.planning_task(None, domain.max_steps)
    agent = result.state

    gp_task = domain.planning_task(None, args.model_steps)

    def on(model, n_parallel: int = 1, task=task) -> Callable[[], int]:
        def run() -> int:
            out = plan(agent, basis, domain.sarsa, model, task, starts,
                       args.plan_episodes, rng=rng, n_parallel=n_parallel,
                       progress=progress)  # fmt: skip
            return int(out.steps.sum())

        return run

    n, dt = timed(on(SimulatorModel(domain)))
    rates["Sarsa planning, true model"] = n / dt
    gp = batch_only(result.transitions, rng=rng, n_max=args.gp_size)
    full = LearnedModel(FullPredict(gp), angle_dims=domain.angle_dims)
    n, dt = timed(on(full, task=gp_task))
    rates["Sarsa planning, GP predict (mean+var)"] = n / dt
    mean_only = LearnedModel(MeanOnly(gp), angle_dims=domain.angle_dims)
    n, dt = timed(on(mean_only, task=gp_task))
    rates["Sarsa planning, GP predict_mean"] = n / dt
    fused = LearnedModel(gp, angle_dims=domain.angle_dims)
    n, dt = timed(on(fused, task=gp_task))
    rates["Sarsa planning, GP mean_predictor"] = n / dt
    n, dt = timed(on(fused, args.parallel, task=gp_task))
    rates[f"Sarsa planning, GP mean_predictor, {args.parallel} in lockstep"] = n / dt

    raw_rate = rates["raw simulator (env.step)"]
    print(
        f"\n{domain.name}: order-{domain.order} Fourier basis, "
        f"{basis.n_features} features x {domain.n_actions} actions; GP model on "
        f"{len(result.transitions)} transitions (<= {args.gp_size} per action "
        f"conditioned on); simulated episodes on GP models cut at {args.model_steps}"
    )
    print(f"{'':50s} {'steps/s':>10s} {'/ raw sim':>10s}")
    for name, rate in rates.items():
        print(f"{name:50s} {rate:10.0f} {rate / raw_rate:10.2f}")
    return rates


if __name__ == "__main__":
    main()
