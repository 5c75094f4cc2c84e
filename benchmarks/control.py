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

Every row is called once untimed (a warm-up), then measured ``--repeats`` times,
all rows in turn, the order reversed on every other repeat
(``benchmarks.timing.paired``); rates are medians, ratios the median of the
repeats' ratios with their range. Each call of a learning or planning row starts
from the same agent, instance and seed, so every repeat does the same work. The
raw rate is ``benchmarks.simulation``'s ``env.step`` loop (actions drawn before
the clock starts). Before timing, the GP rows' predictions at the real task's
states are checked to agree (see ``check_same_predictions``).

    python -m benchmarks.control --domain acrobot [--repeats 5]
"""

from __future__ import annotations

# first, before numpy loads: one BLAS thread, headless MuJoCo (tasks/__init__.py)
import tasks  # noqa: F401

# isort: split

import argparse
import time
from collections.abc import Callable

import numpy as np

from benchmarks.simulation import env_steps_per_second
from benchmarks.timing import paired, ratio_text
from hipmdp.baselines import GPBaseline, batch_only
from hipmdp.planning import LearnedModel, plan
from hipmdp.sarsa import epsilon_greedy
from tasks.agents import DOMAINS, LearnResult, SimulatorModel, learn
from tasks.experiment import printable_output


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


def per_second(fn: Callable[[], int]) -> float:
    """Run ``fn`` (returning a step count); steps per wall-clock second."""
    start = time.perf_counter()
    steps = fn()
    return steps / (time.perf_counter() - start)


def check_same_predictions(gp: GPBaseline, models: dict, data) -> None:
    """The GP rows differ only in how E[Δ] = Σ_j k(s, x_j) α_j is computed: their
    predictions at the data's states must agree to round-off. The sum's terms
    cancel (here up to ~1e6 for means ~1: the GPs are conditioned with little
    noise), so round-off is relative to its terms' size, at most σ_f²‖α‖₁ per
    (action, dimension): measured ≤ 4e-16 of it, allowed 1e-13 (1e-9 of the
    mean where that is larger)."""
    scale = np.array(
        [
            [
                0.0 if p is None else p.hyper.signal_var * np.abs(p.alpha).sum()
                for p in row
            ]
            for row in gp.posteriors
        ]
    )  # (A, D)
    S, acts = data.states, data.actions
    want = models["predict (mean+var)"].predict(S, acts)
    tol = np.maximum(1e-13 * scale[acts], 1e-9 * np.abs(want))
    for name in ("predict_mean", "mean_predictor"):
        err = np.abs(models[name].predict(S, acts) - want)
        if not np.all(err <= tol):
            worst = np.unravel_index(np.argmax(err / tol), err.shape)
            raise AssertionError(
                f"{name}: predictions differ from predict's by {err[worst]:.3e} at "
                f"{worst}, allowed {tol[worst]:.3e}"
            )


def main(argv: list[str] | None = None) -> dict[str, float]:
    printable_output()
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
    parser.add_argument(
        "--repeats", type=int, default=5, help="paired measurements of every row"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--no-progress", action="store_true", help="no progress bars (warm-up only)"
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    domain = DOMAINS[args.domain]
    progress = not args.no_progress
    rng = np.random.default_rng(args.seed)
    basis = domain.basis()
    env = domain.make_env(None, seed=args.seed)

    def raw() -> float:
        return env_steps_per_second(env, domain.n_actions, args.raw_steps, rng)

    states = rng.uniform(basis.low, basis.high, size=(2000, basis.state_dim))
    weights = rng.normal(size=(domain.n_actions, basis.n_features))

    def select() -> int:
        for s in states:
            epsilon_greedy(weights @ basis(s), 0.0, rng=rng)
        return len(states)

    def real(progress: bool = False) -> LearnResult:
        # a fresh instance and stream: every call does the same work
        env = domain.make_env(None, seed=args.seed)
        rng = np.random.default_rng(args.seed)
        return learn(env, domain, args.episodes, rng=rng, progress=progress)

    # the first call of every row is untimed (a warm-up); this one's result is
    # the agent and the data the planning rows start from
    result = real(progress)
    env_steps_per_second(env, domain.n_actions, args.raw_steps // 10 + 1, rng)
    select()
    starts = result.transitions.states[
        np.concatenate([[0], np.flatnonzero(result.transitions.dones[:-1]) + 1])
    ]
    task = domain.planning_task(None, domain.max_steps)
    gp_task = domain.planning_task(None, args.model_steps)
    gp = batch_only(
        result.transitions, rng=np.random.default_rng(args.seed + 1), n_max=args.gp_size
    )
    models = {
        "predict (mean+var)": LearnedModel(
            FullPredict(gp), angle_dims=domain.angle_dims
        ),
        "predict_mean": LearnedModel(MeanOnly(gp), angle_dims=domain.angle_dims),
        "mean_predictor": LearnedModel(gp, angle_dims=domain.angle_dims),
    }
    check_same_predictions(gp, models, result.transitions)

    def on(model, n_parallel: int = 1, task=task, progress=False) -> Callable[[], int]:
        def run() -> int:
            # a fresh stream: every call does the same work
            out = plan(result.state, basis, domain.sarsa, model, task, starts,
                       args.plan_episodes, rng=np.random.default_rng(args.seed + 2),
                       n_parallel=n_parallel, progress=progress)  # fmt: skip
            return int(out.steps.sum())

        return run

    rows: dict[str, Callable[[], float]] = {
        "raw simulator (env.step)": raw,
        "action selection (phi + argmax)": lambda: per_second(select),
        "Sarsa on the real task": lambda: per_second(lambda: int(real().steps.sum())),
    }
    plans = {"Sarsa planning, true model": on(SimulatorModel(domain))}
    for name, model in models.items():
        plans[f"Sarsa planning, GP {name}"] = on(model, task=gp_task)
    fused = models["mean_predictor"]
    plans[f"Sarsa planning, GP mean_predictor, {args.parallel} in lockstep"] = on(
        fused, args.parallel, task=gp_task
    )
    for name, run in plans.items():
        rows[name] = lambda run=run: per_second(run)
    for run in plans.values():  # warm-up
        run()
    rates = paired(rows, args.repeats)
    raw_rates = rates["raw simulator (env.step)"]

    print(
        f"\n{domain.name}: order-{domain.order} Fourier basis, "
        f"{basis.n_features} features x {domain.n_actions} actions; GP model on "
        f"{len(result.transitions)} transitions (<= {args.gp_size} per action "
        f"conditioned on); simulated episodes on GP models cut at {args.model_steps}"
    )
    print(
        f"medians of {args.repeats} paired repeats; '/ raw sim' is the median of "
        "the repeats' ratios (range)"
    )
    print(f"{'':54s} {'steps/s':>8s}  / raw sim")
    for name, r in rates.items():
        print(f"{name:54s} {np.median(r):8.0f}  {ratio_text(r, raw_rates)}")
    m_pm = rates["Sarsa planning, GP mean_predictor"]
    pm = rates["Sarsa planning, GP predict_mean"]
    print(f"mean_predictor / predict_mean planning rate: {ratio_text(m_pm, pm)}")
    return {name: float(np.median(r)) for name, r in rates.items()}


if __name__ == "__main__":
    main()
