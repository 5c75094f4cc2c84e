"""Blocked Gibbs sampler of the IBP-GP HiP-MDP: public API (DESIGN §2–§3).

Symbols (see `hipmdp.gibbs_model`): rows r = a·D + d (R = A·D prediction tasks, the
IBP's N = R customers), instances b (B), features k (Kf, feature 0 = mean dynamics,
not part of the IBP), m support points S*.

    data = GibbsData(Y=(R, B, m), K=(R, m, m), noise=(R,))
    priors = GibbsPriors(alpha, sigma_w, sigma_w0, n_w)
    cache = prepare(data)                        # eigendecompose each K[r] once
    state = init_state(data, priors, rng=rng)
    state = gibbs_sweep(state, data, priors, cache, rng=rng)   # pure
    result = run_chains(data, priors, n_sweeps=250, n_chains=4, rng=rng)

The sweep and the IBP bookkeeping are documented in `hipmdp.gibbs_sweep`, the
structured algebra in `hipmdp.gibbs_eigen`, the dense reference in
`hipmdp.gibbs_dense`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from tqdm.auto import tqdm

from hipmdp.data import check_integer
from hipmdp.gibbs_eigen import (
    EigenAlgebra,
    GibbsCache,
    from_eigen,
    log_joint_eigen,
    log_marginal_eigen,
    prepare,
    to_eigen,
)
from hipmdp.gibbs_model import (
    GibbsData,
    GibbsPriors,
    GibbsState,
    check_data,
    check_priors,
    check_state,
)
from hipmdp.gibbs_sweep import f_block, sweep

__all__ = [
    "ChainResult",
    "GibbsCache",
    "GibbsData",
    "GibbsPriors",
    "GibbsState",
    "gibbs_sweep",
    "init_state",
    "log_joint",
    "log_marginal",
    "prepare",
    "run_chains",
]

Array = np.ndarray


def _check_rng(rng, where: str) -> None:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"{where}: rng must be a numpy Generator, got {rng!r}")


def _check_cache(data: GibbsData, cache: GibbsCache) -> GibbsCache:
    """``cache`` if it was prepared from ``data``, else a ValueError: what reads
    the cache never looks at ``data`` again, so other data went unnoticed (a
    log_joint of Y * 2 scored the original Y). Compares the shapes, σ², Y
    (rotated back) and K's diagonal (from its eigendecomposition):
    O(R B m² + R m²), against the O(R m³) of preparing."""
    Y = np.asarray(data.Y, dtype=float)
    if Y.shape != cache.Yt.shape or not np.array_equal(data.noise, cache.noise):
        raise ValueError("cache: prepared from other data; use prepare(data)")
    scale = max(np.abs(Y).max(initial=0.0), 1e-300)
    Yback = cache.Yt @ np.swapaxes(cache.U, 1, 2)
    diag = np.diagonal(np.asarray(data.K, dtype=float), axis1=1, axis2=2)
    diag_back = np.einsum("rij,rj->ri", cache.U**2, cache.lam)
    top = cache.lam.max(axis=1, keepdims=True)
    if not np.allclose(Yback, Y, rtol=0, atol=1e-8 * scale) or not np.allclose(
        diag_back, diag, rtol=0, atol=1e-6 * top
    ):
        raise ValueError("cache: prepared from other data; use prepare(data)")
    return cache


def init_state(
    data: GibbsData,
    priors: GibbsPriors,
    *,
    rng: np.random.Generator,
    cache: GibbsCache | None = None,
) -> GibbsState:
    """A starting state: the mean dynamics only (z = [1,...,1], Kf = 1), f[0] drawn
    from its conditional. Latent features then enter through the new-feature step,
    whose weights are importance-resampled to fit the residual; a start with random
    features from the IBP prior instead begins far from the data and climbs slowly.
    `priors` is validated for symmetry with the sweep; `rng` draws f[0]."""
    data, priors = check_data(data), check_priors(priors)
    _check_rng(rng, "init_state")
    cache = prepare(data) if cache is None else _check_cache(data, cache)
    R, B, m = data.Y.shape
    z, w, mu_w = np.ones((1, R), dtype=bool), np.ones((1, B)), np.zeros(1)
    ft = f_block(EigenAlgebra(cache), z, w, np.zeros((1, R, m)), rng=rng)
    return GibbsState(z, w, from_eigen(ft, cache), mu_w)


def gibbs_sweep(
    state: GibbsState,
    data: GibbsData,
    priors: GibbsPriors,
    cache: GibbsCache,
    *,
    rng: np.random.Generator,
) -> GibbsState:
    """One full blocked Gibbs sweep (order and IBP bookkeeping: `hipmdp.gibbs_sweep`).

    Pure: returns a new GibbsState. `data` must be the data `cache` was prepared
    from. Cost O(Kf R m²) for rotating f in and out of the eigenbasis, O(Kf R B m)
    for the conditionals, O(N_w B m) per new-feature proposal.
    """
    priors = check_priors(priors)
    _check_rng(rng, "gibbs_sweep")
    _check_cache(data, cache)
    check_state(state, *cache.Yt.shape)
    ft = to_eigen(state.f, cache)
    z, w, ft, mu_w = sweep(
        EigenAlgebra(cache), state.z, state.w, ft, state.mu_w, priors, rng=rng
    )
    return GibbsState(z, w, from_eigen(ft, cache), mu_w)


def log_joint(
    state: GibbsState,
    data: GibbsData,
    priors: GibbsPriors,
    cache: GibbsCache | None = None,
) -> float:
    """log p(Y, z, w, f, μ_w), the joint log-probability traced per sweep:

    Σ_r,b log N(Y[r,b]; Σ_k z w f, σ²[r] I) + Σ_{z[k,r]=1} log N(f[k,r]; 0, K[r])
    + Σ_{k≥1} [Σ_b log N(w[k,b]; μ_w[k], σ_w²) + log N(μ_w[k]; 0, σ_w0²)]
    + log P_IBP([z[1:]])   (`hipmdp.gibbs_model.ibp_log_prior`)
    """
    priors = check_priors(priors)
    cache = prepare(data) if cache is None else _check_cache(data, cache)
    check_state(state, *cache.Yt.shape)
    ft = to_eigen(state.f, cache)
    return log_joint_eigen(state.z, state.w, ft, state.mu_w, priors, cache)


def log_marginal(
    state: GibbsState,
    data: GibbsData,
    priors: GibbsPriors,
    cache: GibbsCache | None = None,
) -> float:
    """log p(Y, z, w, μ_w) with every f marginalised (`log_marginal_eigen`)."""
    priors = check_priors(priors)
    cache = prepare(data) if cache is None else _check_cache(data, cache)
    check_state(state, *cache.Yt.shape)
    return log_marginal_eigen(state.z, state.w, state.mu_w, priors, cache)


class ChainResult(NamedTuple):
    """Result of `run_chains`.

    best: the kept sample (GibbsState); best_log_joint: its log_joint;
    best_score: its selection score; best_chain, best_sweep: where it was found;
    traces: log_joint per sweep (n_chains, n_sweeps);
    traces_marginal: log_marginal per sweep (n_chains, n_sweeps);
    n_features: K+ (feature 0 excluded) per sweep (n_chains, n_sweeps).
    """

    best: GibbsState
    best_log_joint: float
    best_score: float
    best_chain: int
    best_sweep: int
    traces: Array
    traces_marginal: Array
    n_features: Array


def run_chains(
    data: GibbsData,
    priors: GibbsPriors,
    *,
    n_sweeps: int,
    n_chains: int,
    rng: np.random.Generator,
    progress: bool = True,
    select: str = "marginal",
    anneal: int | None = None,
) -> ChainResult:
    """Run `n_chains` independent chains of `n_sweeps` sweeps; keep the best sample.

    Chain c uses the stream `rng.spawn(n_chains)[c]` and starts from `init_state`.
    The kept sample maximises `select`: "marginal" (default) = `log_marginal`, the
    joint with f integrated out, or "joint" = `log_joint`. The default deviates from
    "highest joint": log N(f; 0, K) carries −½ log det K per active f[k,r], which for
    a near-singular K is a large bonus for every switched-on entry, so the full joint
    ranks samples by how many f's are on rather than by fit. Samples are never
    averaged across chains (feature labels differ between chains).

    Annealing (not in the paper): during the first `anneal` sweeps (default
    n_sweeps // 4) the sweep uses the inflated noise σ²[r]·T_s[r] with
    T_s[r] = T0[r]^((anneal − s)/anneal), T0[r] = max(1, mean(Y[r]²)/σ²[r]): it
    starts where noise and signal are of one size and falls geometrically to the
    model's σ². At high signal-to-noise ratios a cold chain locks into a "rotated"
    solution (features on every row whose weights span the true ones) that Gibbs
    steps cannot leave; the warm start lets the sparse pattern form first. Only
    samples from the sweeps after annealing (which target the true posterior) can
    be kept; traces are the true log-probabilities at every sweep. `anneal=0`
    switches it off.
    """
    data, priors = check_data(data), check_priors(priors)
    _check_rng(rng, "run_chains")
    check_integer("run_chains: n_sweeps", n_sweeps, 1)
    check_integer("run_chains: n_chains", n_chains, 1)
    if select not in ("marginal", "joint"):
        raise ValueError(
            f"run_chains: select must be 'marginal' or 'joint', got {select}"
        )
    anneal = n_sweeps // 4 if anneal is None else anneal
    check_integer("run_chains: anneal", anneal, 0)
    if anneal >= n_sweeps:
        raise ValueError(f"run_chains: anneal must be in [0, n_sweeps), got {anneal}")
    cache = prepare(data)
    alg = EigenAlgebra(cache)
    signal = (
        np.mean(data.Y**2, axis=(1, 2)) if data.Y.size else np.zeros(len(cache.noise))
    )
    log_T0 = np.log(np.maximum(1.0, signal / cache.noise))
    hot = [
        EigenAlgebra(
            cache._replace(noise=cache.noise * np.exp(log_T0 * (anneal - s) / anneal))
        )
        for s in range(anneal)
    ]
    traces = np.empty((n_chains, n_sweeps))
    traces_m = np.empty((n_chains, n_sweeps))
    n_features = np.empty((n_chains, n_sweeps), dtype=int)
    best, best_score, where = None, -np.inf, (0, 0)
    bar = tqdm(total=n_chains * n_sweeps, disable=not progress, desc="gibbs")
    for c, chain_rng in enumerate(rng.spawn(n_chains)):
        s0 = init_state(data, priors, rng=chain_rng, cache=cache)
        z, w, ft, mu_w = s0.z, s0.w, to_eigen(s0.f, cache), s0.mu_w
        for s in range(n_sweeps):
            alg_s = hot[s] if s < anneal else alg
            z, w, ft, mu_w = sweep(alg_s, z, w, ft, mu_w, priors, rng=chain_rng)
            traces[c, s] = log_joint_eigen(z, w, ft, mu_w, priors, cache)
            traces_m[c, s] = log_marginal_eigen(z, w, mu_w, priors, cache)
            n_features[c, s] = z.shape[0] - 1
            score = traces_m[c, s] if select == "marginal" else traces[c, s]
            if s >= anneal and score > best_score:
                best, best_score, where = (z, w, ft, mu_w), score, (c, s)
            bar.update()
            bar.set_postfix(K=n_features[c, s], lp=f"{traces[c, s]:.4g}")
    bar.close()
    z, w, ft, mu_w = best
    return ChainResult(
        best=GibbsState(z, w, from_eigen(ft, cache), mu_w),
        best_log_joint=float(traces[where]),
        best_score=float(best_score),
        best_chain=where[0],
        best_sweep=where[1],
        traces=traces,
        traces_marginal=traces_m,
        n_features=n_features,
    )
