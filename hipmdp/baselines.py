"""Baselines of the paper's prediction experiments: single GPs that ignore instances.

Symbols: `a` action, `d` state dimension, `Δs` the predicted change; one zero-mean GP
per `(a, d)` with the anisotropic squared-exponential kernel of `hipmdp.kernels`.

- "batch only" (the average model): one GP on all batch data of every training
  instance, ignoring which instance a transition came from;
- "train only": one GP on the new instance's few transitions;
- "batch + train": one GP on both.

Hyperparameters are fitted by maximum marginal likelihood on (a subsample of) the same
data the GP is conditioned on, pooled as one GP (that is what these baselines assume),
unless given. Large batches use a subset-of-data approximation: at most `n_max`
transitions per action, drawn uniformly with `rng`; "batch + train" always keeps every
training transition and fills the rest of the budget from the batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hipmdp.data import Transitions, check_integer, check_queries, gaussian_loglik
from hipmdp.gp import GPPosterior, HyperSet, condition, fit_hyperparameters, subsample
from hipmdp.kernels import KernelMeans, check_periodic

Array = np.ndarray


@dataclass(frozen=True, eq=False)
class GPBaseline:
    """Independent GPs per (action, dimension) on pooled data.

    posteriors: posteriors[a][d] is the GP conditioned on action-a data, or None where
    action a has no data (the prior N(0, σ_f²) is used there); hyper: their
    hyperparameters (noise σ²[a,d] included); name: which baseline.
    """

    posteriors: tuple[tuple[GPPosterior | None, ...], ...]
    hyper: HyperSet
    name: str

    @property
    def n_actions(self) -> int:
        return len(self.posteriors)

    @property
    def state_dim(self) -> int:
        return self.hyper.signal_var.shape[1]

    def predict_mean(self, states: Array, actions: Array) -> Array:
        """Predictive mean of Δs only, (n, D): O(n) per state against the variance's
        O(n²). states: (n, D); actions: (n,)."""
        return self._predict(states, actions, with_var=False)[0]

    def mean_predictor(self) -> KernelMeans:
        """`predict_mean` as one :class:`~hipmdp.kernels.KernelMeans` (for many
        calls, as in planning). The GPs of one action share their inputs; each
        keeps the hyperparameters it was conditioned with."""
        ell = np.array(self.hyper.lengthscales, dtype=float)
        sf2 = np.array(self.hyper.signal_var, dtype=float)
        inputs, coef = [], []
        for a, row in enumerate(self.posteriors):
            posts = [p for p in row if p is not None]
            if not posts:  # no data for this action: mean 0, as in predict_mean
                inputs.append(np.zeros((0, self.state_dim)))
                coef.append(np.zeros((self.state_dim, 0)))
                continue
            if len(posts) != len(row) or any(
                not np.array_equal(p.X, posts[0].X) for p in posts
            ):
                raise ValueError(
                    f"posteriors[{a}]: expected one input set for every dimension"
                )
            for d, p in enumerate(posts):
                ell[a, d], sf2[a, d] = p.hyper.lengthscales, p.hyper.signal_var
            inputs.append(posts[0].X)
            coef.append(np.array([p.alpha for p in posts]))
        return KernelMeans(inputs, ell, sf2, coef, self.hyper.periodic)

    def predict(self, states: Array, actions: Array) -> tuple[Array, Array]:
        """Predictive mean and variance (noise included) of Δs, each (n, D).

        states: (n, D); actions: (n,) integers in [0, n_actions).
        """
        return self._predict(states, actions, with_var=True)

    def _predict(
        self, states: Array, actions: Array, with_var: bool
    ) -> tuple[Array, Array]:
        states, actions = check_queries(states, actions, self.state_dim, self.n_actions)
        D = self.state_dim
        mean = np.zeros((len(states), D))
        var = np.zeros((len(states), D))
        for a in np.unique(actions):
            idx = np.flatnonzero(actions == a)
            for d in range(D):
                post = self.posteriors[a][d]
                h = self.hyper.get(a, d)
                if post is None:
                    var[idx, d] = h.signal_var + h.noise_var
                elif not with_var:
                    mean[idx, d] = post.predict_mean(states[idx])
                else:
                    mean[idx, d], var[idx, d] = post.predict(
                        states[idx], include_noise=True
                    )
        return mean, var

    def log_likelihood(self, data: Transitions) -> float:
        """Σ_i Σ_d log N(Δ[i,d]; mean[i,d], var[i,d]) under `predict`."""
        if not isinstance(data, Transitions):  # an AttributeError on .states
            raise ValueError(
                f"data: expected hipmdp.Transitions, got {type(data).__name__}"
            )
        mean, var = self.predict(data.states, data.actions)
        return gaussian_loglik(data.deltas, mean, var)


def fit_gp_baseline(
    data: Transitions,
    *,
    rng: np.random.Generator,
    n_actions: int | None = None,
    hyper: HyperSet | None = None,
    n_max: int = 2000,
    n_hyper: int = 500,
    keep: Array | None = None,
    name: str = "gp",
    periodic: tuple[int, ...] | None = None,
) -> GPBaseline:
    """Condition one GP per (a, d) on `data`, pooled over instances.

    n_actions: A (default data.n_actions); hyper: fixed hyperparameters, else fitted
    per (a, d) on at most n_hyper of the transitions used; n_max: at most this many
    transitions per action (subset of data); keep: bool (N,), transitions always kept;
    periodic: the angle dimensions the kernels treat as periodic (`hipmdp.kernels`;
    default: `hyper.periodic` if hyper is given, else none).
    """
    if not isinstance(data, Transitions):
        raise ValueError(
            f"data: expected hipmdp.Transitions, got {type(data).__name__}"
        )
    if not isinstance(rng, np.random.Generator):
        raise ValueError(
            f"rng: expected numpy.random.Generator, got {type(rng).__name__}"
        )
    check_integer("n_max", n_max, 1)
    check_integer("n_hyper", n_hyper, 2)
    if n_actions is not None:
        check_integer("n_actions", n_actions, 1)
    A = data.n_actions if n_actions is None else int(n_actions)
    D = data.state_dim
    if data.n_actions > A:
        raise ValueError(f"n_actions: expected >= {data.n_actions} (data), got {A}")
    if hyper is not None and hyper.signal_var.shape != (A, D):
        raise ValueError(
            f"hyper: expected (A, D) = ({A}, {D}), got {hyper.signal_var.shape}"
        )
    if periodic is None:
        periodic = () if hyper is None else hyper.periodic
    periodic = check_periodic(periodic, D)
    if hyper is not None and hyper.periodic != periodic:
        raise ValueError(
            f"periodic: expected hyper.periodic = {hyper.periodic} (hyper is given), "
            f"got {periodic}"
        )
    if keep is None:
        keep = np.zeros(len(data), dtype=bool)
    else:
        keep = np.asarray(keep)
        if keep.shape != (len(data),) or keep.dtype != bool:
            raise ValueError(
                f"keep: expected a bool array of shape ({len(data)},), got "
                f"{keep.dtype} {keep.shape}"
            )
    deltas = data.deltas
    ell, sf2, sn2 = np.ones((A, D, D)), np.ones((A, D)), np.ones((A, D))
    rows = []
    for a in range(A):
        kept = np.flatnonzero((data.actions == a) & keep)
        rest = np.flatnonzero((data.actions == a) & ~keep)
        idx = np.sort(
            np.concatenate(
                [kept, rest[subsample(len(rest), max(n_max - len(kept), 0), rng=rng)]]
            )
        )
        rows.append(idx)
        if hyper is None:
            if len(idx) < 2:
                raise ValueError(
                    f"data: action {a} has {len(idx)} transitions; at least 2 are "
                    "needed to fit hyperparameters (or pass hyper=)"
                )
            sub = idx[subsample(len(idx), n_hyper, rng=rng)]
            for d in range(D):
                h = fit_hyperparameters([(data.states[sub], deltas[sub, d])], periodic)
                ell[a, d], sf2[a, d], sn2[a, d] = h[:3]
    if hyper is None:
        hyper = HyperSet(ell, sf2, sn2, periodic)
    posteriors = tuple(
        tuple(
            condition(data.states[idx], deltas[idx, d], hyper.get(a, d))
            if len(idx)
            else None
            for d in range(D)
        )
        for a, idx in enumerate(rows)
    )
    return GPBaseline(posteriors=posteriors, hyper=hyper, name=name)


def _own(kwargs: dict, *names: str) -> None:
    """Refuse ``kwargs`` that a named baseline sets itself (were a duplicate
    keyword TypeError)."""
    taken = sorted(set(names) & set(kwargs))
    if taken:
        raise ValueError(
            f"{', '.join(taken)}: set by this baseline; call fit_gp_baseline to "
            "choose it"
        )


def batch_only(batch: Transitions, *, rng: np.random.Generator, **kwargs) -> GPBaseline:
    """The average model: one GP on all batch data (kwargs: see fit_gp_baseline,
    but `name`)."""
    _own(kwargs, "name")
    return fit_gp_baseline(batch, rng=rng, name="batch only", **kwargs)


def train_only(train: Transitions, *, rng: np.random.Generator, **kwargs) -> GPBaseline:
    """One GP on the new instance's transitions only (kwargs: see
    fit_gp_baseline, but `name`)."""
    _own(kwargs, "name")
    return fit_gp_baseline(train, rng=rng, name="train only", **kwargs)


def batch_plus_train(
    batch: Transitions, train: Transitions, *, rng: np.random.Generator, **kwargs
) -> GPBaseline:
    """One GP on batch and train data together; every train transition is kept
    (kwargs: see fit_gp_baseline, but `name` and `keep`)."""
    _own(kwargs, "name", "keep")
    if not isinstance(train, Transitions):
        raise ValueError(f"train: expected hipmdp.Transitions, got {type(train)}")
    # the two passed the other way round kept the whole batch: a GP on all of it
    if train.instance_ids.size > 1:
        raise ValueError(
            f"train: expected one new instance's transitions, got instances "
            f"{train.instance_ids.tolist()[:10]} (batch_plus_train takes (batch, "
            "train))"
        )
    both = Transitions.concatenate([batch, train])
    keep = np.concatenate([np.zeros(len(batch), bool), np.ones(len(train), bool)])
    return fit_gp_baseline(both, rng=rng, keep=keep, name="batch + train", **kwargs)
