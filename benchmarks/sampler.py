"""Speed of the blocked Gibbs sampler: structured (eigenbasis) vs dense reference.

Run:  python -m benchmarks.sampler [--repeats 3]   (~11 min on two cores)
      python -m benchmarks.sampler --quick       (m = 250, no m sweep; ~1 min)

(On a shared machine a multi-threaded BLAS spins against the other processes and
is many times slower than one thread; drop the variable on an idle machine.)

At paper scale (m = 750 support points, B = 7 instances, 2 actions × 4 dimensions →
R = 8 rows), on synthetic data drawn from the model (3 latent features), it prints,
measured side by side in one run:

1. the time of one full sweep, structured vs dense, and their ratio. The dense
   new-feature step factors a (B·m)² matrix per weight draw, so both sweeps use
   N_w = 4 here; the structured sweep is also timed at N_w = 1000, the setting
   used for fitting. All three start from one warm state (10 structured sweeps
   at N_w = 1000), whose K+ is printed;
2. the time of single conditionals, structured vs dense (f-block of one row, one
   z decision, one new-feature weight draw, the w-block);
3. the seconds of a whole 250-sweep fit (one chain, N_w = 1000, `run_chains`),
   timed once;
4. (not with --quick) the sweep time for m ∈ {250, 500, 1000, 2000}, every column
   of a row from that m's one warm state (dense only for m ≤ 500: one dense sweep
   at m = 1000 factors ~40 matrices of size 7000²).

Before timing, each pair's first calls are compared (also their warm-up): the
conditionals' outputs to a relative 1e-9, and one sweep of each side from the warm
state with the same seed, draws replaced by their means (`gibbs_dense.MeanDraws`),
z exactly and w, f, μ_w to 1e-9. Each figure is the median of `--repeats`
measurements taken in turn with the other side's (`benchmarks.timing.paired`), a
ratio the median of the repeats' ratios with their range; a structured
measurement is itself the median of 5 calls.
"""

from __future__ import annotations

# first, before numpy loads: one BLAS thread, headless MuJoCo (tasks/__init__.py)
import tasks  # noqa: F401

# isort: split

import argparse
import time
from typing import NamedTuple

import numpy as np

from benchmarks.timing import paired, ratio_text, seconds
from hipmdp import gibbs_dense as dense
from hipmdp import gibbs_eigen as fast
from hipmdp.gibbs import (
    GibbsData,
    GibbsPriors,
    gibbs_sweep,
    init_state,
    prepare,
    run_chains,
)
from hipmdp.gibbs_dense import MeanDraws
from hipmdp.gibbs_sweep import sweep
from tasks.experiment import printable_output

B, A, D = 7, 2, 4
R = A * D
RTOL = 1e-9  # structured against dense: the same math, different round-off


def synthetic(m: int, *, rng: np.random.Generator) -> GibbsData:
    """Data drawn from the model: S* uniform in [-2, 2]^D, an SE kernel per row with
    its own length scales, 3 latent features on random rows, noise σ² = 1e-2."""
    S = rng.uniform(-2, 2, size=(m, D))
    K = np.empty((R, m, m))
    for r in range(R):
        ell = rng.uniform(0.8, 2.0, size=D)
        d2 = (((S[:, None, :] - S[None, :, :]) / ell) ** 2).sum(-1)
        K[r] = np.exp(-0.5 * d2) + 1e-4 * np.eye(m)  # jitter: dense needs K⁻¹
    z = rng.random((4, R)) < 0.5
    z[0] = True
    w = np.vstack([np.ones(B), 2.0 * rng.normal(size=(3, B))])
    lam, U = np.linalg.eigh(K)
    f = np.einsum(
        "rmj,rj,krj->krm", U, np.sqrt(np.maximum(lam, 0)), rng.normal(size=(4, R, m))
    )
    noise = np.full(R, 1e-2)
    Y = np.einsum("kr,kb,krm->rbm", z, w, f)
    Y += np.sqrt(noise[0]) * rng.normal(size=Y.shape)
    return GibbsData(Y, K, noise)


def warm_state(data, priors, cache, n: int = 10):
    """A realistic state: n structured sweeps from `init_state`."""
    rng = np.random.default_rng(1)
    state = init_state(data, priors, rng=rng, cache=cache)
    for _ in range(n):
        state = gibbs_sweep(state, data, priors, cache, rng=rng)
    return state


