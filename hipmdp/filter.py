"""Online belief over a new instance's latent weights, in information form.

Symbols: `k` latent parameter (the mean-dynamics feature k = 1 is excluded: its weight
is fixed at 1, so the belief is over the `K - 1` others); `d` state dimension; `n`
transitions; `F` basis values `z[k,a,d] f[k,a,d](s)`, shape (n, D, K - 1); `f_1` the
mean dynamics `f[1,a,d](s)`, shape (n, D); `σ²` the variance of each (transition,
dimension) row given the weights, shape (n, D) (`HipMDP.update` passes the model's
calibrated error τ², the paper the GP noise σ²[a,d]); `Δ` observed changes `s' - s`,
shape (n, D).

The belief `N(w; μ, Σ)` is kept as `(h, P) = (Σ⁻¹ μ, Σ⁻¹)`:

    prior:   P₀ = I / σ_w²,  h₀ = P₀ μ_w
    update:  h ← h + Fᵀ Σ⁻¹ (Δ - f_1),   P ← P + Fᵀ Σ⁻¹ F

with `Σ = diag(σ²)` over the stacked (transition, dimension) rows. The paper prints the
innovation as `Δ`; the mean-dynamics term must be subtracted (DESIGN errata). Since
every step adds a sum over rows, one update with n transitions equals n single updates.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import linalg

from hipmdp.data import atomic_write, is_real_number, load_npz, npz_bytes, read_only

Array = np.ndarray
#: What a belief file's metadata says it is (:meth:`Belief.save`).
BELIEF_KIND = "hipmdp.Belief"


@dataclass(frozen=True, eq=False)
class Belief:
    """Gaussian belief over the latent weights in information form.

    h: information vector Σ⁻¹ μ, shape (K - 1,); P: precision Σ⁻¹, shape (K - 1, K - 1).
    model: which model's weights the belief is over (`HipMDP.basis_key`), set by
    `HipMDP.prior` and kept by every update, so that a model refuses another's
    belief of the same size; None for a belief built by hand (taken by any model
    of its size).
    """

    h: Array
    P: Array
    model: str | None = field(default=None, kw_only=True)

    def __post_init__(self) -> None:
        h = np.asarray(self.h, dtype=float)
        P = np.asarray(self.P, dtype=float)
        if h.ndim != 1 or P.shape != (len(h), len(h)):
            raise ValueError(
                f"Belief: expected h (k,) and P (k, k), got {h.shape} and {P.shape}"
            )
        if not (np.all(np.isfinite(h)) and np.all(np.isfinite(P))):
            raise ValueError("Belief: expected finite h and P")
        scale = np.abs(P).max(initial=0.0)
        if np.abs(P - P.T).max(initial=0.0) > 1e-8 * scale:
            raise ValueError("Belief: expected a symmetric precision P")
        if len(h):
            try:
                np.linalg.cholesky(P)
            except np.linalg.LinAlgError:
                raise ValueError(
                    "Belief: expected a positive-definite precision P"
                ) from None
        if self.model is not None and not isinstance(self.model, str):
            raise ValueError(
                f"Belief: expected model to be a str or None, got {self.model!r}"
            )
        object.__setattr__(self, "h", read_only(h, float))
        object.__setattr__(self, "P", read_only(P, float))

    @property
    def dim(self) -> int:
        """Number of latent weights K - 1."""
        return len(self.h)

    @property
    def mean(self) -> Array:
        """μ = P⁻¹ h, shape (K - 1,)."""
        if self.dim == 0:
            return np.zeros(0)
        return linalg.cho_solve(linalg.cho_factor(self.P, lower=True), self.h)

    @property
    def cov(self) -> Array:
        """Σ = P⁻¹, shape (K - 1, K - 1)."""
        if self.dim == 0:
            return np.zeros((0, 0))
        return linalg.cho_solve(linalg.cho_factor(self.P, lower=True), np.eye(self.dim))

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``h``, ``P`` and ``model`` to one .npz, atomically, no pickle (to
        go on filtering an instance in another process: :meth:`load`). The
        bytes depend only on the belief. Returns the path; a ``path`` not
        ending in ``.npz`` is refused (``ValueError``)."""
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"path: expected a .npz file name, got {path.name!r}")
        meta = {"kind": BELIEF_KIND, "format_version": 1, "model": self.model}
        data = npz_bytes({"h": self.h, "P": self.P, "meta_json": json.dumps(meta)})
        return atomic_write(path, lambda fh: fh.write(data), clean=True)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Belief:
        """Read a belief written by :meth:`save` (allow_pickle=False); a
        ValueError names the file and what is wrong with it."""
        with load_npz(path) as npz:
            names = sorted(npz.files)
            if names != ["P", "h", "meta_json"]:
                raise ValueError(
                    f"{path}: not a belief file (expected arrays h, P and "
                    f"meta_json, got {', '.join(names) or 'none'})"
                )
            h, P, raw = npz["h"], npz["P"], str(npz["meta_json"])
        try:
            meta = json.loads(raw)
        except ValueError:
            raise ValueError(f"{path}: meta_json is not valid JSON") from None
        if not isinstance(meta, dict) or meta.get("kind") != BELIEF_KIND:
            raise ValueError(f"{path}: not a belief file (meta_json's kind)")
        version = meta.get("format_version")
        if type(version) is not int or version != 1:  # not true, not 1.0
            raise ValueError(f"{path}: expected format_version 1, got {version!r}")
        for name, value in (("h", h), ("P", P)):
            if value.dtype.kind not in "fiu":  # complex lost its imaginary part
                raise ValueError(
                    f"{path}: {name}: expected real numbers, got dtype {value.dtype}"
                )
        try:
            return cls(h, P, model=meta.get("model"))
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None


