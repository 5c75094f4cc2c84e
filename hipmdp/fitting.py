"""Batch inference: from several instances' transitions to a fitted HiP-MDP.

Symbols: `b` training instance (B of them), `a` action (A), `d` state dimension (D),
`r = a·D + d` one (action, dimension) row, `m` support points `S*`, `k` latent
feature (feature 0 = mean dynamics), `Y[r,b] = Δ_b(S*)` smoothed changes.

Pipeline (DESIGN §2):

1. hyperparameters of every `(a, d)` GP by maximum marginal likelihood on a
   reproducible subsample (`hipmdp.gp.fit_hyper_set`);
2. support states S* by greedy maximum reconstruction error (`hipmdp.support`);
3. per-instance GP smoothing: for each b and a, `Δ_b(S*) = k(S*, S_ab) (K_ab +
   σ² I)⁻¹ Δ_b(S_ab)` on (a subsample of) instance b's action-a transitions;
4. blocked Gibbs sampling of z, w, f, μ_w (`hipmdp.gibbs.run_chains`), best sample;
5. the returned weights are the conditional posterior means E[w_b | z, f, μ_w, Y], and
   the prior mean for a new instance is E[μ_w | those weights].
"""

from __future__ import annotations

import numbers
from dataclasses import asdict, dataclass

import numpy as np
from tqdm.auto import tqdm

from hipmdp.data import Transitions
from hipmdp.filter import prior_belief, update_belief
from hipmdp.gibbs import GibbsData, GibbsPriors, run_chains
from hipmdp.gp import HyperSet, condition, fit_hyper_set, subsample
from hipmdp.kernels import se_kernel
from hipmdp.model import HipMDP
from hipmdp.support import select_support

Array = np.ndarray


@dataclass(frozen=True)
class FitConfig:
    """Settings of `fit`.

    | name         | meaning                                        | default | range |
    |--------------|------------------------------------------------|---------|-------|
    | n_support    | m, number of support points S*                 | 750     | >= 1  |
    | n_sweeps     | Gibbs sweeps per chain                         | 250     | >= 1  |
    | n_chains     | independent chains; the best sample is kept    | 2       | >= 1  |
    | alpha        | IBP concentration α                            | 2.0     | > 0   |
    | sigma_w      | σ_w, w[k,b] ~ N(μ_w[k], σ_w²)                  | 4.0     | > 0   |
    | sigma_w0     | σ_w0, μ_w[k] ~ N(0, σ_w0²)                     | 4.0     | > 0   |
    | n_w          | N_w importance draws of a new feature's w      | 1000    | >= 1  |
    | n_hyper      | transitions per action, hyperparameter fit     | 1000    | >= 2  |
    | n_candidates | candidate states for the support selection     | 3000    | >= m  |
    | n_smooth     | transitions per (instance, action), smoothing  | 1000    | >= 1  |
    | progress     | show progress bars                             | True    |       |

    The paper's cartpole run: n_support=750, n_sweeps=250, alpha=2, sigma_w=4.
    """

    n_support: int = 750
    n_sweeps: int = 250
    n_chains: int = 2
    alpha: float = 2.0
    sigma_w: float = 4.0
    sigma_w0: float = 4.0
    n_w: int = 1000
    n_hyper: int = 1000
    n_candidates: int = 3000
    n_smooth: int = 1000
    progress: bool = True

    def __post_init__(self) -> None:
        minimum = {
            "n_support": 1,
            "n_sweeps": 1,
            "n_chains": 1,
            "n_w": 1,
            "n_hyper": 2,
            "n_candidates": 1,
            "n_smooth": 1,
        }
        for name, low in minimum.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < low:
                raise ValueError(
                    f"FitConfig.{name}: expected an integer >= {low}, got {v!r}"
                )
        for name in ("alpha", "sigma_w", "sigma_w0"):
            v = getattr(self, name)
            if (
                isinstance(v, bool)
                or not isinstance(v, numbers.Real)
                or not (np.isfinite(v) and v > 0)
            ):
                raise ValueError(
                    f"FitConfig.{name}: expected a finite number > 0, got {v!r}"
                )
        if self.n_candidates < self.n_support:
            raise ValueError(
                f"FitConfig.n_candidates: expected >= n_support={self.n_support}, "
                f"got {self.n_candidates}"
            )
        if not isinstance(self.progress, bool):
            raise ValueError(
                f"FitConfig.progress: expected a bool, got {self.progress!r}"
            )


