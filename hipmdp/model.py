"""The fitted IBP-GP HiP-MDP: basis functions, latent weights, online filtering.

Symbols: `k` latent parameter (k = 0 here is the paper's k = 1, the mean dynamics),
`a` action, `d` state dimension, `b` training instance, `m` support points `S*`
(m, D); `z[k,a,d]` on/off flags, `f[k,a,d](S*)` basis values, `w[k,b]` weights,
`σ²[a,d]` noise. The model is

    Δs_d = Σ_k z[k,a,d] w[k,b] f[k,a,d](s) + ε,   ε ~ N(0, σ²[a,d]),

and each basis function is interpolated from its support values with the GP mean

    f[k,a,d](s) = k_ad(s, S*) (K_ad + σ²[a,d] I)⁻¹ f[k,a,d](S*) = k_ad(s, S*) c[k,a,d],

the coefficients `c` being solved once at construction, so evaluating the basis at n
states is a matrix product.

Predictive variance. Between support points a basis function is known only up to
its GP interpolation variance

    v_ad(s) = k_ad(s, s) - k_ad(s, S*) (K_ad + σ²[a,d] I)⁻¹ k_ad(S*, s),

and with independent basis functions the prediction's variance is

    Var[Δs_d] = σ²[a,d] + F Σ_w Fᵀ + v_ad(s) (1 + Σ_k z[k,a,d] (μ_k² + Σ_w[k,k])).

The paper ignores the last term; without it the variance of a deterministic
simulator's dynamics is the fitted noise (~1e-8 here), and held-out log-likelihoods
are meaningless. `predict_mean` (used for planning) skips the variance entirely.

Model error. Even with the interpolation variance, a deterministic simulator's
fitted noise leaves out what the model cannot represent (smoothed support values,
a few features): on the acrobot at paper size the median error was 4-7 predictive
standard deviations in two of four test settings checked. `hipmdp.fit` therefore
calibrates two terms per (a, d) on its training instances
(`hipmdp.fitting.model_error`), and `predict` uses

    Var[Δs_d] = σ² + F Σ_w Fᵀ + c[a,d] v_ad(s) (1 + Σ_k z (μ_k² + Σ_w[k,k])) + r0[a,d]

(`interp_var_scale` c, >= 1 as `fit` calibrates it (a model made by hand may give
any c >= 0), `residual_var` r0 >= 0; c = 1, r0 = 0 when absent, as in models saved
before they existed).

Filtering with the model error. The filter's likelihood for one (transition, dimension)
row is N(Δ; f_1 + F w, τ²), and τ² must be the model's error given the weights, not
σ² alone: with σ² ~ 1e-8 against real errors ~ 1e-4 the belief collapses after a few
transitions onto whichever weights fit them, and its covariance means nothing. `update`
uses the variance above without the weight-uncertainty term, by default
(`filter_weights="prior_mean"`) with the weights at their prior mean μ_w, which `fit`
sets to the mean training weight:

    τ²[i,d] = σ² + c[a,d] v_ad(s_i) (1 + Σ_{k≥1} z[k,a,d] μ_w[k]²) + r0[a,d]

(k ≥ 1 here: every latent feature; the 1 is the mean dynamics' weight).

c was calibrated with each training instance's own weights (`fitting.model_error`);
that factor's mean keeps the weights' spread, mean_b w² = μ_w² + var_b w, and is
typically 17-36× larger on the acrobot. (The calibration weighs each instance by its
transitions; the mean here weighs instances equally, as balanced batches do.)
`filter_weights="training"` filters with that mean, mean_b w[k,b]², instead. It is
not the default because, measured, it gains nothing consistent: held-out
log-likelihood 26-27 nats lower on the paper-size acrobot, 8 higher on the cart-pole,
per-setting MSE level (README, "The filter's model-error weights").

Because τ² does not depend on the belief, the update stays linear-Gaussian: one update
with n transitions still equals n single ones. `update(..., model_error=False)` is the
paper's filter (τ² = σ²).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import linalg

from hipmdp.data import (
    Transitions,
    atomic_write,
    check_queries,
    gaussian_loglik,
    is_real_number,
    load_npz,
    npz_bytes,
    read_only,
)
from hipmdp.filter import Belief, predictive, prior_belief, update_belief
from hipmdp.gp import HyperSet
from hipmdp.kernels import KernelMeans, se_kernel

Array = np.ndarray

FORMAT_VERSION = 1

#: Where `HipMDP.update` takes its model-error factor's weights: the prior mean μ_w
#: (the default, and every model's before the setting existed), or the squared
#: training weights' mean (as c was calibrated). Model files without the field were
#: written with "prior_mean".
FILTER_WEIGHTS = ("prior_mean", "training")
_ARRAYS = (
    "support",
    "lengthscales",
    "signal_var",
    "noise_var",
    "z",
    "f",
    "weights",
    "mu_w",
    "instance_ids",
)
#: The arrays a model file may hold besides ``_ARRAYS`` (written when set).
_OPTIONAL_ARRAYS = ("residual_var", "interp_var_scale", "periodic")


def interpolation_coefficients(support: Array, hyper: HyperSet, f: Array) -> Array:
    """c[k,a,d] = (K_ad + σ²[a,d] I)⁻¹ f[k,a,d](S*).

    support: S*, (m, D); f: (K, A, D, m). Returns c with the shape of f.
    """
    K, A, D, m = f.shape
    c = np.empty_like(f)
    for a in range(A):
        for d in range(D):
            h = hyper.get(a, d)
            Kss = se_kernel(support, support, h.lengthscales, h.signal_var, h.periodic)
            cf = linalg.cho_factor(Kss + h.noise_var * np.eye(m), lower=True)
            c[:, a, d] = linalg.cho_solve(cf, f[:, a, d].T).T
    return c


@dataclass(frozen=True, eq=False)
class HipMDP:
    """A fitted HiP-MDP.

    Attributes:
        support: S*, shape (m, D).
        hyper: per-(a, d) kernel hyperparameters and noise σ²[a,d].
        z: bool (K, A, D), z[0] all True (mean dynamics).
        f: basis values f[k,a,d](S*), shape (K, A, D, m).
        weights: posterior means of w[k,b] for the training instances, shape (K, B),
            weights[0] = 1.
        mu_w: prior mean of a new instance's weights, shape (K,), mu_w[0] = 1.
        sigma_w: prior standard deviation σ_w of a weight around μ_w.
        instance_ids: training instance ids, shape (B,), the columns of `weights`.
        info: JSON-serialisable metadata (config, log joint, ...).
        residual_var, interp_var_scale: the model-error terms r0 and c of the
            predictive variance (module docstring), each (A, D), or None.
        filter_weights: the weights of the filter's model-error factor,
            "prior_mean" (μ_w², module docstring) or "training" (mean_b w[k,b]²;
            see `hipmdp.FitConfig`). This field is what the filter uses;
            `info["config"]` records what `fit` was given.
        basis_key: a digest of what defines the basis functions (support, z,
            f and the GPs' hyperparameters), set on construction: `prior` tags
            its belief with it, and a belief tagged with another key is refused.
    """

    support: Array
    hyper: HyperSet
    z: Array
    f: Array
    weights: Array
    mu_w: Array
    sigma_w: float
    instance_ids: Array
    info: dict
    residual_var: Array | None = None
    interp_var_scale: Array | None = None
    filter_weights: str = "prior_mean"

    def __post_init__(self) -> None:
        for name in ("support", "f", "weights", "mu_w"):
            value = np.asarray(getattr(self, name))
            if not (np.issubdtype(value.dtype, np.number) and value.dtype != bool):
                raise ValueError(f"{name}: expected numbers, got dtype {value.dtype}")
            object.__setattr__(self, name, read_only(value, float))
        if np.ndim(self.f) != 4:
            raise ValueError(f"f: expected shape (K, A, D, m), got {np.shape(self.f)}")
        K, A, D, m = self.f.shape
        z = np.asarray(self.z)
        if z.dtype != bool:  # 0/1 integers or floats are taken; 0.5 is not a flag
            if not np.issubdtype(z.dtype, np.number) or not np.isin(z, (0, 1)).all():
                raise ValueError(
                    f"z: expected booleans (or 0/1), got dtype {z.dtype} with values "
                    f"{np.unique(z).tolist()[:5]}"
                )
        object.__setattr__(self, "z", read_only(z, bool))
        ids = np.asarray(self.instance_ids)
        if ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(
                f"instance_ids: expected integers (B,), got dtype {ids.dtype} and "
                f"shape {ids.shape}"
            )
        if len(np.unique(ids)) != len(ids):
            raise ValueError("instance_ids: expected distinct ids (one per column)")
        object.__setattr__(self, "instance_ids", read_only(ids, np.int64))
        if not np.all(np.isfinite(self.support)):
            raise ValueError("support: expected finite values")
        if self.hyper.signal_var.shape != (A, D):
            raise ValueError(
                f"hyper: expected (A, D) = ({A}, {D}) GPs as f has, got "
                f"{self.hyper.signal_var.shape}"
            )
        if not np.all(np.isfinite(self.f)):
            raise ValueError("f: expected finite values")
        if not (
            is_real_number(self.sigma_w)
            and np.isfinite(self.sigma_w)
            and self.sigma_w > 0
        ):
            raise ValueError(
                f"sigma_w: expected a finite number > 0, got {self.sigma_w!r}"
            )
        object.__setattr__(self, "sigma_w", float(self.sigma_w))
        B = len(self.instance_ids)
        if np.shape(self.weights) != (K, B):
            raise ValueError(
                f"weights: expected shape (K, B) = ({K}, {B}) (B instance_ids), "
                f"got {np.shape(self.weights)}"
            )
        for name in ("residual_var", "interp_var_scale"):
            if getattr(self, name) is not None:
                r = np.asarray(getattr(self, name), dtype=float)
                if r.shape != (A, D) or not np.all(np.isfinite(r) & (r >= 0)):
                    raise ValueError(
                        f"{name}: expected finite values >= 0 of shape ({A}, {D})"
                    )
                object.__setattr__(self, name, read_only(r, float))
        if self.filter_weights not in FILTER_WEIGHTS:
            raise ValueError(
                f"filter_weights: expected one of {FILTER_WEIGHTS}, got "
                f"{self.filter_weights!r}"
            )
        if self.support.shape != (m, D):
            raise ValueError(
                f"support: expected shape ({m}, {D}), got {self.support.shape}"
            )
        if self.z.shape != (K, A, D) or not self.z[0].all():
            raise ValueError(f"z: expected bool (K={K}, {A}, {D}) with z[0] all True")
        if self.weights.shape[0] != K or self.mu_w.shape != (K,):
            raise ValueError(f"weights, mu_w: expected {K} rows")
        for name in ("weights", "mu_w"):
            w = getattr(self, name)
            if not np.all(np.isfinite(w)):
                raise ValueError(f"{name}: expected finite values")
            if not np.all(w[0] == 1.0):  # the mean dynamics' weight is 1
                raise ValueError(f"{name}: expected row 0 (the mean dynamics) all 1")
        object.__setattr__(
            self, "_coef", interpolation_coefficients(self.support, self.hyper, self.f)
        )
        # what the basis functions are, so what w means: from the stored arrays
        # that define them (with their shapes), not from _coef, whose round-off
        # depends on the BLAS and its thread count (the same file loaded in two
        # processes gave two keys)
        digest = hashlib.sha256()
        h = self.hyper
        for part in (
            self.support,
            self.z,
            self.f,
            h.lengthscales,
            h.signal_var,
            h.noise_var,
        ):
            part = np.ascontiguousarray(part, dtype=float)
            digest.update(repr(part.shape).encode())
            digest.update(part.tobytes())
        digest.update(repr(tuple(h.periodic)).encode())
        object.__setattr__(self, "basis_key", digest.hexdigest()[:16])
        object.__setattr__(self, "_factors", {})  # (a, d) -> Cholesky, on demand

    def _factor(self, a: int, d: int):
        """Cholesky factor of K_ad + σ²[a,d] I, computed on first use."""
        if (a, d) not in self._factors:
            h = self.hyper.get(a, d)
            m = len(self.support)
            Kss = se_kernel(
                self.support, self.support, h.lengthscales, h.signal_var, h.periodic
            )
            self._factors[a, d] = linalg.cho_factor(
                Kss + h.noise_var * np.eye(m), lower=True
            )
        return self._factors[a, d]

    def interpolation_var(self, states: Array, actions: Array) -> Array:
        """v_ad(s), the GP interpolation variance of a basis function, (n, D)."""
        return self._evaluate(states, actions, with_var=True)[1]

    def __getstate__(self) -> dict:
        # factors are a cache: not shipped to worker processes
        state = dict(self.__dict__)
        state["_factors"] = {}
        return state

    # -- shape facts ---------------------------------------------------------------
    @property
    def n_features(self) -> int:
        """K, including the mean dynamics."""
        return self.f.shape[0]

    @property
    def n_actions(self) -> int:
        return self.f.shape[1]

    @property
    def state_dim(self) -> int:
        return self.f.shape[2]

    # -- basis evaluation ------------------------------------------------------------
    def _check_inputs(self, states: Array, actions: Array) -> tuple[Array, Array]:
        return check_queries(states, actions, self.state_dim, self.n_actions)

    def basis(self, states: Array, actions: Array) -> Array:
        """z[k,a,d] f[k,a,d](s) for each transition's action, shape (n, D, K).

        states: (n, D); actions: (n,).
        """
        return self._evaluate(states, actions, with_var=False)[0]

    def _evaluate(
        self, states: Array, actions: Array, with_var: bool
    ) -> tuple[Array, Array | None]:
        """The basis (n, D, K) and, if asked, v_ad(s) (n, D), from one kernel
        evaluation k_ad(s, S*) per (action, dimension)."""
        states, actions = self._check_inputs(states, actions)
        F = np.zeros((len(states), self.state_dim, self.n_features))
        v = np.zeros((len(states), self.state_dim)) if with_var else None
        for a in np.unique(actions):
            idx = np.flatnonzero(actions == a)
            for d in range(self.state_dim):
                h = self.hyper.get(a, d)
                Kx = se_kernel(
                    states[idx], self.support, h.lengthscales, h.signal_var, h.periodic
                )
                F[idx, d] = (Kx @ self._coef[:, a, d].T) * self.z[:, a, d]
                if with_var:
                    L, _ = self._factor(a, d)
                    # L is our own factor and the states were checked finite
                    V = linalg.solve_triangular(L, Kx.T, lower=True, check_finite=False)
                    v[idx, d] = np.maximum(h.signal_var - (V * V).sum(0), 0.0)
        return F, v

    # -- online filtering ------------------------------------------------------------
    def prior(self) -> Belief:
        """Belief over an unseen instance's weights k = 2..K: N(μ_w, σ_w² I).

        In the arrays' 0-based indexing these are rows 1..K-1 of `weights` (row
        0, the mean dynamics, is the constant 1): `belief.mean[j]` is the new
        instance's counterpart of `weights[j + 1]`, and `mu_w[1:]` the prior mean.
        """
        return prior_belief(self.mu_w[1:], self.sigma_w, model=self.basis_key)

    def _check_belief(self, belief: Belief) -> None:
        if not isinstance(belief, Belief):
            raise ValueError(
                f"belief: expected a hipmdp.Belief (from prior() or update()), "
                f"got {type(belief).__name__}"
            )
        if belief.dim != self.n_features - 1:
            raise ValueError(
                f"belief: expected {self.n_features - 1} weights, got {belief.dim}"
            )
        if belief.model is not None and belief.model != self.basis_key:
            raise ValueError(
                f"belief: it is over another model's weights (basis {belief.model}, "
                f"this model's {self.basis_key}); a weight means nothing without its "
                "basis functions: start from this model's prior() (or, knowing that, "
                "untag it: Belief(belief.h, belief.P))"
            )

    def update(
        self, belief: Belief, data: Transitions, *, model_error: bool = True
    ) -> Belief:
        """Condition the belief on any number of a new instance's transitions.

        h ← h + Fᵀ T⁻¹ (Δ - f_1(s)),   P ← P + Fᵀ T⁻¹ F   (see hipmdp.filter)

        with T = diag(τ²) the model's error given the weights (`filter_noise`), or
        with τ² = σ² (the paper's filter) if `model_error` is False.
        """
        self._check_belief(belief)
        self._check_data(data)
        if not isinstance(model_error, bool):
            raise ValueError(
                f"model_error: expected True or False, got {model_error!r}"
            )
        F, v = self._evaluate(data.states, data.actions, with_var=model_error)
        noise = self._filter_noise(data.actions, v)
        return update_belief(belief, F[..., 1:], data.deltas - F[..., 0], noise)

    def filter_noise(self, states: Array, actions: Array) -> Array:
        """τ²[i,d], the variance of Δs given the weights that `update` filters with,
        shape (n, D) (module docstring)."""
        _, v = self._evaluate(states, actions, with_var=True)
        return self._filter_noise(np.asarray(actions, dtype=int), v)

    def _filter_noise(self, actions: Array, v: Array | None) -> Array:
        noise = self.hyper.noise_var[actions]
        if v is None:
            return noise
        # feature 0 has w = 1
        if self.filter_weights == "prior_mean":  # μ_w[k]²
            m2 = np.concatenate([[1.0], self.mu_w[1:] ** 2])
        else:  # "training": mean_b w[k,b]²
            m2 = np.concatenate([[1.0], np.mean(self.weights[1:] ** 2, axis=1)])
        scale = np.einsum("kad,k->ad", self.z, m2)
        if self.interp_var_scale is not None:
            scale = scale * self.interp_var_scale
        noise = noise + v * scale[actions]
        if self.residual_var is not None:
            noise = noise + self.residual_var[actions]
        return noise

    def predict(
        self, states: Array, actions: Array, belief: Belief
    ) -> tuple[Array, Array]:
        """Predicted Δs and its variance, each (n, D): noise, weight uncertainty and
        basis interpolation variance (module docstring)."""
        self._check_belief(belief)
        F, v = self._evaluate(states, actions, with_var=True)
        a = np.asarray(actions, dtype=int)
        mean, var = predictive(belief, F[..., 1:], F[..., 0], self.hyper.noise_var[a])
        # E[w_k²] for the active features of each (a, d); feature 0 has w = 1
        w2 = np.concatenate([[1.0], belief.mean**2 + np.diag(belief.cov)])
        scale = np.einsum("kad,k->ad", self.z, w2)[a]  # (n, D)
        if self.interp_var_scale is not None:
            scale = scale * self.interp_var_scale[a]
        var = var + v * scale
        if self.residual_var is not None:
            var = var + self.residual_var[a]
        return mean, var

    def predict_mean(self, states: Array, actions: Array, belief: Belief) -> Array:
        """Predicted Δs only, f_1(s) + F(s) μ, shape (n, D)."""
        self._check_belief(belief)
        F = self.basis(states, actions)
        return F[..., 0] + F[..., 1:] @ belief.mean

    def mean_predictor(self, belief: Belief) -> KernelMeans:
        """`predict_mean` at this belief as one :class:`~hipmdp.kernels.KernelMeans`
        (for many calls with one belief, as in planning): the features fold into
        β_ad = Σ_k z[k,a,d] μ_k c[k,a,d] (μ_0 = 1), one GP mean per (a, d)."""
        self._check_belief(belief)
        w = np.concatenate([[1.0], np.asarray(belief.mean, dtype=float)])
        beta = np.einsum("kadm,kad,k->adm", self._coef, self.z, w)
        return KernelMeans(
            [self.support] * self.n_actions,
            self.hyper.lengthscales,
            self.hyper.signal_var,
            list(beta),
            self.hyper.periodic,
        )

    def log_likelihood(self, data: Transitions, belief: Belief) -> float:
        """Σ_i Σ_d log N(Δ[i,d]; mean[i,d], var[i,d]) under the predictive of `predict`
        (each transition and dimension scored on its own marginal)."""
        self._check_data(data)
        mean, var = self.predict(data.states, data.actions, belief)
        return gaussian_loglik(data.deltas, mean, var)

    def _check_data(self, data: Transitions) -> None:
        if not isinstance(data, Transitions):
            raise ValueError(f"data: expected hipmdp.Transitions, got {type(data)}")
        if data.state_dim != self.state_dim:
            raise ValueError(
                f"data: expected state dimension {self.state_dim}, got {data.state_dim}"
            )
        # A belief is over one instance's weights: transitions of several instances
        # would be merged into one posterior without a word.
        ids = data.instance_ids
        if ids.size > 1:
            raise ValueError(
                f"data: expected transitions of one instance, got instances "
                f"{ids.tolist()[:10]}; take one with data.select(instances=b)"
            )
        # Δs of angles depend on angle_dims and dt (hipmdp.data): the filter must
        # compute them as the fit did. (Models saved before dt was recorded
        # lack "dt"; their angle_dims are still checked.)
        for name in ("angle_dims", "dt"):
            if name not in self.info:
                continue
            fitted, got = self.info[name], getattr(data, name)
            if name == "angle_dims":
                fitted, got = tuple(fitted), tuple(got)
            if fitted != got:
                raise ValueError(
                    f"data: {name} {got!r} differs from the fitted model's "
                    f"{fitted!r}; build the new instance's Transitions as the batch's"
                )

    # -- files -------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write one .npz (arrays + a JSON metadata string), atomically, no pickle.

        The bytes depend only on the model (see :func:`hipmdp.data.npz_bytes`).
        Returns the path; a ``path`` not ending in ``.npz`` is refused
        (``ValueError``).
        """
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"path: expected a .npz file name, got {path.name!r}")
        arrays = {
            "support": self.support,
            "lengthscales": self.hyper.lengthscales,
            "signal_var": self.hyper.signal_var,
            "noise_var": self.hyper.noise_var,
            "z": self.z,
            "f": self.f,
            "weights": self.weights,
            "mu_w": self.mu_w,
            "instance_ids": self.instance_ids,
        }
        for name in ("residual_var", "interp_var_scale"):
            if getattr(self, name) is not None:
                arrays[name] = getattr(self, name)
        if self.hyper.periodic:
            arrays["periodic"] = np.array(self.hyper.periodic, dtype=np.int64)
        meta = {
            "format_version": FORMAT_VERSION,
            "sigma_w": self.sigma_w,
            "filter_weights": self.filter_weights,
            "info": self.info,
        }
        arrays["meta_json"] = np.array(json.dumps(meta))
        data = npz_bytes(arrays)
        return atomic_write(path, lambda fh: fh.write(data), clean=True)


