"""Support points S* by greedy maximum reconstruction error.

Symbols: `S*` support states, shape (m, D); `X` candidate states (n, D); `r = (a, d)`
one of the R prediction tasks, each with its own kernel `k_r` (ℓ_r, σ_f,r²) and noise
`σ_r²`.

Each basis function is interpolated from its values at S* with the GP mean
`f(s) = k_r(s, S*) (K_r + σ_r² I)⁻¹ f(S*)`. For a function drawn from the GP prior,
the expected squared error of that reconstruction at `s`, relative to the prior
variance, is

    e_r(s) = (σ_f,r² - k_r(s, S*) (K_r + σ_r² I)⁻¹ k_r(S*, s)) / σ_f,r²,

and the error of a candidate is the mean over tasks, `e(s) = (1/R) Σ_r e_r(s)`. The
greedy rule adds the candidate with the largest current `e(s)` until there are `m`
support points (the paper found minimising the maximum error best). Because the error
depends only on states, the rule places support points where the data are, covering
them evenly in each kernel's metric.

Deviation from a naive implementation: the posterior variances are updated
incrementally. With `L_r` the Cholesky factor of `K_r + σ_r² I` on the chosen points,
`C_r = k_r(X, S*) L_r⁻ᵀ` (n, j) gives `e_r = (σ_f,r² - ‖C_r[i]‖²) / σ_f,r²`; adding
candidate `p` appends the column `(k_r(X, x_p) - C_r C_r[p]ᵀ) / sqrt(σ_f,r² + σ_r² -
‖C_r[p]‖²)`. A step costs O(R n j), the whole selection O(R n m²). Candidates are a
uniform subsample (from `rng`) when the data are large.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from tqdm.auto import tqdm

from hipmdp.data import check_integer, check_rng
from hipmdp.gp import HyperSet, subsample
from hipmdp.kernels import (
    _check_params,
    centre,
    check_periodic,
    embed,
    expanded_sqdist,
    se_kernel,
)

Array = np.ndarray


class Support(NamedTuple):
    """Chosen support points.

    points: S*, shape (m, D); index: rows of the input state array they came from (m,);
    errors: e(s) of each point when it was chosen, shape (m,) (non-increasing up to
    round-off).
    """

    points: Array
    index: Array
    errors: Array


def _kernels(hyper: HyperSet) -> list[tuple[Array, float, float]]:
    A, D = hyper.signal_var.shape
    return [
        (
            hyper.lengthscales[a, d],
            float(hyper.signal_var[a, d]),
            float(hyper.noise_var[a, d]),
        )
        for a in range(A)
        for d in range(D)
    ]


def greedy_support(
    X: Array,
    kernels: list[tuple[Array, float, float]],
    m: int,
    progress: bool = False,
    periodic: tuple[int, ...] = (),
) -> Support:
    """Greedy max-error selection of `m` rows of X (n, D), incremental Cholesky.

    kernels: one (ℓ_r (D,), σ_f,r², σ_r²) per task r; periodic: the angle dimensions
    of X (`hipmdp.kernels`). Deterministic; ties go to the lowest index. Returns
    Support with index into X.
    """
    X = np.asarray(X, dtype=float)
    n = X.shape[0]
    if not 1 <= m <= n:
        raise ValueError(f"m: expected 1 <= m <= {n} (number of candidates), got {m}")
    # embedded once: the plain kernel of E with ℓ[dims] is the periodic kernel of X;
    # centred once as the kernels centre X (never the angles' cos/sin columns,
    # which se_kernel of E would take for plain ones)
    periodic = check_periodic(periodic, X.shape[1])
    E, dims = embed(X, periodic)
    shift = centre(E, dims, periodic)
    if shift is not None:
        E = E - shift
    for ell, sf2, _ in kernels:  # as se_kernel checked them
        _check_params(ell, sf2, X.shape[1])
    R = len(kernels)
    C = np.zeros(
        (R, m, n)
    )  # C_r transposed: row j holds column j of C_r over candidates
    var = np.array([[sf2] * n for _, sf2, _ in kernels])  # posterior variance (R, n)
    sf2s = np.array([k[1] for k in kernels])
    chosen = np.empty(m, dtype=int)
    errors = np.empty(m)
    for j in tqdm(range(m), desc="support points", disable=not progress):
        err = (var / sf2s[:, None]).mean(0)
        err[chosen[:j]] = -np.inf  # never choose a point twice
        p = int(np.argmax(err))
        chosen[j], errors[j] = p, err[p]
        for r, (ell, sf2, sn2) in enumerate(kernels):
            cp = C[r, :j, p]
            diag = np.sqrt(max(sf2 + sn2 - cp @ cp, 1e-300))
            kp = sf2 * np.exp(-0.5 * expanded_sqdist(E, E[p : p + 1], ell[dims]))[:, 0]
            col = (kp - cp @ C[r, :j]) / diag
            C[r, j] = col
            var[r] -= col * col
    return Support(points=X[chosen], index=chosen, errors=errors)


def greedy_support_dense(
    X: Array,
    kernels: list[tuple[Array, float, float]],
    m: int,
    periodic: tuple[int, ...] = (),
) -> Support:
    """Plain reference of `greedy_support`: every step recomputes each e_r(s) from a
    fresh dense solve with (K_r + σ_r² I) on the chosen points. For tests, O(R n m³)."""
    X = np.asarray(X, dtype=float)
    n = X.shape[0]
    chosen: list[int] = []
    errors = []
    for _ in range(m):
        err = np.zeros(n)
        for ell, sf2, sn2 in kernels:
            v = np.full(n, sf2)
            if chosen:
                S = X[chosen]
                Kss = se_kernel(S, S, ell, sf2, periodic) + sn2 * np.eye(len(chosen))
                Kxs = se_kernel(X, S, ell, sf2, periodic)
                v = sf2 - np.einsum("ij,ji->i", Kxs, np.linalg.solve(Kss, Kxs.T))
            err += v / sf2
        err /= len(kernels)
        err[chosen] = -np.inf
        p = int(np.argmax(err))
        chosen.append(p)
        errors.append(err[p])
    idx = np.array(chosen)
    return Support(points=X[idx], index=idx, errors=np.array(errors))


def select_support(
    states: Array,
    hyper: HyperSet,
    m: int,
    *,
    n_candidates: int,
    rng: np.random.Generator,
    progress: bool = False,
) -> Support:
    """Choose m support states among `states` (N, D) for the kernels in `hyper`.

    Candidates: at most `n_candidates` distinct rows drawn uniformly with `rng`
    (duplicate states are dropped first); then `greedy_support`. The returned index
    refers to rows of `states`.
    """
    states = np.asarray(states, dtype=float)
    dim = hyper.lengthscales.shape[2]
    if states.ndim != 2 or states.shape[1] != dim:
        raise ValueError(
            f"states: expected shape (N, {dim}), the hyperparameters' state "
            f"dimension, got {states.shape}"
        )  # a narrower one was fitted with the first length scales
    if not np.all(np.isfinite(states)):
        raise ValueError("states: expected finite values")  # NaN rows were chosen
    check_integer("n_support (m)", m, 1)
    check_integer("n_candidates", n_candidates, 1)
    check_rng(rng)
    _, first = np.unique(states, axis=0, return_index=True)
    first = np.sort(first)
    cand = first[subsample(len(first), n_candidates, rng=rng)]
    if m > len(cand):
        raise ValueError(
            f"n_support: expected at most {len(cand)} distinct candidate states, "
            f"got {m}"
        )
    sup = greedy_support(
        states[cand], _kernels(hyper), m, progress=progress, periodic=hyper.periodic
    )
    return Support(points=sup.points, index=cand[sup.index], errors=sup.errors)
