"""Anisotropic squared-exponential kernel with analytic gradients.

Symbols: `x, x'` states of dimension `D`; `ℓ` length scales, shape (D,); `σ_f²` signal
variance; `σ_n²` noise variance (added by the GP, not by the kernel).

    k(x, x') = σ_f² exp(-½ Σ_j δ_j(x_j, x'_j)² / ℓ_j²)

with `δ_j = x_j - x'_j`, or, for a periodic dimension `j` (an angle: `periodic`
lists them), the chord `δ_j = 2 sin((x_j - x'_j) / 2)`. The chord is the distance
between `(cos x_j, sin x_j)` and `(cos x'_j, sin x'_j)`, so the kernel is the SE
kernel of that embedding (MacKay's periodic kernel, period 2π): positive definite,
smooth across `x_j = ±π`, and equal to the plain kernel to O(δ⁴) for small
differences. Every function here takes `periodic` (default none) and computes
distances in the embedding (`embed`).

Hyperparameters are optimised on the log scale, `θ = (log ℓ_1..log ℓ_D, log σ_f²,
log σ_n²)`, so every gradient here is with respect to log-parameters.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from hipmdp.data import check_queries, is_integer

Array = np.ndarray

# KernelMeans evaluates at most this many kernel values at once (a few
# temporaries of this size: about 50 MB)
_CHUNK = 1 << 21


class KernelGrad(NamedTuple):
    """Kernel matrix and its derivatives with respect to the log-parameters.

    K: k(X, X), shape (n, n).
    dK: ∂K/∂θ_i for θ = (log ℓ_1..log ℓ_D, log σ_f²), shape (D + 1, n, n).
    """

    K: Array
    dK: Array


def _check_params(lengthscales: Array, signal_var: float, dim: int) -> Array:
    ell = np.asarray(lengthscales, dtype=float)
    if ell.shape != (dim,):
        raise ValueError(f"lengthscales: expected shape ({dim},), got {ell.shape}")
    if not np.all(np.isfinite(ell)) or np.any(ell <= 0):
        raise ValueError(f"lengthscales: expected finite positive values, got {ell}")
    if not np.isfinite(signal_var) or signal_var <= 0:
        raise ValueError(f"signal_var: expected finite positive, got {signal_var}")
    return ell


def check_periodic(periodic, dim: int) -> tuple[int, ...]:
    """`periodic` as a sorted tuple of distinct dimensions in [0, dim), or raise."""
    try:
        raw = tuple(periodic)
    except TypeError:
        raise ValueError(
            f"periodic: expected a sequence of dimension indices, got {periodic!r}"
        ) from None
    if not all(is_integer(j) for j in raw):  # int() made 1.5 dimension 1, "01" 0 and 1
        raise ValueError(
            f"periodic: expected integer dimension indices, got {periodic!r}"
        )
    dims = tuple(sorted(int(j) for j in raw))
    if len(set(dims)) != len(dims) or any(not 0 <= j < dim for j in dims):
        raise ValueError(
            f"periodic: expected distinct dimensions in [0, {dim}), got {periodic!r}"
        )
    return dims


def embedded_columns(dim: int, periodic: tuple[int, ...] = ()) -> Array:
    """Per column of `embed`'s output, the input dimension it came from, (D + P,):
    the non-periodic dimensions in order, then the periodic ones twice (cos, sin).
    Index the length scales with it."""
    plain = [j for j in range(dim) if j not in periodic]
    return np.array(plain + list(periodic) * 2, dtype=int)


def embed(X: Array, periodic: tuple[int, ...] = ()) -> tuple[Array, Array]:
    """Inputs in the space where the kernel's distance is Euclidean.

    X: (n, D); periodic: dimensions replaced by (cos x_j, sin x_j). Returns the
    embedded inputs (n, D + P) and `embedded_columns` (D + P,): the plain SE kernel
    of the embedded inputs with length scales ``ℓ[columns]`` is the periodic kernel.
    With no periodic dimensions X is returned as is.
    """
    col = embedded_columns(X.shape[1], periodic)
    if not periodic:
        return X, col
    p = list(periodic)
    plain = col[: len(col) - 2 * len(p)]
    return np.concatenate([X[:, plain], np.cos(X[:, p]), np.sin(X[:, p])], 1), col


#: A plain (non-angle) input column whose mean lies more than this many standard
#: deviations from 0 is centred before distances are expanded (`centre`).
CENTRE_RATIO = 8.0


def centre(E: Array, col: Array, periodic: tuple[int, ...] = ()) -> Array | None:
    """The point to subtract from both sets of embedded inputs before the expanded
    distance |a|² + |b|² - 2 a·b, or None for none.

    The expanded form loses precision as the inputs move away from 0 relative to
    their spread, and nearly noise-free GPs magnify the loss: a user's states
    offset by 75 times their spread made a fit's held-out MSE 70 times worse, and
    larger offsets made the fit fail. So each plain column of ``E`` (n, D + P)
    whose mean is more than `CENTRE_RATIO` standard deviations from 0 (so also a
    constant column other than 0) is centred on its mean; the others, the angle
    embedding's cos/sin (bounded by 1) and sets of fewer than 2 rows are left
    (shift 0). Inputs near 0, as every experiment's here, are therefore computed
    exactly as without this step.
    """
    if len(E) < 2:
        return None
    mean, sd = E.mean(0), E.std(0)
    far = (np.abs(mean) > CENTRE_RATIO * sd) & ~np.isin(col, periodic)
    if not far.any():
        return None
    return np.where(far, mean, 0.0)


def scaled_sqdist(
    X1: Array, X2: Array, lengthscales: Array, periodic: tuple[int, ...] = ()
) -> Array:
    """Squared distance after scaling by the length scales.

        r²(x, x') = Σ_j δ_j(x_j, x'_j)² / ℓ_j²

    (δ_j the chord on `periodic` dimensions, module docstring). X1: (n1, D); X2:
    (n2, D); lengthscales: ℓ, (D,). Returns (n1, n2), clipped at 0 (the expanded form
    |a|² + |b|² - 2 a·b can go slightly negative by round-off). Inputs far from 0
    are first shifted by the point `centre` takes from X2 alone (as `KernelMeans`
    takes it from its inputs, so the two agree, and a query's distances do not
    depend on the other queries: bit for bit in a batch of the same size; a
    query alone can be summed in another order by BLAS), which leaves the
    distances as they are.
    """
    E1, col = embed(X1, periodic)
    E2, _ = embed(X2, periodic)
    shift = centre(E2, col, periodic)
    if shift is not None:
        E1, E2 = E1 - shift, E2 - shift
    return expanded_sqdist(E1, E2, lengthscales[col])


def expanded_sqdist(E1: Array, E2: Array, scales: Array) -> Array:
    """``Σ_c ((e1_c - e2_c) / scales_c)²`` of embedded inputs E1 (n1, C) and E2
    (n2, C) as the expanded form |a|² + |b|² - 2 a·b, clipped at 0, with no
    centring: for inputs already embedded and centred as `scaled_sqdist` does
    (`embed`, then `centre` with the embedding's columns and angles)."""
    A = E1 / scales
    Bm = E2 / scales
    d2 = (A * A).sum(1)[:, None] + (Bm * Bm).sum(1)[None, :] - 2.0 * (A @ Bm.T)
    return np.maximum(d2, 0.0)


def se_kernel(
    X1: Array,
    X2: Array,
    lengthscales: Array,
    signal_var: float,
    periodic: tuple[int, ...] = (),
) -> Array:
    """Cross-covariance `k(X1, X2) = σ_f² exp(-½ r²)`.

    X1: (n1, D); X2: (n2, D); lengthscales: ℓ, (D,); signal_var: σ_f²; periodic:
    the angle dimensions (module docstring). Returns shape (n1, n2).
    """
    X1 = np.atleast_2d(np.asarray(X1, dtype=float))
    X2 = np.atleast_2d(np.asarray(X2, dtype=float))
    if X1.shape[1] != X2.shape[1]:
        raise ValueError(
            f"X1 and X2: expected the same dimension, got {X1.shape[1]} and "
            f"{X2.shape[1]}"
        )
    ell = _check_params(lengthscales, signal_var, X1.shape[1])
    periodic = check_periodic(periodic, X1.shape[1])
    return signal_var * np.exp(-0.5 * scaled_sqdist(X1, X2, ell, periodic))


def se_kernel_grad(
    X: Array, lengthscales: Array, signal_var: float, periodic: tuple[int, ...] = ()
) -> KernelGrad:
    """k(X, X) and its gradient with respect to (log ℓ, log σ_f²).

        ∂K/∂log ℓ_j = K ⊙ δ_j(x_j, x'_j)² / ℓ_j²
        ∂K/∂log σ_f² = K

    X: (n, D); periodic: the angle dimensions, whose δ_j² is the chord's
    (cos x_j - cos x'_j)² + (sin x_j - sin x'_j)². Returns KernelGrad with K (n, n)
    and dK (D + 1, n, n).
    """
    X = np.atleast_2d(np.asarray(X, dtype=float))
    n, D = X.shape
    ell = _check_params(lengthscales, signal_var, D)
    periodic = check_periodic(periodic, D)
    K = signal_var * np.exp(-0.5 * scaled_sqdist(X, X, ell, periodic))
    dK = np.zeros((D + 1, n, n))
    E, col = embed(X, periodic)
    Es = E / ell[col]
    for c, j in enumerate(col):  # a periodic dimension sums its two columns
        diff = Es[:, c, None] - Es[None, :, c]
        dK[j] += K * diff * diff
    dK[D] = K
    return KernelGrad(K=K, dK=dK)


class KernelMeans:
    """Fixed kernel-weighted sums ``μ_ad(s) = σ_f²[a,d] Σ_j exp(-½ r²_ad(s, x_aj))
    β_ad[j]``, every output dimension ``d`` of one action in one evaluation.

    This is the shape of every mean prediction that planning makes: a GP's
    predictive mean (``x_a`` its data, ``β = (K + σ² I)⁻¹ y``), or a HiP-MDP's at a
    fixed belief (``x_a = S*``, ``β_ad = Σ_k z[k,a,d] μ_k c[k,a,d]``). The inputs
    scaled by each output's length scales and their squared norms are computed once
    here, so a call costs a few array operations per action, against one
    :func:`se_kernel` call per (action, dimension).

    Args:
        inputs: per action ``a``, ``x_a``, shape ``(n_a, D)`` (``n_a`` may be 0: the
            mean is then 0).
        lengthscales: ``ℓ[a,d]``, shape ``(A, E, D)`` for ``E`` outputs.
        signal_var: ``σ_f²[a,d]``, shape ``(A, E)``.
        coefficients: per action ``β_a``, shape ``(E, n_a)``.
        periodic: the angle dimensions (module docstring), shared by every kernel.
    """

    def __init__(
        self, inputs, lengthscales, signal_var, coefficients, periodic=()
    ) -> None:
        ell = np.asarray(lengthscales, dtype=float)
        sf2 = np.asarray(signal_var, dtype=float)
        if ell.ndim != 3 or sf2.shape != ell.shape[:2]:
            raise ValueError(
                "lengthscales, signal_var: expected shapes (A, E, D) and (A, E), got "
                f"{ell.shape} and {sf2.shape}"
            )
        A, E, D = ell.shape
        if len(inputs) != A or len(coefficients) != A:
            raise ValueError(
                f"inputs, coefficients: expected {A} actions, got {len(inputs)} and "
                f"{len(coefficients)}"
            )
        self.n_actions, self.n_outputs, self.state_dim = A, E, D
        self.periodic = check_periodic(periodic, D)
        col = embedded_columns(D, self.periodic)
        self._scaled, self._sqnorm, self._coef, self._shift = [], [], [], []
        for a in range(A):
            x = np.asarray(inputs[a], dtype=float)
            if x.ndim != 2 or x.shape[1] != D or not np.all(np.isfinite(x)):
                # reshape(-1, D) read a (4, 2) input as (2, 4) when D = 4
                raise ValueError(
                    f"inputs[{a}]: expected finite values of shape (n, {D}), got "
                    f"shape {x.shape}"
                    + ("" if x.ndim != 2 or x.shape[1] != D else " with non-finite")
                )
            beta = np.asarray(coefficients[a], dtype=float)
            if beta.shape != (E, len(x)) or not np.all(np.isfinite(beta)):
                raise ValueError(
                    f"coefficients[{a}]: expected finite values of shape "
                    f"({E}, {len(x)}), got shape {beta.shape}"
                    + ("" if beta.shape != (E, len(x)) else " with non-finite")
                )
            for d in range(E):
                _check_params(ell[a, d], float(sf2[a, d]), D)
            x = embed(x, self.periodic)[0]  # (n_a, D + P)
            shift = centre(x, col, self.periodic)  # as scaled_sqdist's
            self._shift.append(shift)
            if shift is not None:
                x = x - shift
            B = x[None] / ell[a][:, None, col]  # (E, n_a, D + P)
            self._scaled.append(B.transpose(0, 2, 1).copy())  # (E, D + P, n_a)
            self._sqnorm.append((B * B).sum(-1)[:, None, :])  # (E, 1, n_a)
            # σ_f² folded into β: μ = exp(-½ r²) @ (σ_f² β)
            self._coef.append((sf2[a][:, None] * beta)[:, :, None])  # (E, n_a, 1)
        self._inv_ell = 1.0 / ell[..., col]  # (A, E, D + P)

    def __call__(self, states, actions) -> Array:
        """``μ_ad(s_i)`` for each row's action, shape ``(n, E)``.

        states: ``(n, D)`` finite; actions: ``(n,)`` integers in ``[0, A)``.
        """
        states, actions = check_queries(states, actions, self.state_dim, self.n_actions)
        states = embed(states, self.periodic)[0]
        out = np.zeros((len(states), self.n_outputs))
        if len(actions) and np.all(actions == actions[0]):  # e.g. planning's state
            groups = [(int(actions[0]), None)]  # every row: slices, no gather
        else:
            groups = [(a, np.flatnonzero(actions == a)) for a in np.unique(actions)]
        for a, idx in groups:
            # at most _CHUNK kernel values at a time: (E, rows, n_a) floats
            rows = max(1, _CHUNK // max(1, self.n_outputs * self._coef[a].shape[1]))
            n = len(states) if idx is None else len(idx)
            for start in range(0, n, rows):
                part = slice(start, start + rows)
                part = part if idx is None else idx[part]
                out[part] = self._means(a, states[part])
        return out

    def _means(self, a: int, states: Array) -> Array:
        if self._shift[a] is not None:
            states = states - self._shift[a]
        S = states[None] * self._inv_ell[a][:, None, :]  # (E, n, D + P), embedded
        d2 = (S * S).sum(-1)[:, :, None] + self._sqnorm[a] - 2.0 * (S @ self._scaled[a])
        k = np.exp(-0.5 * np.maximum(d2, 0.0))  # (E, n, n_a)
        return (k @ self._coef[a])[..., 0].T
