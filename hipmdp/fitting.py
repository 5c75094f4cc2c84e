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
   the prior mean for a new instance is the mean training weight: E[μ_w | those
   weights] with a flat hyperprior (the model's own, σ_w0, would shrink it toward 0;
   see the comment in `fit`);
6. the model-error terms of the predictive variance per `(a, d)` (`model_error`),
   on a reproducible subsample of the batch.
"""

from __future__ import annotations

import numbers
import warnings
from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy import optimize
from tqdm.auto import tqdm

from hipmdp.data import Transitions, check_integer, check_rng
from hipmdp.filter import prior_belief, update_belief
from hipmdp.gibbs import GibbsData, GibbsPriors, run_chains
from hipmdp.gp import MIN_SCALE, HyperSet, condition, fit_hyper_set, subsample
from hipmdp.kernels import se_kernel
from hipmdp.model import FILTER_WEIGHTS, HipMDP
from hipmdp.support import select_support

Array = np.ndarray


#: FitConfig.new_features: the paper's new-feature step, or its multiple-try form.
NEW_FEATURES = ("paper", "multiple_try")

#: The priors' documented ranges (FitConfig), ends included but α's 0.
PRIOR_RANGES = {
    "alpha": (0.0, 100.0),
    "sigma_w": (1e-3, 1e4),
    "sigma_w0": (1e-3, 1e4),
}


@dataclass(frozen=True)
class FitConfig:
    """Settings of `fit`.

    | name           | meaning                             | default    | range       |
    |----------------|-------------------------------------|------------|-------------|
    | n_support      | m, number of support points S*      | 750        | >= 1        |
    | n_sweeps       | Gibbs sweeps per chain              | 250        | >= 1        |
    | n_chains       | chains; the best sample is kept     | 2          | >= 1        |
    | alpha          | IBP concentration α                 | 2.0        | (0, 100]    |
    | sigma_w        | σ_w, w[k,b] ~ N(μ_w[k], σ_w²)       | 4.0        | [1e-3, 1e4] |
    | sigma_w0       | σ_w0, μ_w[k] ~ N(0, σ_w0²)          | 4.0        | [1e-3, 1e4] |
    | n_w            | N_w draws of a new feature's w      | 1000       | >= 1        |
    | new_features   | the new-feature step                | paper      | below       |
    | n_hyper        | transitions/action, hyperparameters | 1000       | >= 2        |
    | n_candidates   | candidates for the support points   | 3000       | >= m        |
    | n_smooth       | transitions/(instance, action)      | 1000       | >= 1        |
    | n_residual     | transitions/action, model error     | 2000       | >= 1        |
    | periodic       | kernels periodic in angle_dims      | False      |             |
    | filter_weights | the filter's model-error weights    | prior_mean | below       |
    | progress       | show progress bars                  | True       |             |

    `periodic`: every kernel measures an angle difference by its chord
    `2 sin(Δθ / 2)` (`hipmdp.kernels`), so states either side of `θ = ±π` are
    neighbours; without it they are `2π` apart.

    `new_features`: "paper": the paper's Metropolis-Hastings step on a row's
    singleton features, exact as N_w → ∞ only; "multiple_try": the same step with
    the current singletons' own weights as one of their N_w draws, exact for every
    N_w at the same cost (`hipmdp.gibbs_sweep`; a test measures both). It changes
    the sampler's draws, so a fit with it is not the default's.

    `filter_weights`: the weights at which `HipMDP.update` takes the factor
    (1 + Σ_k z w_k²) of its model-error variance τ² (`hipmdp.model`, "Filtering
    with the model error"). "prior_mean": the prior mean weights μ_w. "training":
    the squared weights averaged over the training instances, as `model_error`
    calibrated c (up to its weighting by each instance's transitions); that keeps
    the weights' spread (a factor typically 17-36× larger on the acrobot), but
    measured it gains nothing consistent (README, "The filter's
    model-error weights"). It changes only the filter, not the fit.

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
    n_residual: int = 2000
    periodic: bool = False
    filter_weights: str = "prior_mean"
    progress: bool = True
    new_features: str = "paper"

    def __post_init__(self) -> None:
        minimum = {
            "n_support": 1,
            "n_sweeps": 1,
            "n_chains": 1,
            "n_w": 1,
            "n_hyper": 2,
            "n_candidates": 1,
            "n_smooth": 1,
            "n_residual": 1,
        }
        for name, low in minimum.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < low:
                raise ValueError(
                    f"FitConfig.{name}: expected an integer >= {low}, got {v!r}"
                )
            object.__setattr__(self, name, int(v))  # e.g. np.int64: JSON needs int
        # beyond these the sampler fails deep inside (σ_w0 = 1e10: an indefinite
        # matrix; α = 1e300, σ_w = 1e160: overflow) after the costly stages
        for name, (low, high) in PRIOR_RANGES.items():
            v = getattr(self, name)
            if (
                isinstance(v, bool)
                or not isinstance(v, numbers.Real)
                or not (np.isfinite(v) and v > 0)
            ):
                raise ValueError(
                    f"FitConfig.{name}: expected a finite number > 0, got {v!r}"
                )
            if not low <= v <= high:  # (v > 0 is checked above)
                opening = "(" if low == 0 else "["
                raise ValueError(
                    f"FitConfig.{name}: expected a value in {opening}{low:g}, "
                    f"{high:g}], got {v!r}"
                )
            object.__setattr__(self, name, float(v))
        if self.n_candidates < self.n_support:
            raise ValueError(
                f"FitConfig.n_candidates: expected >= n_support={self.n_support}, "
                f"got {self.n_candidates}"
            )
        if self.filter_weights not in FILTER_WEIGHTS:
            raise ValueError(
                f"FitConfig.filter_weights: expected one of {FILTER_WEIGHTS}, got "
                f"{self.filter_weights!r}"
            )
        object.__setattr__(self, "filter_weights", str(self.filter_weights))
        if self.new_features not in NEW_FEATURES:
            raise ValueError(
                f"FitConfig.new_features: expected one of {NEW_FEATURES}, got "
                f"{self.new_features!r}"
            )
        object.__setattr__(self, "new_features", str(self.new_features))
        for name in ("periodic", "progress"):
            v = getattr(self, name)
            if not isinstance(v, bool | np.bool_):
                raise ValueError(f"FitConfig.{name}: expected a bool, got {v!r}")
            object.__setattr__(self, name, bool(v))

    def periodic_dims(self, data: Transitions) -> tuple[int, ...]:
        """The dimensions every kernel treats as angles: `data.angle_dims` if
        `periodic`, else none. Baselines meant to compare with this fit take it
        (`hipmdp.baselines.fit_gp_baseline(..., periodic=)`)."""
        return tuple(data.angle_dims) if self.periodic else ()


#: The largest data magnitude :func:`fit` accepts: the fourth root of float64's
#: largest value, so that products of up to four data values stay finite.
#: Measured on a synthetic batch: data at 1e77 fit without a floating-point
#: warning, data at 1e85 fail deep in the sampler ("Probabilities contain NaN").
MAX_MAGNITUDE = float(np.finfo(float).max) ** 0.25


def check_batch(data: Transitions, config: FitConfig) -> None:
    """Raise ValueError unless `data` can be fitted: a Transitions with at least two
    instances, every action 0..A-1 observed in every instance, magnitudes up to
    MAX_MAGNITUDE, angle_dims declared if `config.periodic`, and enough distinct
    states for the support points. (Shapes and
    finiteness are checked by Transitions itself and again here, in case arrays
    were modified in place.) Warns (RuntimeWarning) if an action's changes in a
    dimension are nonzero but of mean square below `hipmdp.gp.MIN_SCALE`."""
    if not isinstance(data, Transitions):
        raise ValueError(
            f"data: expected hipmdp.Transitions, got {type(data).__name__}"
        )
    if not (np.all(np.isfinite(data.states)) and np.all(np.isfinite(data.next_states))):
        raise ValueError("data: expected finite states and next_states")
    for name in ("states", "next_states"):
        largest = float(np.max(np.abs(getattr(data, name)), initial=0.0))
        if largest > MAX_MAGNITUDE:
            raise ValueError(
                f"data.{name}: expected magnitudes <= {MAX_MAGNITUDE:.3g}, got "
                f"{largest:.3g}; the fit multiplies data values and would overflow "
                "float64; rescale the states (e.g. to SI units)"
            )
    if config.periodic and not data.angle_dims:
        raise ValueError(
            "FitConfig.periodic: the data declare no angle_dims, so no kernel "
            "would be periodic; set Transitions(..., angle_dims=...) or periodic=False"
        )
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
    deltas = data.deltas
    for a in range(data.n_actions):
        ms = np.mean(deltas[data.actions == a] ** 2, axis=0)
        small = np.flatnonzero((ms > 0) & (ms < MIN_SCALE))
        if len(small):
            d = int(small[0])
            warnings.warn(
                f"data.deltas: action {a}, dimension {d} has mean squared change "
                f"{ms[d]:.3g}, below {MIN_SCALE:g}, where the GP hyperparameter "
                "search stops scaling its bounds to the data (hipmdp.gp.MIN_SCALE): "
                "the fit will likely be poor; rescale the states (e.g. to SI units)",
                RuntimeWarning,
                stacklevel=3,
            )
            break


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

    Raises:
        ValueError: before any work, if `hyper` is not for `data`'s actions and
            state dimension, `support` is not finite (m, D), `n_smooth` < 1, or
            an (instance, action) has no transitions (its Y would be 0).
    """
    if not isinstance(data, Transitions):
        raise ValueError(f"data: expected Transitions, got {type(data).__name__}")
    A, D = hyper.signal_var.shape
    if (A, D) != (data.n_actions, data.state_dim):
        raise ValueError(
            f"hyper: expected {data.n_actions} actions and state dimension "
            f"{data.state_dim} (the data's), got {A} and {D}"
        )  # an action without hyperparameters was dropped
    support = np.asarray(support, dtype=float)
    if support.ndim != 2 or support.shape[1] != D or not np.all(np.isfinite(support)):
        raise ValueError(
            f"support: expected finite values of shape (m, {D}), got shape "
            f"{support.shape}"
        )
    check_integer("n_smooth", n_smooth, 1)  # 0 gave Y = 0 everywhere
    check_rng(rng)
    ids = data.instance_ids
    for a in range(A):
        missing = np.setdiff1d(ids, data.instances[data.actions == a])
        if len(missing):
            raise ValueError(
                f"data: action {a} has no transitions in instances "
                f"{missing.tolist()} (their Y would be 0)"
            )
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
    f = np.asarray(f, dtype=float)
    if f.ndim != 3:
        raise ValueError(f"f: expected shape (K, R, m), got {np.shape(f)}")
    K, R, m = f.shape
    Y = np.asarray(Y, dtype=float)
    B = Y.shape[1] if Y.ndim == 3 else "B"
    for name, value, shape in (
        ("Y", Y, (R, B, m)),
        ("z", z, (K, R)),
        ("noise", noise, (R,)),
        ("mu_w", mu_w, (K,)),
    ):  # a Y of (R, B, 1) broadcast against f's m support points
        if np.shape(value) != shape:
            raise ValueError(
                f"{name}: expected shape {shape} (f is (K, R, m) = {f.shape}), "
                f"got {np.shape(value)}"
            )
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
    Same data, config and a fresh generator from the same seed → identical
    model. The fit's streams are spawned from ``rng``'s seed sequence
    (``rng.spawn``), not drawn from its state: earlier draws from ``rng`` do not
    change the fit, and a restored ``bit_generator.state`` does not reproduce
    one; but earlier spawns do (an earlier ``fit``, ``run_chains`` or
    ``rng.spawn`` on the same object): a second ``fit`` with the same generator
    is another fit.
    """
    if not isinstance(config, FitConfig):
        raise ValueError(f"config: expected FitConfig, got {type(config).__name__}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(
            f"rng: expected numpy.random.Generator, got {type(rng).__name__}"
        )
    check_batch(data, config)
    # spawn(5)'s first four children are spawn(4)'s: adding a stream changed nothing
    rng_hyper, rng_support, rng_smooth, rng_gibbs, rng_residual = rng.spawn(5)
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
        periodic=config.periodic_dims(data),
        progress=config.progress,
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
                support,
                support,
                hyper.lengthscales[a, d],
                hyper.signal_var[a, d],
                hyper.periodic,
            )
            for a in range(A)
            for d in range(D)
        ]
    )
    noise = hyper.noise_var.reshape(A * D)
    gdata = GibbsData(Y=Y.reshape(A * D, B, m), K=Kss, noise=noise)
    priors = GibbsPriors(
        config.alpha, config.sigma_w, config.sigma_w0, config.n_w,
        multiple_try=config.new_features == "multiple_try",
    )  # fmt: skip
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
        "data_sha256": data.sha256(),  # which data: a check can tie model to data
        "angle_dims": list(data.angle_dims),
        "dt": data.dt,
    }
    model = HipMDP(
        support=support,
        hyper=hyper,
        z=z.reshape(K, A, D),
        f=f.reshape(K, A, D, m),
        weights=weights,
        mu_w=prior_mean,
        sigma_w=float(config.sigma_w),
        instance_ids=data.instance_ids,
        info=info,
        filter_weights=config.filter_weights,
    )
    sub = np.concatenate(
        [
            idx[subsample(len(idx), config.n_residual, rng=rng_residual)]
            for idx in (np.flatnonzero(data.actions == a) for a in range(A))
        ]
    )
    r0, c = model_error(model, data.take(sub))
    return replace(model, residual_var=r0, interp_var_scale=c)