def load(path: str | os.PathLike) -> HipMDP:
    """Read a model written by `HipMDP.save` (allow_pickle=False)."""
    with load_npz(path) as npz:
        missing = [k for k in (*_ARRAYS, "meta_json") if k not in npz.files]
        if missing:
            raise ValueError(f"{path}: not a HiP-MDP model file, missing {missing}")
        # a renamed optional array (a damaged member name: zipfile checks the
        # data's CRC, not the central directory's names) would read as absent,
        # and the model would load without its calibrated error or periodicity
        known = {*_ARRAYS, *_OPTIONAL_ARRAYS, "meta_json"}
        unknown = sorted(set(npz.files) - known)
        if unknown:
            raise ValueError(
                f"{path}: holds arrays no HiP-MDP model file has "
                f"({', '.join(unknown)}): a damaged member name, or not a model file"
            )
        arr = {k: npz[k] for k in _ARRAYS}
        optional = {
            k: npz[k] if k in npz.files else None
            for k in ("residual_var", "interp_var_scale")
        }
        periodic = ()
        if "periodic" in npz.files:  # [0.5] loaded as (0,), a 0-d array failed
            p = npz["periodic"]
            if p.ndim != 1 or not np.issubdtype(p.dtype, np.integer):
                raise ValueError(
                    f"{path}: periodic: expected a list of dimensions, got dtype "
                    f"{p.dtype} and shape {p.shape}"
                )
            periodic = tuple(int(j) for j in p)
        raw = str(npz["meta_json"])  # a damaged array: the archive's error
        try:
            meta = json.loads(raw)
        except ValueError:
            raise ValueError(f"{path}: meta_json is not valid JSON") from None
    if not isinstance(meta, dict) or meta.get("format_version") != FORMAT_VERSION:
        version = meta.get("format_version") if isinstance(meta, dict) else None
        raise ValueError(
            f"{path}: expected format_version {FORMAT_VERSION}, got {version}"
        )
    missing = [k for k in ("sigma_w", "info") if k not in meta]
    if missing:
        raise ValueError(f"{path}: meta_json lacks {missing}")
    # a string "0.001" or true loaded as a number, a list as info
    sigma_w = meta["sigma_w"]
    if not is_real_number(sigma_w):
        raise ValueError(f"{path}: sigma_w: expected a number, got {sigma_w!r}")
    if not isinstance(meta["info"], dict):
        raise ValueError(
            f"{path}: info: expected an object, got {type(meta['info']).__name__}"
        )
    try:
        hyper = HyperSet(
            arr["lengthscales"], arr["signal_var"], arr["noise_var"], periodic
        )
        return HipMDP(
            support=arr["support"],
            hyper=hyper,
            z=arr["z"],  # checked: booleans, or 0/1 (2 or 0.5 is not a flag)
            f=arr["f"],
            weights=arr["weights"],
            mu_w=arr["mu_w"],
            sigma_w=float(sigma_w),
            instance_ids=arr["instance_ids"],
            info=meta["info"],
            # files written before the field existed filtered at μ_w
            filter_weights=meta.get("filter_weights", "prior_mean"),
            **optional,
        )
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}: {err}") from None