def check_batch(data: Transitions, config: FitConfig) -> None:
    """Raise ValueError unless `data` can be fitted: a Transitions with at least two
    instances, every action 0..A-1 observed in every instance, and enough distinct
    states for the support points. (Shapes and finiteness are checked by Transitions
    itself and again here, in case arrays were modified in place.)"""
    if not isinstance(data, Transitions):
        raise ValueError(
            f"data: expected hipmdp.Transitions, got {type(data).__name__}"
        )
    if not (np.all(np.isfinite(data.states)) and np.all(np.isfinite(data.next_states))):
        raise ValueError("data: expected finite states and next_states")
    ids = data.instance_ids
    if len(ids) < 2:
        raise ValueError(
            f"data: expected transitions from >= 2 instances, got {len(ids)}"
        )
    for a in range(data.n_actions):
        seen = np.unique(data.instances[data.actions == a])
        if len(seen) == 0:
            raise ValueError(f"data: action {a} has no transitions")
        if len(seen) < len(ids):
            missing = np.setdiff1d(ids, seen).tolist()
            raise ValueError(
                f"data: action {a} has no transitions in instances {missing}"
            )
    n_distinct = len(np.unique(data.states, axis=0))
    if config.n_support > n_distinct:
        raise ValueError(
            f"FitConfig.n_support: expected at most {n_distinct} (distinct states in "
            f"data), got {config.n_support}"
        )


def smooth_onto_support(
    data: Transitions,
    support: Array,
    hyper: HyperSet,
    *,
    n_smooth: int,
    rng: np.random.Generator,
    progress: bool = False,
) -> Array:
    """Y[a,d,b] = Δ_b(S*) by GP regression on instance b's action-a transitions.

        E[Δ_b(s*)] = k_ad(s*, S_ab) (K_ab + σ²[a,d] I)⁻¹ Δ_b,d(S_ab)

    At most `n_smooth` transitions per (b, a) are used (a uniform subsample from
    `rng`). support: S*, (m, D). Returns Y with shape (A, D, B, m).
    """
    A, D = hyper.signal_var.shape
    ids = data.instance_ids
    deltas = data.deltas
    Y = np.empty((A, D, len(ids), len(support)))
    cells = [(bi, b, a) for bi, b in enumerate(ids) for a in range(A)]
    for bi, b, a in tqdm(cells, desc="smoothing", disable=not progress):
        idx = np.flatnonzero((data.instances == b) & (data.actions == a))
        idx = idx[subsample(len(idx), n_smooth, rng=rng)]
        for d in range(D):
            post = condition(data.states[idx], deltas[idx, d], hyper.get(a, d))
            Y[a, d, bi] = post.predict_mean(support)
    return Y


def posterior_weights(
    Y: Array, f: Array, z: Array, noise: Array, mu_w: Array, sigma_w: float
) -> Array:
    """E[w_b | z, f, μ_w, Y] for every instance (DESIGN errata form).

        cov = (Fᵀ Σ⁻¹ F + I/σ_w²)⁻¹,  E[w_b] = cov (μ_w/σ_w² + Fᵀ Σ⁻¹ (Y_b - f_1))

    with rows of F over every (r, support point). Y: (R, B, m); f: (K, R, m);
    z: bool (K, R); noise: (R,); mu_w: (K,). Returns (K, B) with row 0 = 1.
    """
    K, R, m = f.shape
    B = Y.shape[1]
    W = np.ones((K, B))
    F = np.transpose(f[1:] * z[1:, :, None], (2, 1, 0))  # (m, R, K - 1)
    noise_rows = np.broadcast_to(noise, (m, R))
    prior = prior_belief(mu_w[1:], sigma_w)
    for b in range(B):
        innovation = (Y[:, b] - f[0]).T  # (m, R)
        W[1:, b] = update_belief(prior, F, innovation, noise_rows).mean
    return W


