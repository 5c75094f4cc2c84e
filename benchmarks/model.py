"""Benchmark of `hipmdp.fit` at paper scale and of the online filter.

Run:  python -m benchmarks.model [--sweeps 250] [--chains 2] [--repeats 3]
      python -m benchmarks.model --small   (tiny sizes, seconds: runs the checks
                                         for tests; its figures mean nothing)

Data: B = 7 training instances of a synthetic HiP-MDP with 2 actions and 4-dimensional
states (two latent parameters acting on different (action, dimension) rows), 6000
transitions per instance. Prints:

- seconds of each pre-sampler stage on its own (hyperparameters, support points with
  m = 750, per-instance smoothing) and of the whole `hipmdp.fit` (m = 750, 250 sweeps,
  FitConfig's default chains), each timed once;
- filter latency: one single-transition `update`, with the paper's filter and with
  the model-error filter side by side, and followed by a single-state `predict` or
  `predict_mean` (200 transitions in a row per measurement, 50 with --small);
- single-state means at a fixed belief, as planning calls them: `predict_mean`
  against `mean_predictor(belief)` (the features folded into one
  `hipmdp.kernels.KernelMeans`), side by side, and the predictor's one-off build;
- batched `predict`, `predict_mean` and `mean_predictor` throughput in states per
  second.

The means are first compared (also the warm-up), to a relative 1e-9: single
states, `mean_predictor` against `predict_mean`; batched, both against
`predict`'s mean. The comparisons are `--repeats` measurements of each side
taken in turn (`benchmarks.timing.paired`); figures are medians, ratios the
median of the repeats' ratios with their range.
"""

from __future__ import annotations

# first, before numpy loads: one BLAS thread, headless MuJoCo (tasks/__init__.py)
import tasks  # noqa: F401

# isort: split

import argparse
import time

import numpy as np

import hipmdp
from benchmarks.timing import paired, ratio_text, seconds
from hipmdp.fitting import FitConfig, smooth_onto_support
from hipmdp.gp import fit_hyper_set
from hipmdp.support import select_support
from tasks.experiment import printable_output

A, D, B, N_PER = 2, 4, 7, 6000