def priors_at(n_w: int) -> GibbsPriors:
    return GibbsPriors(alpha=2.0, sigma_w=4.0, sigma_w0=1.0, n_w=n_w)


def close(got, want, what: str) -> None:
    """got equals want to RTOL, relative to want's largest entry near zeros."""
    want = np.asarray(want)
    atol = RTOL * float(np.max(np.abs(want), initial=0.0))
    np.testing.assert_allclose(got, want, rtol=RTOL, atol=atol, err_msg=what)


def check_sweeps(state, data, priors, cache) -> None:
    """One sweep of each side from `state` with the same seed agrees: z exactly,
    w, f and μ_w to RTOL (draws replaced by their means, `gibbs_dense.MeanDraws`:
    the two sides draw through different square roots of one covariance)."""
    ft = fast.to_eigen(state.f, cache)
    algebras = [
        (MeanDraws(fast.EigenAlgebra(cache)), ft),
        (MeanDraws(dense.DenseAlgebra(data)), state.f),
    ]
    (zs, ws, fs, mus), (zd, wd, fd, mud) = (
        sweep(
            alg, state.z, state.w, f, state.mu_w, priors, rng=np.random.default_rng(2)
        )
        for alg, f in algebras
    )
    np.testing.assert_array_equal(zs, zd, err_msg="sweep z")
    close(ws, wd, "sweep w")
    close(fast.from_eigen(fs, cache), fd, "sweep f")
    close(mus, mud, "sweep mu_w")


class Sweeps(NamedTuple):
    """Seconds of one sweep from one warm state (repeats,) per side; NaN without
    the dense side."""

    n_features: int
    fast_1000: np.ndarray
    fast_4: np.ndarray
    dense_4: np.ndarray


def sweeps(m: int, with_dense: bool, repeats: int) -> Sweeps:
    """One warm state at m (10 structured sweeps at N_w = 1000) and one sweep from
    it timed three ways, side by side: structured at N_w = 1000 and at N_w = 4,
    dense at N_w = 4 (the dense side first checked against the structured one)."""
    data = synthetic(m, rng=np.random.default_rng(0))
    cache = prepare(data)
    state = warm_state(data, priors_at(1000), cache)
    p4, p1000 = priors_at(4), priors_at(1000)
    sides = {
        "fast_1000": lambda: gibbs_sweep(
            state, data, p1000, cache, rng=np.random.default_rng(2)
        ),
        "fast_4": lambda: gibbs_sweep(
            state, data, p4, cache, rng=np.random.default_rng(2)
        ),
    }
    measure = {name: (lambda fn=fn: seconds(fn, 5)) for name, fn in sides.items()}
    if with_dense:
        check_sweeps(state, data, p4, cache)  # also the dense side's warm-up
        measure["dense_4"] = lambda: seconds(
            lambda: dense.dense_gibbs_sweep(
                state, data, p4, rng=np.random.default_rng(2)
            )
        )
    t = paired(measure, repeats, warm_up=sides)
    nan = np.full(repeats, np.nan)
    return Sweeps(state.n_features, t["fast_1000"], t["fast_4"], t.get("dense_4", nan))