def prior_belief(mu_w: Array, sigma_w: float, model: str | None = None) -> Belief:
    """Prior over an unseen instance's weights: P₀ = I/σ_w², h₀ = P₀ μ_w.

    mu_w: μ_w[k] for k = 2..K, shape (K - 1,); model: the belief's `Belief.model`.
    """
    mu_w = np.asarray(mu_w, dtype=float)
    if mu_w.ndim != 1 or not np.all(np.isfinite(mu_w)):
        raise ValueError(f"mu_w: expected finite shape (K - 1,), got {mu_w.shape}")
    if not (is_real_number(sigma_w) and np.isfinite(sigma_w) and sigma_w > 0):
        raise ValueError(f"sigma_w: expected a finite number > 0, got {sigma_w!r}")
    P0 = np.eye(len(mu_w)) / sigma_w**2
    return Belief(h=P0 @ mu_w, P=P0, model=model)


def _check_rows(belief: Belief, F: Array, **rows: Array) -> tuple[Array, ...]:
    """``F`` and the (n, D) arrays ``rows`` as finite float arrays of matching
    shapes, ``noise_var`` > 0, or a ValueError naming the argument (NaN in F or
    the innovation was blamed on the Belief; predictive broadcast an f1 of shape
    (D,) and took a negative σ²)."""
    if not isinstance(belief, Belief):
        raise ValueError(f"belief: expected a Belief, got {type(belief).__name__}")
    F = np.asarray(F, dtype=float)
    if F.ndim != 3 or F.shape[2] != belief.dim:
        raise ValueError(f"F: expected shape (n, D, {belief.dim}), got {F.shape}")
    out = [F]
    for name, x in rows.items():
        x = np.asarray(x, dtype=float)
        if x.shape != F.shape[:2]:
            raise ValueError(f"{name}: expected shape {F.shape[:2]}, got {x.shape}")
        out.append(x)
    for name, x in zip(["F", *rows], out, strict=True):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name}: expected finite values")
    named = dict(zip(rows, out[1:], strict=True))
    if "noise_var" in named and not np.all(named["noise_var"] > 0):
        raise ValueError("noise_var: expected finite values > 0")
    return tuple(out)


def update_belief(
    belief: Belief, F: Array, innovation: Array, noise_var: Array
) -> Belief:
    """Condition the belief on n transitions at once.

        h ← h + Σ_{i,d} F[i,d,:] (Δ[i,d] - f_1[i,d]) / σ²[i,d]
        P ← P + Σ_{i,d} F[i,d,:] F[i,d,:]ᵀ / σ²[i,d]

    F: (n, D, K - 1); innovation: Δ - f_1, shape (n, D); noise_var: σ², shape (n, D).
    """
    F, innovation, noise_var = _check_rows(
        belief, F, innovation=innovation, noise_var=noise_var
    )
    inv = 1.0 / noise_var
    h = belief.h + np.einsum("idk,id->k", F, innovation * inv)
    P = belief.P + np.einsum("idk,idj->kj", F * inv[..., None], F)
    return Belief(h=h, P=0.5 * (P + P.T), model=belief.model)


def predictive(
    belief: Belief, F: Array, f1: Array, noise_var: Array
) -> tuple[Array, Array]:
    """Predictive mean and variance of Δs under the belief.

        mean[i,d] = f_1[i,d] + F[i,d,:] μ
        var[i,d]  = σ²[i,d] + F[i,d,:] Σ F[i,d,:]ᵀ

    F: (n, D, K - 1); f1, noise_var: (n, D). Returns two (n, D) arrays. The basis
    functions are taken at their GP-mean interpolation (their own uncertainty is
    ignored, as in the paper).
    """
    F, f1, noise_var = _check_rows(belief, F, f1=f1, noise_var=noise_var)
    if belief.dim == 0:
        return f1.copy(), noise_var.copy()
    mu, cov = belief.mean, belief.cov
    mean = f1 + F @ mu
    var = noise_var + np.einsum("idk,kj,idj->id", F, cov, F)
    return mean, var
