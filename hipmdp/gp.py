"""Gaussian-process regression: marginal likelihood, hyperparameter fitting, prediction.

Symbols: `X` inputs (states), shape (n, D); `y` targets (one state dimension of Δs),
shape (n,); `ℓ` length scales (D,), `σ_f²` signal variance, `σ_n²` noise variance;
`a` action, `d` state dimension, `b` instance. The prior mean is zero, as for every
basis function `f[k,a,d] ~ GP(0, k_ad)` of the model.

Hyperparameters of the `(a, d)` GP are shared by all instances: the marginal likelihood
maximised is the sum over instances `b` of independent GP marginal likelihoods, each on
instance `b`'s own transitions. Pooling instances into one GP would count the
between-instance variation as noise, which is exactly what the latent parameters are
meant to explain.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import linalg, optimize
from tqdm.auto import tqdm

from hipmdp.data import check_integer, check_rng, read_only
from hipmdp.kernels import check_periodic, se_kernel, se_kernel_grad

Array = np.ndarray

# Bounds of the hyperparameter search, relative to the data's scale (see `_bounds`).
_LENGTH_RANGE = 1e2  # ℓ_j within [std_j / 100, std_j * 100]
_SIGNAL_RANGE = (1e-4, 1e2)  # σ_f² within this factor of mean(y²)
_NOISE_RANGE = (1e-8, 1.0)  # σ_n² within this factor of mean(y²)
#: The floor of the targets' scale mean(y²) that the bounds are relative to: targets
#: whose mean square is below it get bounds that are not scaled to them (a
#: pendulum's changes scaled by 1e-10, mean square ~1e-20, fitted a one-feature
#: HiP-MDP with a held-out MSE about the changes' variance; unscaled, 3e-6 of it).
MIN_SCALE = 1e-12


class GPHyper(NamedTuple):
    """GP hyperparameters: lengthscales ℓ (D,), signal_var σ_f², noise_var σ_n²;
    periodic: the input dimensions that are angles (`hipmdp.kernels`), fixed, not
    fitted."""

    lengthscales: Array
    signal_var: float
    noise_var: float
    periodic: tuple[int, ...] = ()

    def to_theta(self) -> Array:
        """θ = (log ℓ, log σ_f², log σ_n²), shape (D + 2,)."""
        return np.concatenate(
            [
                np.log(self.lengthscales),
                [np.log(self.signal_var), np.log(self.noise_var)],
            ]
        )

    @classmethod
    def from_theta(cls, theta: Array, periodic: tuple[int, ...] = ()) -> GPHyper:
        """Inverse of `to_theta` (θ does not hold `periodic`)."""
        theta = np.asarray(theta, dtype=float)
        return cls(
            np.exp(theta[:-2]),
            float(np.exp(theta[-2])),
            float(np.exp(theta[-1])),
            tuple(periodic),
        )


@dataclass(frozen=True)
class HyperSet:
    """Hyperparameters of every `(a, d)` GP.

    lengthscales: ℓ[a,d], shape (A, D, D); signal_var: σ_f²[a,d], shape (A, D);
    noise_var: σ²[a,d], shape (A, D); periodic: the state dimensions every kernel
    treats as angles (`hipmdp.kernels`), default none.
    """

    lengthscales: Array
    signal_var: Array
    noise_var: Array
    periodic: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        ell = np.asarray(self.lengthscales, dtype=float)
        if ell.ndim != 3 or ell.shape[1] != ell.shape[2]:
            raise ValueError(
                f"HyperSet.lengthscales: expected shape (A, D, D), got {ell.shape}"
            )
        for name in ("lengthscales", "signal_var", "noise_var"):
            value = np.asarray(getattr(self, name), dtype=float)
            if name != "lengthscales" and value.shape != ell.shape[:2]:
                raise ValueError(
                    f"HyperSet.{name}: expected shape {ell.shape[:2]} (A, D), "
                    f"got {value.shape}"
                )
            if not np.all(np.isfinite(value) & (value > 0)):
                raise ValueError(f"HyperSet.{name}: expected finite values > 0")
            object.__setattr__(self, name, read_only(value, float))
        dim = ell.shape[-1]
        object.__setattr__(self, "periodic", check_periodic(self.periodic, dim))

    def get(self, a: int, d: int) -> GPHyper:
        """The hyperparameters of action `a`, state dimension `d`."""
        return GPHyper(
            self.lengthscales[a, d],
            float(self.signal_var[a, d]),
            float(self.noise_var[a, d]),
            self.periodic,
        )


class NLML(NamedTuple):
    """-log marginal likelihood `value` and its gradient `grad` in θ (D + 2,)."""

    value: float
    grad: Array


def neg_log_marginal_likelihood(
    theta: Array, groups: list[tuple[Array, Array]], periodic: tuple[int, ...] = ()
) -> NLML:
    """Negative log marginal likelihood of independent zero-mean GPs sharing θ.

    For each group (X_b (n_b, D), y_b (n_b,)), with C = K + σ_n² I and α = C⁻¹ y:

        -log p(y_b | X_b, θ) = ½ yᵀα + ½ log|C| + ½ n_b log 2π
        ∂/∂θ_i = -½ tr((α αᵀ - C⁻¹) ∂C/∂θ_i)

    with ∂C/∂log σ_n² = σ_n² I. The value and gradient are summed over groups;
    `periodic` are the angle dimensions of X (`hipmdp.kernels`).
    """
    hyper = GPHyper.from_theta(theta, periodic)
    value = 0.0
    grad = np.zeros(len(theta))
    for X, y in groups:
        n = len(y)
        if n == 0:
            continue
        kg = se_kernel_grad(X, hyper.lengthscales, hyper.signal_var, hyper.periodic)
        C = kg.K + hyper.noise_var * np.eye(n)
        L = linalg.cholesky(C, lower=True)
        alpha = linalg.cho_solve((L, True), y)
        value += (
            0.5 * y @ alpha + np.log(np.diag(L)).sum() + 0.5 * n * np.log(2 * np.pi)
        )
        Cinv = linalg.cho_solve((L, True), np.eye(n))
        Q = np.outer(alpha, alpha) - Cinv
        # tr(Q dK) = Σ_ij Q_ij dK_ij since both are symmetric.
        grad[:-1] -= 0.5 * np.einsum("ij,kij->k", Q, kg.dK)
        grad[-1] -= 0.5 * hyper.noise_var * np.trace(Q)
    return NLML(float(value), grad)


def _bounds(
    groups: list[tuple[Array, Array]],
) -> tuple[Array, list[tuple[float, float]]]:
    """Starting point θ₀ and box bounds, both scaled to the data."""
    X = np.concatenate([g[0] for g in groups])
    y = np.concatenate([g[1] for g in groups])
    std = X.std(0)
    std = np.where(std > 0, std, 1.0)
    scale = max(float(np.mean(y * y)), MIN_SCALE)
    theta0 = np.concatenate([np.log(std), [np.log(scale), np.log(1e-2 * scale)]])
    lr = np.log(_LENGTH_RANGE)
    bounds = [(float(np.log(s) - lr), float(np.log(s) + lr)) for s in std]
    bounds.append(tuple(float(np.log(scale * r)) for r in _SIGNAL_RANGE))
    bounds.append(tuple(float(np.log(scale * r)) for r in _NOISE_RANGE))
    return theta0, bounds


def fit_hyperparameters(
    groups: list[tuple[Array, Array]], periodic: tuple[int, ...] = ()
) -> GPHyper:
    """Maximise the summed marginal likelihood over θ (L-BFGS-B, analytic gradient).

    groups: list of (X_b (n_b, D), y_b (n_b,)), one per instance; periodic: the angle
    dimensions of X (`hipmdp.kernels`). Deterministic given the data. The search
    starts at ℓ = std(X), σ_f² = mean(y²), σ_n² = mean(y²)/100 and is boxed
    relative to those scales.
    """
    if not groups or sum(len(g[1]) for g in groups) < 2:
        raise ValueError("groups: expected at least 2 data points in total")
    theta0, bounds = _bounds(groups)
    failed = []  # the θ at which the kernel matrix was not positive definite

    def fun(theta: Array) -> tuple[float, Array]:
        try:
            res = neg_log_marginal_likelihood(theta, groups, periodic)
        except linalg.LinAlgError:
            failed.append(theta)
            return 1e300, np.zeros_like(theta)
        return res.value, res.grad

    result = optimize.minimize(fun, theta0, jac=True, method="L-BFGS-B", bounds=bounds)
    if failed and np.array_equal(result.x, theta0):
        warnings.warn(
            "fit_hyperparameters: the search stopped at its starting point, where "
            "its first steps met kernel matrices that were not positive definite "
            f"({len(failed)} of its evaluations): the hyperparameters returned "
            "are the start, not an optimum. Check the inputs for near-duplicates "
            "and the targets' scale.",
            RuntimeWarning,
            stacklevel=2,
        )
    return GPHyper.from_theta(result.x, periodic)


class GPPosterior(NamedTuple):
    """A GP conditioned on data: X (n, D), alpha = (K + σ_n² I)⁻¹ y (n,), the Cholesky
    factor L (n, n) of K + σ_n² I, and its hyperparameters."""

    X: Array
    alpha: Array
    L: Array
    hyper: GPHyper

    def predict_mean(self, Xs: Array) -> Array:
        """Predictive mean K(Xs, X) α at Xs (n_s, D), shape (n_s,)."""
        h = self.hyper
        return se_kernel(Xs, self.X, h.lengthscales, h.signal_var, h.periodic) @ (
            self.alpha
        )

    def predict(self, Xs: Array, include_noise: bool = False) -> tuple[Array, Array]:
        """Predictive mean and variance at Xs (n_s, D).

        mean = K(Xs, X) α
        var  = σ_f² - diag(K(Xs, X) (K + σ_n² I)⁻¹ K(X, Xs))  [+ σ_n²]
        """
        h = self.hyper
        Ks = se_kernel(Xs, self.X, h.lengthscales, h.signal_var, h.periodic)
        mean = Ks @ self.alpha
        V = linalg.solve_triangular(self.L, Ks.T, lower=True)
        var = np.maximum(h.signal_var - (V * V).sum(0), 0.0)
        if include_noise:
            var = var + h.noise_var
        return mean, var


def condition(X: Array, y: Array, hyper: GPHyper) -> GPPosterior:
    """Condition the zero-mean GP on (X (n, D), y (n,))."""
    given = np.asarray(X, dtype=float)
    X = np.atleast_2d(given)
    y = np.asarray(y, dtype=float)
    if y.ndim != 1:  # (n, 1) gave (n_s, 1) means, broadcast silently downstream
        raise ValueError(f"y: expected shape (n,), got {y.shape}")
    if X.shape[0] != y.shape[0]:
        one_point = ""
        if given.ndim == 1 and given.size == y.size > 1:
            one_point = (
                f" (a 1-D X is one point of dimension {given.size}; for "
                f"{given.size} points of one dimension pass X[:, None])"
            )
        raise ValueError(
            f"X and y: expected the same length, got {len(X)} and {len(y)}" + one_point
        )
    for name, value in (("X", X), ("y", y)):
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{name}: expected finite values")
    try:
        noise = float(hyper.noise_var)
    except (TypeError, ValueError):
        noise = np.nan
    if not (np.isfinite(noise) and noise > 0):
        raise ValueError(  # σ_n² = -5 failed in the Cholesky factorisation
            f"hyper.noise_var: expected a finite number > 0, got {hyper.noise_var!r}"
        )
    K = se_kernel(X, X, hyper.lengthscales, hyper.signal_var, hyper.periodic)
    L = linalg.cholesky(K + hyper.noise_var * np.eye(len(y)), lower=True)
    alpha = linalg.cho_solve((L, True), y)
    return GPPosterior(X, alpha, L, hyper)


def subsample(n: int, size: int, *, rng: np.random.Generator) -> Array:
    """Sorted indices of `min(n, size)` distinct items drawn uniformly from range(n)."""
    if n <= size:
        return np.arange(n)
    return np.sort(rng.choice(n, size=size, replace=False))


def fit_hyper_set(
    states: Array,
    actions: Array,
    deltas: Array,
    instances: Array,
    n_actions: int,
    *,
    n_subsample: int,
    rng: np.random.Generator,
    periodic: tuple[int, ...] = (),
    progress: bool = False,
) -> HyperSet:
    """Fit the hyperparameters of every `(a, d)` GP on a reproducible subsample.

    states: (N, D); actions: (N,); deltas: Δs, (N, D); instances: (N,).
    For each action a, at most `max(2, n_subsample // B)` transitions per instance
    are drawn (without replacement, from `rng`), and for each d the summed
    per-instance marginal likelihood is maximised (`fit_hyperparameters`);
    periodic: the angle dimensions of the states (`hipmdp.kernels`); progress: a
    bar over the `(a, d)` fits. Returns a HyperSet.
    """
    states, deltas = np.asarray(states, float), np.asarray(deltas, float)
    actions, instances = np.asarray(actions), np.asarray(instances)
    if states.ndim != 2 or not len(states):
        raise ValueError(f"states: expected shape (N >= 1, D), got {states.shape}")
    N, D = states.shape
    for name, value, shape in (
        ("deltas", deltas, (N, D)), ("actions", actions, (N,)),
        ("instances", instances, (N,)),
    ):  # fmt: skip
        if value.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {value.shape}")
    for name, value in (("states", states), ("deltas", deltas)):
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{name}: expected finite values")
    check_integer("n_actions", n_actions, 1)  # 0 returned an empty HyperSet
    check_integer("n_subsample", n_subsample, 1)  # <= 0 used 2 per instance
    if not np.issubdtype(actions.dtype, np.integer) or np.any(
        (actions < 0) | (actions >= n_actions)
    ):
        raise ValueError(f"actions: expected integers in [0, {n_actions})")
    check_rng(rng)
    counts = np.bincount(actions, minlength=n_actions)
    if np.any(counts < 2):
        a = int(np.argmax(counts < 2))
        raise ValueError(
            f"actions: expected at least 2 transitions of each action, got "
            f"{counts[a]} of action {a}"
        )
    ids = np.unique(instances)
    per_instance = max(2, n_subsample // len(ids))
    ell = np.empty((n_actions, D, D))
    sf2 = np.empty((n_actions, D))
    sn2 = np.empty((n_actions, D))
    with tqdm(total=n_actions * D, desc="hyperparameters", disable=not progress) as bar:
        for a in range(n_actions):
            rows = []
            for b in ids:
                idx = np.flatnonzero((actions == a) & (instances == b))
                rows.append(idx[subsample(len(idx), per_instance, rng=rng)])
            for d in range(D):
                groups = [(states[r], deltas[r, d]) for r in rows if len(r)]
                h = fit_hyperparameters(groups, periodic)
                ell[a, d], sf2[a, d], sn2[a, d] = h[:3]
                bar.update()
    return HyperSet(ell, sf2, sn2, periodic)