def true_deltas(S: np.ndarray, acts: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Δs = f_1(s, a) + w_1 g_1(s, a) on dims 1 and 3, + w_2 g_2(s) on dim 1, a = 0."""
    u = 2.0 * acts - 1.0
    delta = 0.05 * np.roll(S, -1, axis=1)  # position-like dims follow velocities
    delta[:, 1] += 0.1 * np.sin(S[:, 2]) + 0.05 * u + w[0] * 0.05 * np.cos(S[:, 2]) * u
    delta[:, 3] += 0.1 * np.sin(S[:, 2] + S[:, 0]) + w[0] * 0.04 * np.sin(S[:, 2])
    delta[:, 1] += w[1] * 0.03 * np.cos(S[:, 3]) * (acts == 0)
    return delta


def make_batch(
    rng: np.random.Generator, n_per: int = N_PER
) -> tuple[hipmdp.Transitions, np.ndarray]:
    W = rng.uniform(-1.5, 1.5, size=(B, 2))
    parts = []
    for b in range(B):
        S = rng.normal(size=(n_per, D))
        acts = rng.integers(0, A, size=n_per)
        delta = true_deltas(S, acts, W[b]) + 1e-3 * rng.normal(size=(n_per, D))
        parts.append(hipmdp.Transitions(S, acts, S + delta, np.full(n_per, b)))
    return hipmdp.Transitions.concatenate(parts), W


def timed(fn):
    """fn()'s result and its wall-clock seconds (one call: for the stages)."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


# --small: every size cut so that a test runs the whole script, checks included,
# in seconds with --sweeps 3 --chains 1 (300 transitions per instance, m = 30,
# 50 filter transitions, 1,000 batched states)
SMALL = dict(n_support=30, n_hyper=100, n_candidates=200, n_smooth=100, n_residual=200)


def main(argv: list[str] | None = None) -> None:
    printable_output()
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.model", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--sweeps", type=int, default=250)
    parser.add_argument("--chains", type=int, default=FitConfig.n_chains)
    parser.add_argument(
        "--repeats", type=int, default=3, help="paired repeats per comparison"
    )
    parser.add_argument(
        "--small",
        action="store_true",
        help="tiny sizes (for tests: the checks run, the figures mean nothing)",
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    n_per, n_filter, n_batched = (
        (300, 50, 1000) if args.small else (N_PER, 200, 100_000)
    )
    rng = np.random.default_rng(0)
    batch, _ = make_batch(rng, n_per)
    config = FitConfig(
        **(SMALL if args.small else dict(n_support=750)),
        n_sweeps=args.sweeps,
        n_chains=args.chains,
        progress=False,
    )
    print(
        f"data: B={B} instances x {n_per} transitions, A={A}, D={D}; "
        f"m={config.n_support}, {config.n_sweeps} sweeps x {config.n_chains} chains"
        f"; {n_filter} filter transitions"
    )

    deltas = batch.deltas
    hyper, t = timed(
        lambda: fit_hyper_set(
            batch.states,
            batch.actions,
            deltas,
            batch.instances,
            A,
            n_subsample=config.n_hyper,
            rng=np.random.default_rng(1),
        )
    )
    print(f"stage hyperparameters ({config.n_hyper} per action): {t:8.2f} s")
    support, t = timed(
        lambda: select_support(
            batch.states,
            hyper,
            config.n_support,
            n_candidates=config.n_candidates,
            rng=np.random.default_rng(2),
        )
    )
    print(f"stage support points ({config.n_candidates} candidates): {t:8.2f} s")
    _, t = timed(
        lambda: smooth_onto_support(
            batch,
            support.points,
            hyper,
            n_smooth=config.n_smooth,
            rng=np.random.default_rng(3),
        )
    )
    print(f"stage smoothing ({config.n_smooth} per instance-action): {t:8.2f} s")

    model, t = timed(lambda: hipmdp.fit(batch, config, rng=np.random.default_rng(4)))
    print(f"hipmdp.fit total: {t:8.2f} s   (K = {model.n_features} features)")

    # Filter latency: single-transition update + single-state predict.
    new = make_batch(np.random.default_rng(5), n_per)[0]
    new = new.select(instances=[0]).head(n_filter)
    singles = [
        hipmdp.Transitions(
            new.states[i : i + 1],
            new.actions[i : i + 1],
            new.next_states[i : i + 1],
            new.instances[i : i + 1],
        )
        for i in range(len(new))
    ]
    # The Cholesky factors of the support kernels are computed on first use: do
    # that before timing. predict = mean and variance (the variance needs an m x m
    # triangular solve per state and (a, d)); predict_mean = what planning calls.
    # The model-error filter needs the same solve for the transition's action.
    model.interpolation_var(new.states[:A], np.arange(A))

    def latency(model_error: bool, then: str | None) -> float:
        belief = model.prior()
        t0 = time.perf_counter()
        for one in singles:
            belief = model.update(belief, one, model_error=model_error)
            if then is not None:
                getattr(model, then)(one.states, one.actions, belief)
        return (time.perf_counter() - t0) / len(singles)

    filters = {
        "paper": lambda: latency(False, None),
        "error": lambda: latency(True, None),
        "predict": lambda: latency(True, "predict"),
        "predict_mean": lambda: latency(True, "predict_mean"),
    }
    lat = paired(filters, args.repeats, warm_up=filters)
    paper, err = np.median(lat["paper"]), np.median(lat["error"])
    print(f"filter update, one transition, paper filter: {paper * 1e3:8.3f} ms")
    print(
        f"filter update, one transition, model-error filter: {err * 1e3:8.3f} ms"
        f"   ({ratio_text(lat['error'], lat['paper'])} the paper filter)"
    )
    for name in ("predict", "predict_mean"):
        t = np.median(lat[name])
        print(f"filter update + {name}, one transition: {t * 1e3:8.3f} ms")
    belief = model.update(model.prior(), new)

    # Planning: one state at a time at a fixed belief. Building the fused
    # predictor is timed too: planning pays it once per belief (per planning
    # stage), predict_mean pays its share on every call.
    fused = model.mean_predictor(belief)
    one = [(s[None], a[None]) for s, a in zip(new.states, new.actions, strict=True)]
    single = {
        "predict_mean": lambda: [model.predict_mean(s, a, belief) for s, a in one],
        "mean_predictor": lambda: [fused(s, a) for s, a in one],
    }
    close(single["mean_predictor"](), single["predict_mean"](), "single-state means")
    t = paired(
        {k: (lambda fn=fn: seconds(fn)) for k, fn in single.items()}, args.repeats
    )
    slow, fast = np.median(t["predict_mean"]), np.median(t["mean_predictor"])
    build = seconds(lambda: model.mean_predictor(belief), 21)
    print(
        f"single-state predict_mean vs mean_predictor: {slow / len(one) * 1e6:8.1f} "
        f"vs {fast / len(one) * 1e6:8.1f} us  "
        f"({ratio_text(t['predict_mean'], t['mean_predictor'])}); building "
        f"the mean_predictor once: {build * 1e6:.0f} us ({build / fast * len(one):.1f}"
        " of its calls)"
    )

    S = np.random.default_rng(6).normal(size=(n_batched, D))
    acts = np.random.default_rng(7).integers(0, A, size=len(S))
    calls = {
        "predict": lambda: model.predict(S, acts, belief)[0],
        "predict_mean": lambda: model.predict_mean(S, acts, belief),
        "mean_predictor": lambda: fused(S, acts),
    }
    means = {name: fn() for name, fn in calls.items()}  # also the warm-up
    close(means["predict_mean"], means["predict"], "batched predict_mean")
    close(means["mean_predictor"], means["predict"], "batched mean_predictor")
    t = paired(
        {k: (lambda fn=fn: seconds(fn)) for k, fn in calls.items()}, args.repeats
    )
    for name in calls:
        sec = np.median(t[name])
        print(
            f"batched {name}: {len(S) / sec:12.0f} states/s  "
            f"({len(S)} states, {sec:.2f} s)"
        )
    print(
        "batched mean_predictor / predict_mean: "
        f"{ratio_text(t['predict_mean'], t['mean_predictor'])}"
    )


def close(got, want, what: str) -> None:
    """got equals want to a relative 1e-9 (the same means, computed differently),
    near zeros relative to want's largest entry."""
    got, want = np.asarray(got), np.asarray(want)
    atol = 1e-9 * float(np.max(np.abs(want), initial=0.0))
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=atol, err_msg=what)


if __name__ == "__main__":
    main()
