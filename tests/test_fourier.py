"""The Fourier basis: feature count, range, and the direct formula."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hipmdp.fourier import FourierBasis


@pytest.mark.parametrize(("order", "dim"), [(0, 3), (3, 4), (5, 4), (2, 1)])
def test_feature_count_is_order_plus_one_to_the_d(order: int, dim: int) -> None:
    basis = FourierBasis(order, -np.ones(dim), np.ones(dim))
    assert basis.n_features == (order + 1) ** dim
    assert basis.coefficients.shape == ((order + 1) ** dim, dim)
    # every integer vector in {0..n}^D exactly once
    assert len({tuple(c) for c in basis.coefficients}) == basis.n_features
    assert basis(np.zeros(dim)).shape == ((order + 1) ** dim,)


def test_features_equal_direct_formula_one_feature_at_a_time() -> None:
    """φ_i(s) = cos(π c_i · x), x = clip((s - low)/(high - low), 0, 1), written out
    with scalar loops over every coefficient vector of {0..3}^3."""
    rng = np.random.default_rng(0)
    low, high = np.array([-2.0, 0.0, -5.0]), np.array([2.0, 1.0, 15.0])
    basis = FourierBasis(3, low, high)
    # states inside and outside the bounds (outside ones are clipped)
    states = rng.uniform(low - 1.0, high + 1.0, size=(7, 3))
    got = basis(states)
    for n, s in enumerate(states):
        x = [min(max((s[d] - low[d]) / (high[d] - low[d]), 0.0), 1.0) for d in range(3)]
        for i, c in enumerate(itertools.product(range(4), repeat=3)):
            expected = np.cos(np.pi * sum(cj * xj for cj, xj in zip(c, x, strict=True)))
            assert got[n, i] == pytest.approx(expected, abs=1e-12)
    # one state at a time gives the batch rows
    np.testing.assert_allclose(basis(states[2]), got[2], atol=1e-14)


def test_features_lie_in_unit_interval_and_constant_feature_is_one() -> None:
    rng = np.random.default_rng(1)
    basis = FourierBasis(5, np.full(4, -1.0), np.full(4, 1.0))
    phi = basis(rng.normal(scale=3.0, size=(200, 4)))
    assert np.all(np.abs(phi) <= 1.0)
    np.testing.assert_array_equal(phi[:, 0], 1.0)
    # clipping: a state far outside the box has the features of the nearest corner
    np.testing.assert_allclose(basis(np.full(4, 50.0)), basis(np.ones(4)))


def test_step_scale_is_inverse_coefficient_norm() -> None:
    basis = FourierBasis(2, np.zeros(2), np.ones(2))
    for c, scale in zip(basis.coefficients, basis.step_scale, strict=True):
        norm = np.sqrt(np.sum(c.astype(float) ** 2))
        assert scale == pytest.approx(1.0 if norm == 0 else 1.0 / norm)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"order": -1, "low": [0.0], "high": [1.0]}, "order"),
        ({"order": True, "low": [0.0], "high": [1.0]}, "order: expected an integer"),
        ({"order": 2.0, "low": [0.0], "high": [1.0]}, "order: expected an integer"),
        ({"order": 2, "low": [0.0, 0.0], "high": [1.0]}, "low, high"),
        ({"order": 2, "low": [1.0], "high": [1.0]}, "high"),
        ({"order": 2, "low": [np.nan], "high": [1.0]}, "low, high"),
        # an infinite high gave 1 / (high - low) = 0: every x = 0, φ constant
        ({"order": 2, "low": [0.0], "high": [np.inf]}, "low, high: expected finite"),
        # one bad dimension among good ones
        ({"order": 2, "low": [0.0, 1.0], "high": [1.0, 1.0]}, "high: expected high >"),
        # 2-D bounds were taken with D = their size; no dimensions gave F = 1
        ({"order": 2, "low": [[0.0, 0.0]], "high": [[1.0, 1.0]]}, "low, high: exp"),
        ({"order": 2, "low": [], "high": []}, "low, high: expected two 1-D arrays"),
    ],
)
def test_bad_input_raises_naming_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        FourierBasis(**kwargs)


def test_wrong_state_shape_raises() -> None:
    basis = FourierBasis(1, np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="states"):
        basis(np.zeros(3))
    # a 3-D batch gave 3-D features
    with pytest.raises(ValueError, match=r"states: expected shape \(2,\) or \(N, 2\)"):
        basis(np.zeros((1, 1, 2)))


def test_non_finite_states_raise() -> None:
    """Clipping would turn inf into a box edge and NaN into NaN features."""
    basis = FourierBasis(1, np.zeros(2), np.ones(2))
    for bad in (np.nan, np.inf):
        with pytest.raises(
            ValueError, match=r"states: non-finite value at index \(1, 0\)"
        ):
            basis(np.array([[0.5, 0.5], [bad, 0.5]]))
    # the first non-finite value is named
    with pytest.raises(ValueError, match=r"index \(0, 1\)"):
        basis(np.array([[0.5, np.nan], [np.inf, 0.5]]))


@pytest.mark.parametrize(
    ("order", "dim"), [(np.int64(2**32 - 1), 2), (np.int32(255), 4), (np.uint8(255), 3)]
)
def test_feature_count_guard_holds_for_numpy_integer_orders(order, dim) -> None:
    """(order + 1)^D in the order's own dtype wrapped to 0 (or a small number),
    passed the 1e6 guard and then ran out of memory building the coefficients."""
    with pytest.raises(ValueError, match=r"order: \(order \+ 1\)\^D = \d+ features"):
        FourierBasis(order, np.zeros(dim), np.ones(dim))


def test_feature_count_guard_is_at_one_million() -> None:
    """(order + 1)^D = 10^6 features is allowed, 1001^2 and 2^21 are not."""
    assert FourierBasis(999, np.zeros(2), np.ones(2)).n_features == 1_000_000
    for order, dim in [(1000, 2), (1, 21)]:
        with pytest.raises(ValueError, match=r"order: \(order \+ 1\)\^D = \d+"):
            FourierBasis(order, np.zeros(dim), np.ones(dim))


def test_the_basis_owns_read_only_arrays() -> None:
    """The bounds are copied (the caller's arrays stay writable and changing them
    does not move the basis) and the basis's arrays cannot be changed in place."""
    low, high = np.zeros(2), np.ones(2)
    basis = FourierBasis(2, low, high)
    low[:] = 0.5
    np.testing.assert_array_equal(basis.low, 0.0)
    np.testing.assert_array_equal(basis.normalise(np.array([0.25, 0.5])), [0.25, 0.5])
    for name in ("low", "high", "coefficients", "step_scale"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(basis, name)[0] = 7
