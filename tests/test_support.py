"""Support selection: greedy max-error property, reproducibility."""

from __future__ import annotations

import numpy as np
import pytest

from hipmdp.gp import HyperSet
from hipmdp.support import greedy_support, greedy_support_dense, select_support


def _hyper():
    ell = np.array([[[0.5, 1.0], [1.5, 0.7]], [[1.0, 1.0], [0.4, 2.0]]])
    return HyperSet(ell, np.array([[1.0, 2.0], [0.5, 1.0]]), np.full((2, 2), 1e-3))


def _kernels(h):
    return [
        (h.lengthscales[a, d], h.signal_var[a, d], h.noise_var[a, d])
        for a in range(2)
        for d in range(2)
    ]


def test_incremental_matches_dense_reference():
    # The dense reference recomputes every error from scratch and takes the argmax,
    # so agreement shows each chosen point had the largest current error.
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, size=(120, 2))
    fast = greedy_support(X, _kernels(_hyper()), 25)
    dense = greedy_support_dense(X, _kernels(_hyper()), 25)
    np.testing.assert_array_equal(fast.index, dense.index)
    np.testing.assert_allclose(fast.errors, dense.errors, atol=1e-9)
    assert np.all(np.diff(fast.errors) <= 1e-9)  # the maximum error never increases


def test_reproducible_from_seed_and_subsampled():
    rng = np.random.default_rng(1)
    S = rng.normal(size=(500, 2))
    a = select_support(S, _hyper(), 20, n_candidates=100, rng=np.random.default_rng(5))
    b = select_support(S, _hyper(), 20, n_candidates=100, rng=np.random.default_rng(5))
    c = select_support(S, _hyper(), 20, n_candidates=100, rng=np.random.default_rng(6))
    np.testing.assert_array_equal(a.index, b.index)
    assert not np.array_equal(a.index, c.index)
    np.testing.assert_array_equal(a.points, S[a.index])
    assert len(np.unique(a.index)) == 20


def test_each_tasks_kernel_is_its_own_scales_and_variances():
    """select_support's task (a, d) has ℓ[a,d], σ_f²[a,d] and σ²[a,d] together,
    as HyperSet.get gives them: with A = 3 actions and D = 2 dimensions (not
    square, where a transposed index reads another task's) and a noise of its
    own per task, it picks what the dense reference picks with those kernels."""
    rng = np.random.default_rng(6)
    A, D = 3, 2
    hyper = HyperSet(
        rng.uniform(0.3, 2.0, (A, D, D)),
        rng.uniform(0.5, 2.0, (A, D)),
        rng.uniform(0.01, 0.5, (A, D)),
    )
    X = rng.uniform(-2, 2, size=(80, D))
    got = select_support(X, hyper, 15, n_candidates=80, rng=np.random.default_rng(0))
    tasks = [hyper.get(a, d) for a in range(A) for d in range(D)]
    kernels = [(h.lengthscales, h.signal_var, h.noise_var) for h in tasks]
    dense = greedy_support_dense(X, kernels, 15)
    np.testing.assert_array_equal(got.index, dense.index)
    np.testing.assert_allclose(got.errors, dense.errors, atol=1e-9)


def test_too_many_support_points_raises():
    S = np.repeat(np.arange(5.0)[:, None], 2, axis=1)
    S = np.concatenate([S, S])  # 5 distinct states
    with pytest.raises(ValueError, match="n_support"):
        select_support(S, _hyper(), 6, n_candidates=100, rng=np.random.default_rng(0))


@pytest.mark.parametrize(
    ("states", "kwargs", "match"),
    [
        # a narrower state was fitted with the first length scales, silently
        (np.zeros((10, 1)), {}, r"states: expected shape \(N, 2\)"),
        (np.zeros((10, 3)), {}, r"states: expected shape \(N, 2\)"),
        (np.zeros(10), {}, r"states: expected shape \(N, 2\)"),
        # a NaN row was chosen as a support point
        (np.vstack([np.eye(2), [[np.nan, 0.0]]]), {}, "states: expected finite"),
        (np.eye(2), {"n_candidates": 0}, "n_candidates: expected >= 1"),
        (np.eye(2), {"m": True}, r"n_support \(m\): expected an integer"),
        (np.eye(2), {"rng": 0}, "rng: expected a numpy Generator"),
    ],
)
def test_select_support_refuses_bad_input(states, kwargs, match):
    args = {"m": 1, "n_candidates": 10, "rng": np.random.default_rng(0)} | kwargs
    with pytest.raises(ValueError, match=match):
        select_support(states, _hyper(), args.pop("m"), **args)