def model_error(model: HipMDP, data: Transitions) -> tuple[Array, Array]:
    """What the fitted model cannot represent, per (a, d), from its training data.

    Each transition of training instance b is predicted with b's fitted weights (no
    weight uncertainty), leaving residuals ``r_i``. Per (a, d), the variance of
    ``r_i`` is modelled as

        var_i = σ²[a,d] + c[a,d] · u_i + r0[a,d],   u_i = v_ad(s_i) Σ_k z w[k,b]²,

    (``u_i`` is the interpolation term of `HipMDP.predict`, so ``c = 1, r0 = 0``
    is the uncalibrated model) and ``c >= 1``, ``r0 >= 0`` maximise the Gaussian
    likelihood of the residuals. The errors are heavy-tailed and larger away from
    the support points, which ``c`` captures and one constant variance cannot.

    The calibration may only add variance (``c >= 1``): these residuals are
    in-sample (the support points and smoothed values come from the same
    transitions), so they understate the error at a new instance's states. Without
    the bound, the cart-pole's near-zero training residuals drove ``c`` to 0 and
    its held-out log-likelihood fell by thousands of nats.

    Returns:
        ``(r0, c)``, each (A, D); an (a, d) without transitions gets ``(0, 1)``.
    """
    A, D = model.n_actions, model.state_dim
    col = {int(b): j for j, b in enumerate(model.instance_ids)}
    unknown = sorted(set(np.unique(data.instances).tolist()) - set(col))
    if unknown:
        raise ValueError(f"data: instances {unknown} are not training instances")
    F, v = model._evaluate(data.states, data.actions, with_var=True)
    w = model.weights[:, [col[int(b)] for b in data.instances]].T  # (n, K)
    r2 = (data.deltas - np.einsum("ndk,nk->nd", F, w)) ** 2
    u = v * np.einsum("nk,knd->nd", w * w, model.z[:, data.actions, :])
    r0, c = np.zeros((A, D)), np.ones((A, D))
    for a in range(A):
        rows = data.actions == a
        if not rows.any():
            continue
        for d in range(D):
            r0[a, d], c[a, d] = _fit_error_terms(
                r2[rows, d], u[rows, d], float(model.hyper.noise_var[a, d])
            )
    return r0, c