def fit(data: Transitions, config: FitConfig, *, rng: np.random.Generator) -> HipMDP:
    """Fit a HiP-MDP to batch transitions from several instances (pipeline above).

    data: transitions of B >= 2 training instances, every action seen in each.
    Same data, config and generator state → identical model.
    """
    if not isinstance(config, FitConfig):
        raise ValueError(f"config: expected FitConfig, got {type(config).__name__}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(
            f"rng: expected numpy.random.Generator, got {type(rng).__name__}"
        )
    check_batch(data, config)
    rng_hyper, rng_support, rng_smooth, rng_gibbs = rng.spawn(4)
    A, D = data.n_actions, data.state_dim
    deltas = data.deltas
    hyper = fit_hyper_set(
        data.states,
        data.actions,
        deltas,
        data.instances,
        A,
        n_subsample=config.n_hyper,
        rng=rng_hyper,
    )
    support = select_support(
        data.states,
        hyper,
        config.n_support,
        n_candidates=config.n_candidates,
        rng=rng_support,
        progress=config.progress,
    ).points
    Y = smooth_onto_support(
        data,
        support,
        hyper,
        n_smooth=config.n_smooth,
        rng=rng_smooth,
        progress=config.progress,
    )
    m, B = len(support), len(data.instance_ids)
    Kss = np.stack(
        [
            se_kernel(
                support, support, hyper.lengthscales[a, d], hyper.signal_var[a, d]
            )
            for a in range(A)
            for d in range(D)
        ]
    )
    noise = hyper.noise_var.reshape(A * D)
    gdata = GibbsData(Y=Y.reshape(A * D, B, m), K=Kss, noise=noise)
    priors = GibbsPriors(config.alpha, config.sigma_w, config.sigma_w0, config.n_w)
    result = run_chains(
        gdata,
        priors,
        n_sweeps=config.n_sweeps,
        n_chains=config.n_chains,
        rng=rng_gibbs,
        progress=config.progress,
    )
    best = result.best
    keep = np.concatenate([[True], best.z[1:].any(1)])  # drop features no row uses
    z, f, mu_w = best.z[keep], best.f[keep] * best.z[keep][..., None], best.mu_w[keep]
    weights = posterior_weights(gdata.Y, f, z, noise, mu_w, config.sigma_w)
    # The prior mean of an unseen instance's weights: E[μ_w | w] in the limit of a
    # flat hyperprior, i.e. the mean training weight. Deviation: the model's own
    # E[μ_w | w] = var Σ_b w[k,b] / σ_w², var = (1/σ_w0² + B/σ_w²)⁻¹, shrinks the
    # mean toward 0 by B/(B + σ_w²/σ_w0²) (8/9 at σ_w0 = σ_w = 4, B = 8), but a
    # weight's origin is arbitrary. On the acrobot, whose weights reach ±5 on large
    # basis functions, the shrunk prior-mean model was 12× worse than the average GP
    # on the angular velocities; the mean training weight beats the average GP
    # before any data. σ_w0 still acts as the μ_w hyperprior inside the sampler,
    # where a vague value (100) made the sampler split features.
    prior_mean = weights.mean(1)
    prior_mean[0] = 1.0
    K = len(z)
    info = {
        "config": asdict(config),
        "best_log_joint": float(result.best_log_joint),
        "n_transitions": int(len(data)),
        "angle_dims": list(data.angle_dims),
    }
    return HipMDP(
        support=support,
        hyper=hyper,
        z=z.reshape(K, A, D),
        f=f.reshape(K, A, D, m),
        weights=weights,
        mu_w=prior_mean,
        sigma_w=float(config.sigma_w),
        instance_ids=data.instance_ids,
        info=info,
    )


__all__ = [
    "FitConfig",
    "check_batch",
    "fit",
    "posterior_weights",
    "smooth_onto_support",
]
