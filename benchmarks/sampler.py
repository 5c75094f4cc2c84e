"""Speed of the blocked Gibbs sampler: structured (eigenbasis) vs dense reference.

Run:  python -m benchmarks.sampler   (3-10 min: the dense sweeps)
      python -m benchmarks.sampler --quick

(On a shared machine a multi-threaded BLAS spins against the other processes and
is many times slower than one thread; drop the variable on an idle machine.)

At paper scale (m = 750 support points, B = 7 instances, 2 actions × 4 dimensions →
R = 8 rows), on synthetic data drawn from the model (3 latent features), it prints,
measured side by side in one run from the same state:

1. the time of one full sweep, structured vs dense, and their ratio. The dense
   new-feature step factors a (B·m)² matrix per weight draw, so both sweeps use
   N_w = 4 here (stated in the output); the structured sweep is also timed at
   N_w = 1000, the setting used for fitting;
2. the time of single conditionals, structured vs dense (f-block of one row, one
   z decision, one new-feature weight draw, the w-block);
3. the seconds of a whole 250-sweep fit (one chain, N_w = 1000, `run_chains`);
4. the sweep time for m ∈ {250, 500, 1000, 2000}, with the warm state's number of
   features K+ (dense only for m ≤ 500: one dense sweep at m = 1000 factors ~40
   matrices of size 7000²).

Timings are wall-clock medians; the machine is shared, so they are noisy.
"""

from __future__ import annotations

# first, before numpy loads: one BLAS thread, headless MuJoCo (tasks/__init__.py)
import tasks  # noqa: F401

# isort: split

import argparse
import time

import numpy as np

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

B, A, D = 7, 2, 4
R = A * D


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


def timed(fn, repeat: int = 1) -> float:
    """Median wall-clock seconds of `repeat` calls of fn()."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def warm_state(data, priors, cache, n: int = 10):
    """A realistic state: n structured sweeps from `init_state`."""
    rng = np.random.default_rng(1)
    state = init_state(data, priors, rng=rng, cache=cache)
    for _ in range(n):
        state = gibbs_sweep(state, data, priors, cache, rng=rng)
    return state


def sweeps(m: int, n_w: int, with_dense: bool, repeat: int) -> tuple[float, float, int]:
    """(structured, dense) seconds of one sweep from the same warm state, and its
    number of features K+."""
    data = synthetic(m, rng=np.random.default_rng(0))
    priors = GibbsPriors(alpha=2.0, sigma_w=4.0, sigma_w0=1.0, n_w=n_w)
    cache = prepare(data)
    state = warm_state(data, priors, cache)

    def run_fast():
        gibbs_sweep(state, data, priors, cache, rng=np.random.default_rng(2))

    def run_dense():
        dense.dense_gibbs_sweep(state, data, priors, rng=np.random.default_rng(2))

    t_fast = timed(run_fast, repeat)
    t_dense = timed(run_dense, 1) if with_dense else float("nan")
    return t_fast, t_dense, state.n_features


def conditionals(m: int) -> None:
    """Single conditionals at size m, structured vs dense."""
    rng = np.random.default_rng(3)
    data = synthetic(m, rng=rng)
    cache = prepare(data)
    W = rng.normal(size=(B, 3))
    Wn = rng.normal(size=(1000, B, 1))  # N_w = 1000 draws of one new feature
    E = data.Y[0]
    Et = cache.Yt[0]
    z = np.ones((4, R), dtype=bool)
    f = rng.normal(size=(4, R, m))
    ft = fast.to_eigen(f, cache)
    mu = np.zeros(4)
    rows = [
        (
            "f-block, one row (k=3)",
            lambda: fast.f_posterior(Et, W, cache.lam[0], 1e-2),
            lambda: dense.f_posterior(E, W, data.K[0], 1e-2),
        ),
        (
            "z decision (one k, r)",
            lambda: fast.z_llr(Et, W[:, 0], cache.lam[0], 1e-2),
            lambda: dense.marginal_llr(E, W[:, :1], data.K[0], 1e-2),
        ),
        (
            "new feature, per weight draw",
            lambda: fast.new_llr(Et, Wn, cache.lam[0], 1e-2),
            lambda: dense.marginal_llr(E, W[:, :1], data.K[0], 1e-2),
        ),
        (
            "w-block (all instances)",
            lambda: fast.w_posterior(z, ft, cache.Yt, data.noise, mu, 4.0),
            lambda: dense.w_posterior(z, f, data.Y, data.noise, mu, 4.0),
        ),
    ]
    print(f"\nsingle conditionals at m = {m} (seconds; new feature: 1000 draws / 1000)")
    print(f"{'conditional':32s} {'structured':>12s} {'dense':>10s} {'ratio':>8s}")
    for name, f_fast, f_dense in rows:
        t_fast = timed(f_fast, 5)
        if name.startswith("new feature"):
            t_fast /= len(Wn)
        t_dense = timed(f_dense, 1)
        print(f"{name:32s} {t_fast:12.2e} {t_dense:10.3f} {t_dense / t_fast:8.0f}x")


def main(quick: bool = False) -> None:
    m = 250 if quick else 750
    print(f"sampler benchmark: m = {m}, B = {B}, R = {R} (A = {A}, D = {D})")
    t_fast, t_dense, k = sweeps(m, n_w=4, with_dense=True, repeat=5)
    print(f"\none sweep, N_w = 4, from a state with K+ = {k} features:")
    ratio = t_dense / t_fast
    print(f"  structured {t_fast:.4f} s   dense {t_dense:.2f} s   ratio {ratio:.0f}x")
    t_fast_1000 = sweeps(m, n_w=1000, with_dense=False, repeat=5)[0]
    print(f"  structured sweep at N_w = 1000: {t_fast_1000:.4f} s")
    conditionals(m)

    data = synthetic(m, rng=np.random.default_rng(0))
    priors = GibbsPriors(alpha=2.0, sigma_w=4.0, sigma_w0=1.0, n_w=1000)
    t = time.perf_counter()
    res = run_chains(
        data,
        priors,
        n_sweeps=250,
        n_chains=1,
        rng=np.random.default_rng(5),
        progress=False,
    )
    t_fit = time.perf_counter() - t
    print(
        f"\n250-sweep fit (1 chain, N_w = 1000, incl. eigendecompositions): "
        f"{t_fit:.1f} s; final K+ = {res.n_features[0, -1]}"
    )

    print("\nsweep time vs m (N_w = 1000 structured; dense at N_w = 4, m <= 500 only)")
    print("(the warm state's K+ features differ with m; a sweep's cost grows with K+)")
    print(f"{'m':>6s} {'K+':>4s} {'structured':>12s} {'dense':>10s}")
    for mm in (250, 500) if quick else (250, 500, 1000, 2000):
        tf, _, kk = sweeps(mm, n_w=1000, with_dense=False, repeat=3)
        td = sweeps(mm, n_w=4, with_dense=True, repeat=1)[1] if mm <= 500 else None
        dtxt = f"{td:10.2f}" if td is not None else f"{'-':>10s}"
        print(f"{mm:6d} {kk:4d} {tf:12.4f} {dtxt}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.sampler", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--quick", action="store_true", help="m = 250, no m sweep")
    main(parser.parse_args().quick)