#: How much higher (nats) the log-likelihood of another start of
#: `_fit_error_terms` must be to replace the first start's optimum.
ERROR_TERMS_TOLERANCE = 1.0


def _fit_error_terms(r2: Array, u: Array, noise: float) -> tuple[float, float]:
    """argmax over r0 >= 0, c >= 1 of Σ log N(r; 0, noise + c u + r0), by L-BFGS-B
    on (log r0, log c); the bounds keep both finite.

    The likelihood is flat in log r0 wherever r0 is negligible beside the other
    terms, and heavy-tailed residuals put mean(r²), the scale, far above the best
    r0: a single start at the median could step onto that plateau and stop there,
    hundreds of nats short. So L-BFGS-B also starts from r0 at σ² and at 1e-6 of
    the median r², and another start's optimum replaces the first one's only if its
    log-likelihood is higher by more than `ERROR_TERMS_TOLERANCE` (1 nat): where
    the first start did not stall, the others land within the optimiser's
    tolerance of it (on the paper-size acrobot's fits, 0.012 nats at most, on a
    flat direction), and keeping it keeps such fits the same to the bit.
    """
    scale = max(float(np.mean(r2)), noise, 1e-300)

    def nll(theta: Array) -> tuple[float, Array]:
        e0, ec = np.exp(theta)
        var = noise + ec * u + e0 * scale
        g = 0.5 * (1.0 / var - r2 / var**2)  # d nll / d var
        return float(0.5 * np.sum(r2 / var + np.log(var))), np.array(
            [np.sum(g) * e0 * scale, np.sum(g * u) * ec]
        )

    median = float(np.median(r2))
    starts = (  # r0 / scale; the first as before the other two were added
        max(median / scale, 1e-12),
        max(noise / scale, np.exp(-60.0)),
        max(1e-6 * median / scale, np.exp(-60.0)),
    )
    best = None
    for r0 in starts:
        start = [np.log(r0), 0.0]
        res = optimize.minimize(
            nll, start, jac=True, method="L-BFGS-B", bounds=[(-60.0, 5.0), (0.0, 30.0)]
        )
        if best is None or res.fun < best.fun - ERROR_TERMS_TOLERANCE:
            best = res
    e0, ec = np.exp(best.x)
    return float(e0 * scale), float(ec)


__all__ = [
    "FitConfig",
    "check_batch",
    "fit",
    "posterior_weights",
    "model_error",
    "smooth_onto_support",
]