def conditionals(m: int, repeats: int) -> None:
    """Single conditionals at size m, structured vs dense, each checked first."""
    rng = np.random.default_rng(3)
    data = synthetic(m, rng=rng)
    cache = prepare(data)
    W = rng.normal(size=(B, 3))
    Wn = rng.normal(size=(1000, B, 1))  # N_w = 1000 draws of one new feature
    E, Et, U = data.Y[0], cache.Yt[0], cache.U[0]
    z = np.ones((4, R), dtype=bool)
    f = rng.normal(size=(4, R, m))
    ft = fast.to_eigen(f, cache)
    mu = np.zeros(4)

    def check_f(p, ref):
        close((p.mean @ U.T).ravel(), ref.mean, "f-block mean")
        VU = np.kron(p.V, U)  # vec(F) = (V ⊗ U) vec(G), row-major
        close(VU @ (p.var.ravel()[:, None] * VU.T), ref.cov, "f-block cov")

    def check_w(p, ref):
        close(p[0], ref.mean, "w-block mean")
        close(p[1], ref.cov, "w-block cov")

    rows = [  # name, structured, dense, check(structured out, dense out), per call
        (
            "f-block, one row (k=3)",
            lambda: fast.f_posterior(Et, W, cache.lam[0], 1e-2),
            lambda: dense.f_posterior(E, W, data.K[0], 1e-2),
            check_f,
            1,
        ),
        (
            "z decision (one k, r)",
            lambda: fast.z_llr(Et, W[:, 0], cache.lam[0], 1e-2),
            lambda: dense.marginal_llr(E, W[:, :1], data.K[0], 1e-2),
            lambda a, b: close(a, b, "z decision"),
            1,
        ),
        (
            "new feature, per weight draw",
            lambda: fast.new_llr(Et, Wn, cache.lam[0], 1e-2),
            lambda: dense.marginal_llr(E, Wn[0], data.K[0], 1e-2),
            lambda a, b: close(a[0], b, "new feature"),
            len(Wn),
        ),
        (
            "w-block (all instances)",
            lambda: fast.w_posterior(z, ft, cache.Yt, data.noise, mu, 4.0),
            lambda: dense.w_posterior(z, f, data.Y, data.noise, mu, 4.0),
            check_w,
            1,
        ),
    ]
    print(
        f"\nsingle conditionals at m = {m}, seconds per call (medians of {repeats} "
        "paired repeats; new feature: 1000 draws / 1000)"
    )
    print(f"{'conditional':30s} {'structured':>10s} {'dense':>10s}  ratio (range)")
    for name, f_fast, f_dense, check, per in rows:
        check(f_fast(), f_dense())  # also the warm-up
        t = paired(
            {
                "fast": lambda fn=f_fast, per=per: seconds(fn, 5) / per,
                "dense": lambda fn=f_dense: seconds(fn),
            },
            repeats,
        )
        print(
            f"{name:30s} {np.median(t['fast']):10.2e} {np.median(t['dense']):10.2e}  "
            f"{ratio_text(t['dense'], t['fast'])}"
        )


def main(quick: bool = False, repeats: int = 3) -> None:
    m = 250 if quick else 750
    print(f"sampler benchmark: m = {m}, B = {B}, R = {R} (A = {A}, D = {D})")
    print(f"each figure: the median of {repeats} repeats, the sides in turn")
    sw = sweeps(m, with_dense=True, repeats=repeats)
    print(
        f"\none sweep from a warm state with K+ = {sw.n_features} features\n"
        "(the structured and dense sweeps checked to agree first):"
    )
    f4, d4 = np.median(sw.fast_4), np.median(sw.dense_4)
    print(
        f"  N_w = 4:    structured {f4:.4f} s   dense {d4:.2f} s   "
        f"ratio {ratio_text(sw.dense_4, sw.fast_4, 0)}"
    )
    print(f"  N_w = 1000: structured {np.median(sw.fast_1000):.4f} s")
    conditionals(m, repeats)

    data = synthetic(m, rng=np.random.default_rng(0))
    start = time.perf_counter()
    res = run_chains(
        data,
        priors_at(1000),
        n_sweeps=250,
        n_chains=1,
        rng=np.random.default_rng(5),
        progress=False,
    )
    t_fit = time.perf_counter() - start
    print(
        f"\n250-sweep fit (1 chain, N_w = 1000, incl. eigendecompositions; once): "
        f"{t_fit:.1f} s; final K+ = {res.n_features[0, -1]}"
    )
    if quick:
        return

    print(
        "\nsweep time vs m, every column from one warm state per m (its K+ "
        "features;\na sweep's cost grows with K+); dense at N_w = 4 for m <= 500 only"
    )
    print(
        f"{'m':>6s} {'K+':>4s} {'struct. Nw=1000':>16s} {'struct. Nw=4':>13s} "
        f"{'dense Nw=4':>11s}  dense/struct. at Nw=4"
    )
    for mm in (250, 500, 1000, 2000):
        sw = sweeps(mm, with_dense=mm <= 500, repeats=repeats)
        dense_txt = f"{np.median(sw.dense_4):11.2f}" if mm <= 500 else f"{'-':>11s}"
        ratio = ratio_text(sw.dense_4, sw.fast_4, 0) if mm <= 500 else "-"
        print(
            f"{mm:6d} {sw.n_features:4d} {np.median(sw.fast_1000):16.4f} "
            f"{np.median(sw.fast_4):13.4f} {dense_txt}  {ratio}"
        )


def cli(argv: list[str] | None = None) -> None:
    printable_output()
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.sampler", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--quick", action="store_true", help="m = 250, no m sweep (about a minute)"
    )
    parser.add_argument(
        "--repeats", type=int, default=3, help="paired repeats per figure (medians)"
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    main(args.quick, args.repeats)


if __name__ == "__main__":
    cli()