def test_periodic_incremental_matches_dense_reference():
    rng = np.random.default_rng(2)
    X = rng.uniform(-np.pi, np.pi, size=(120, 2))
    kernels = _kernels(_hyper())
    fast = greedy_support(X, kernels, 25, periodic=(1,))
    dense = greedy_support_dense(X, kernels, 25, periodic=(1,))
    np.testing.assert_array_equal(fast.index, dense.index)
    np.testing.assert_allclose(fast.errors, dense.errors, atol=1e-9)
    assert not np.array_equal(fast.index, greedy_support(X, kernels, 25).index)
    # select_support takes the periodic dimensions from the hyperparameters
    h = _hyper()
    periodic = HyperSet(h.lengthscales, h.signal_var, h.noise_var, periodic=(1,))
    picks = [
        select_support(X, hyper, 20, n_candidates=120, rng=np.random.default_rng(3))
        for hyper in (periodic, h)
    ]
    np.testing.assert_array_equal(
        picks[0].index, greedy_support(X, kernels, 20, periodic=(1,)).index
    )
    assert not np.array_equal(picks[0].index, picks[1].index)


def test_greedy_support_takes_1_to_n_distinct_points():
    """Each candidate at most once, even where a chosen point's remaining error
    ties with a near-duplicate's (both ~σ_n², argmax's lowest index is the
    chosen one); m outside [1, n] is refused, not an empty or repeated set."""
    X = np.array([[0.0, 0.0], [1e-9, 0.0], [5.0, 5.0]])
    kernels = _kernels(_hyper())
    sup = greedy_support(X, kernels, 3)
    assert sorted(sup.index.tolist()) == [0, 1, 2]
    np.testing.assert_array_equal(sup.index, greedy_support_dense(X, kernels, 3).index)
    for m in (0, 4):
        with pytest.raises(ValueError, match=r"m: expected 1 <= m <= 3"):
            greedy_support(X, kernels, m)


def test_concentrated_angles_are_not_centred(monkeypatch):
    """A pole near upright (angle spread 0.05 about 0): the angle's cos column
    lies hundreds of its spreads from 0, but the kernels never centre cos/sin
    columns, so states near 0 are computed as without centring, bit for bit.
    greedy_support embedded the states itself and passed them on as plain
    inputs, which were then centred (errors off by ~1e-13)."""
    from hipmdp import kernels

    rng = np.random.default_rng(4)
    X = np.c_[rng.uniform(-2, 2, size=300), 0.05 * rng.normal(size=300)]
    kernels_ = _kernels(_hyper())
    got = greedy_support(X, kernels_, 40, periodic=(1,))
    monkeypatch.setattr(kernels, "CENTRE_RATIO", np.inf)  # never centre
    plain = greedy_support(X, kernels_, 40, periodic=(1,))
    np.testing.assert_array_equal(got.index, plain.index)
    np.testing.assert_array_equal(got.errors, plain.errors)


@pytest.mark.parametrize("periodic", [(), (1,)])
def test_states_far_from_0_select_as_near_0(periodic):
    """A plain dimension offset by 1e4 (spread ~1): its candidates are centred
    once, so the errors are those of the same states near 0 and the dense
    reference's, to round-off."""
    rng = np.random.default_rng(5)
    X = rng.uniform(-2, 2, size=(150, 2))
    far = X + [1e4, 0.0]
    kernels_ = _kernels(_hyper())
    near = greedy_support(X, kernels_, 25, periodic=periodic)
    got = greedy_support(far, kernels_, 25, periodic=periodic)
    dense = greedy_support_dense(far, kernels_, 25, periodic=periodic)
    np.testing.assert_array_equal(got.index, near.index)
    np.testing.assert_array_equal(got.index, dense.index)
    np.testing.assert_allclose(got.errors, near.errors, atol=1e-9)
