"""Kernel values and analytic gradients vs the definition and finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from hipmdp import kernels
from hipmdp.kernels import KernelMeans, se_kernel, se_kernel_grad


def test_kernel_matches_definition():
    rng = np.random.default_rng(0)
    X1, X2 = rng.normal(size=(5, 3)), rng.normal(size=(4, 3))
    ell, sf2 = np.array([0.5, 1.0, 2.0]), 1.7
    K = se_kernel(X1, X2, ell, sf2)
    for i in range(5):
        for j in range(4):
            r2 = np.sum((X1[i] - X2[j]) ** 2 / ell**2)
            assert K[i, j] == pytest.approx(sf2 * np.exp(-0.5 * r2), rel=1e-12)


def test_kernel_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(6, 3))
    log_params = np.array([np.log(0.7), np.log(1.3), np.log(2.1), np.log(0.9)])

    def kern(p):
        return se_kernel(X, X, np.exp(p[:3]), np.exp(p[3]))

    dK = se_kernel_grad(X, np.exp(log_params[:3]), np.exp(log_params[3])).dK
    eps = 1e-6
    for i in range(4):
        e = np.zeros(4)
        e[i] = eps
        fd = (kern(log_params + e) - kern(log_params - e)) / (2 * eps)
        # central differences: error O(eps²) ~ 1e-12 plus round-off ~ 1e-16/eps
        np.testing.assert_allclose(dK[i], fd, atol=1e-8)


def test_bad_parameters_raise():
    X = np.zeros((2, 2))
    with pytest.raises(ValueError, match="lengthscales"):
        se_kernel(X, X, np.array([1.0]), 1.0)
    with pytest.raises(ValueError, match="lengthscales"):
        se_kernel(X, X, np.array([1.0, -1.0]), 1.0)
    with pytest.raises(ValueError, match="lengthscales"):  # a division by 0
        se_kernel(X, X, np.array([1.0, 0.0]), 1.0)
    for sf2 in (0.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="signal_var"):
            se_kernel(X, X, np.array([1.0, 1.0]), sf2)
    with pytest.raises(ValueError, match="dimension"):
        se_kernel(X, np.zeros((2, 3)), np.array([1.0, 1.0]), 1.0)


def test_scaled_distances_are_never_negative():
    """The expanded form |a|² + |b|² - 2 a·b of a point's distance to itself is
    round-off of either sign; it is clipped at 0."""
    rng = np.random.default_rng(0)
    X = rng.normal(size=(40, 3)) * [1.0, 3.0, 0.5]
    ell = np.array([0.1, 0.2, 0.3])
    d2 = kernels.scaled_sqdist(X, X, ell)
    assert np.all(d2 >= 0.0)
    direct = (((X[:, None] - X[None]) / ell) ** 2).sum(-1)
    np.testing.assert_allclose(d2, direct, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("offset", [0.0, 30.0, 1e3, 1e6])
def test_distances_do_not_depend_on_where_the_inputs_lie(offset):
    """Inputs of spread ~0.3 offset from 0 (an altitude in metres, a position on a
    long track): the expanded form alone lost ~offset²/0.3² of the distances'
    relative precision (at 1e3, r² off by ~1e-4 of the 1e-2..10 the direct
    formula gives; a user's fit failed at 3e3). Centred first, every distance
    is the direct formula's to 1e-12, and the angle columns (chords) too."""
    rng = np.random.default_rng(4)
    X1 = 0.3 * rng.normal(size=(30, 3)) + [offset, -offset, 0.0]
    X2 = 0.3 * rng.normal(size=(20, 3)) + [offset, -offset, 0.0]
    ell = np.array([0.2, 0.5, 0.7])
    for periodic in ((), (2,)):
        delta = X1[:, None] - X2[None]
        if periodic:
            delta[..., 2] = 2 * np.sin(delta[..., 2] / 2)
        direct = ((delta / ell) ** 2).sum(-1)
        got = kernels.scaled_sqdist(X1, X2, ell, periodic)
        np.testing.assert_allclose(got, direct, rtol=1e-12, atol=1e-12)
        # one row in X2 is not centred (no spread to judge by), as KernelMeans
        # leaves one input: a query's distances do not depend on the others,
        # bit for bit where the others change around it (the same shapes: the
        # same BLAS kernel; a query alone, a 1 x 1 product, can take another
        # summation order, 2e-9 apart at offset 1e3 on one machine's OpenBLAS)
        one = kernels.scaled_sqdist(X1, X2[:1], ell, periodic)
        others = X1 + 3.0 * (np.arange(30) != 3)[:, None]  # a mean 3 further
        moved = kernels.scaled_sqdist(others, X2[:1], ell, periodic)
        np.testing.assert_array_equal(moved[3], one[3])
    coef = [rng.normal(size=(1, 20))]
    means = KernelMeans([X2], ell[None, None], np.ones((1, 1)), coef)
    want = np.exp(-0.5 * (((X1[:, None] - X2[None]) / ell) ** 2).sum(-1)) @ coef[0][0]
    got = means(X1, np.zeros(30, dtype=int))[:, 0]
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


def test_inputs_near_zero_are_not_centred():
    """Every experiment's states lie within a few standard deviations of 0: their
    distances are the plain expanded form, bit for bit, so no reported number
    moves with the centring."""
    rng = np.random.default_rng(5)
    X1 = rng.normal(size=(30, 3)) + [30.0, -2.0, 0.0]  # the queries do not decide
    X2 = rng.normal(size=(20, 3)) + [3.0, -2.0, 0.0]  # 3 sd from 0
    ell = np.array([0.2, 0.5, 0.7])
    A, B = X1 / ell, X2 / ell
    plain = (A * A).sum(1)[:, None] + (B * B).sum(1)[None, :] - 2.0 * (A @ B.T)
    got = kernels.scaled_sqdist(X1, X2, ell)
    np.testing.assert_array_equal(got, np.maximum(plain, 0.0))
    assert kernels.centre(X2, np.arange(3)) is None
    far = X2 + [0.0, 9.0 * X2[:, 1].std() - X2[:, 1].mean(), 0.0]  # 9 sd from 0
    np.testing.assert_allclose(
        kernels.centre(far, np.arange(3)), [0, far[:, 1].mean(), 0]
    )
    # an angle's cos/sin columns are never centred; nor is a set of one row
    assert kernels.centre(np.full((5, 1), 0.99), np.array([0]), periodic=(0,)) is None
    assert kernels.centre(far[:1], np.arange(3)) is None


def test_a_column_is_centred_beyond_8_of_its_standard_deviations():
    """The documented threshold (README, `centre`): a plain column whose mean
    lies more than 8 standard deviations from 0, on either side, is centred on
    its mean; one at 7.9 is not. A column of mean 0 and sd 1 (to round-off),
    moved by 7.9 or 8.1: the margin is far beyond round-off, and beyond the
    choice of sd's denominator (n or n - 1: a factor 1.0025 at 200 rows)."""
    x = np.random.default_rng(7).normal(size=(200, 2))
    x = (x - x.mean(0)) / x.std(0)
    col = np.arange(2)
    for offset in (7.9, -7.9):
        assert kernels.centre(x + [offset, 0.0], col) is None
    for offset in (8.1, -8.1):
        np.testing.assert_allclose(
            kernels.centre(x + [offset, 0.0], col), [offset, 0.0], rtol=1e-12
        )


def test_angles_are_told_from_plain_columns_by_their_input_dimension():
    """With dimension 0 an angle, the embedding's columns are (x_1, cos x_0,
    sin x_0): the far plain column is the first, which an index taken for a
    dimension (0) would call the angle's. Angles of spread 0.3 around 0 (cos x_0
    about 17 of its spreads from 0) and x_1 1000 from 0 (spread 0.3): x_1 is
    centred, the angle's columns are not, and the distances are the direct
    formula's."""
    rng = np.random.default_rng(8)
    X1, X2 = (
        np.column_stack([0.3 * rng.normal(size=n), 1e3 + 0.3 * rng.normal(size=n)])
        for n in (30, 20)
    )
    E2, col = kernels.embed(X2, (0,))
    np.testing.assert_array_equal(col, [1, 0, 0])
    np.testing.assert_allclose(
        kernels.centre(E2, col, (0,)), [X2[:, 1].mean(), 0.0, 0.0], rtol=1e-12
    )
    ell = np.array([0.7, 0.5])
    delta = X1[:, None] - X2[None]
    delta[..., 0] = 2 * np.sin(delta[..., 0] / 2)
    np.testing.assert_allclose(
        kernels.scaled_sqdist(X1, X2, ell, (0,)),
        ((delta / ell) ** 2).sum(-1),
        rtol=1e-12,
        atol=1e-12,
    )


def test_kernel_means_are_the_per_output_kernel_sums(monkeypatch):
    # A = 3 actions (the last with no inputs), E = 2 outputs, D = 3; against one
    # se_kernel call per (action, output), row by row.
    rng = np.random.default_rng(3)
    inputs = [rng.normal(size=(7, 3)), rng.normal(size=(4, 3)), np.zeros((0, 3))]
    ell = rng.uniform(0.3, 2.0, size=(3, 2, 3))
    sf2 = rng.uniform(0.5, 2.0, size=(3, 2))
    coef = [rng.normal(size=(2, len(x))) for x in inputs]
    means = KernelMeans(inputs, ell, sf2, coef)
    states = rng.normal(size=(9, 3))
    actions = np.array([0, 1, 2, 1, 0, 0, 2, 1, 1])
    got = means(states, actions)
    for i, a in enumerate(actions):
        for d in range(2):
            k = se_kernel(states[i : i + 1], inputs[a], ell[a, d], sf2[a, d])
            want = (k @ coef[a][d])[0] if len(inputs[a]) else 0.0
            assert got[i, d] == pytest.approx(want, rel=1e-12, abs=1e-14)
    # one action for every row takes the single-group path: the same numbers
    ones = np.ones(9, dtype=int)
    np.testing.assert_array_equal(means(states, ones)[actions == 1], got[actions == 1])
    assert means(np.zeros((0, 3)), np.zeros(0, dtype=int)).shape == (0, 2)
    # large batches are evaluated in chunks of rows: the same numbers
    for chunk in (10, 30):  # 2 outputs x 7 inputs: 1 row, then 2 (and a part)
        monkeypatch.setattr(kernels, "_CHUNK", chunk)
        np.testing.assert_allclose(means(states, actions), got, rtol=1e-14, atol=1e-15)
        chunked = means(states, ones)[actions == 1]
        np.testing.assert_allclose(chunked, got[actions == 1], rtol=1e-14, atol=1e-15)


def test_kernel_means_reject_bad_input():
    x, ell, sf2 = np.zeros((2, 3)), np.ones((1, 2, 3)), np.ones((1, 2))
    with pytest.raises(
        ValueError, match=r"coefficients\[0\]: expected finite .*\(2, 2\)"
    ):
        KernelMeans([x], ell, sf2, [np.zeros((2, 3))])
    with pytest.raises(ValueError, match=r"coefficients\[0\]: .* with non-finite"):
        KernelMeans([x], ell, sf2, [np.full((2, 2), np.nan)])
    # inputs were reshaped to (-1, D): six numbers of shape (3, 2) read as (2, 3)
    with pytest.raises(
        ValueError, match=r"inputs\[0\]: expected .*\(n, 3\), got shape \(3, 2\)"
    ):
        KernelMeans([np.zeros((3, 2))], ell, sf2, [np.zeros((2, 2))])
    with pytest.raises(ValueError, match=r"inputs\[0\]: .* with non-finite"):
        KernelMeans([np.full((2, 3), np.inf)], ell, sf2, [np.zeros((2, 2))])
    with pytest.raises(ValueError, match="lengthscales"):
        KernelMeans([x], -ell, sf2, [np.zeros((2, 2))])
    with pytest.raises(ValueError, match="expected 1 actions"):
        KernelMeans([x, x], ell, sf2, [np.zeros((2, 2))])
    with pytest.raises(ValueError, match="expected 1 actions, got 1 and 2"):
        KernelMeans([x], ell, sf2, [np.zeros((2, 2))] * 2)
    # one σ_f² for both outputs: (1, 1) broadcast against (1, 2)
    with pytest.raises(ValueError, match=r"signal_var: expected shapes .* \(1, 1\)"):
        KernelMeans([x], ell, sf2[:, :1], [np.zeros((2, 2))])
    means = KernelMeans([x], ell, sf2, [np.zeros((2, 2))])
    with pytest.raises(ValueError, match="actions"):
        means(np.zeros((1, 3)), np.array([1]))
    with pytest.raises(ValueError, match="states"):
        means(np.full((1, 3), np.nan), np.array([0]))


# -- periodic dimensions ----------------------------------------------------------


def test_periodic_kernel_is_the_chord_definition_and_the_embedding_kernel():
    # dims 0 and 2 periodic: δ = 2 sin(Δ/2) there, the plain difference on dim 1
    rng = np.random.default_rng(4)
    X1, X2 = rng.uniform(-4, 4, size=(5, 3)), rng.uniform(-4, 4, size=(4, 3))
    ell, sf2 = np.array([0.5, 1.0, 2.0]), 1.7
    K = se_kernel(X1, X2, ell, sf2, periodic=(2, 0))
    for i in range(5):
        for j in range(4):
            delta = X1[i] - X2[j]
            delta[[0, 2]] = 2 * np.sin(delta[[0, 2]] / 2)
            r2 = np.sum(delta**2 / ell**2)
            assert K[i, j] == pytest.approx(sf2 * np.exp(-0.5 * r2), rel=1e-12)

    # the same as the plain kernel of (cos, sin) columns, each with its angle's ℓ
    def lift(X):
        return np.column_stack(
            [
                np.cos(X[:, 0]),
                np.sin(X[:, 0]),
                X[:, 1],
                np.cos(X[:, 2]),
                np.sin(X[:, 2]),
            ]
        )

    ell5 = ell[[0, 0, 1, 2, 2]]
    np.testing.assert_allclose(K, se_kernel(lift(X1), lift(X2), ell5, sf2), rtol=1e-12)
    # 2π shifts of an angle change nothing; of the plain dimension they do
    shift = np.zeros(3)
    shift[[0, 2]] = 2 * np.pi * np.array([1, -3])
    np.testing.assert_allclose(
        se_kernel(X1 + shift, X2, ell, sf2, periodic=(0, 2)), K, rtol=1e-10
    )
    assert not np.allclose(
        se_kernel(X1 + [0, 2 * np.pi, 0], X2, ell, sf2, periodic=(0, 2)), K
    )
    assert not np.allclose(se_kernel(X1, X2, ell, sf2), K)  # the option matters


def test_periodic_kernel_gradient_matches_finite_differences():
    rng = np.random.default_rng(5)
    X = rng.uniform(-4, 4, size=(6, 3))
    log_params = np.array([np.log(0.7), np.log(1.3), np.log(2.1), np.log(0.9)])

    def kern(p):
        return se_kernel(X, X, np.exp(p[:3]), np.exp(p[3]), periodic=(1,))

    kg = se_kernel_grad(X, np.exp(log_params[:3]), np.exp(log_params[3]), (1,))
    np.testing.assert_allclose(kg.K, kern(log_params), rtol=1e-14)
    eps = 1e-6
    for i in range(4):
        e = np.zeros(4)
        e[i] = eps
        fd = (kern(log_params + e) - kern(log_params - e)) / (2 * eps)
        np.testing.assert_allclose(kg.dK[i], fd, atol=1e-8)


def test_periodic_kernel_means_are_the_per_output_kernel_sums():
    rng = np.random.default_rng(6)
    inputs = [rng.uniform(-3, 3, size=(7, 3)), rng.uniform(-3, 3, size=(4, 3))]
    ell = rng.uniform(0.3, 2.0, size=(2, 2, 3))
    sf2 = rng.uniform(0.5, 2.0, size=(2, 2))
    coef = [rng.normal(size=(2, len(x))) for x in inputs]
    means = KernelMeans(inputs, ell, sf2, coef, periodic=(0, 1))
    states = rng.uniform(-3, 3, size=(9, 3))
    actions = np.array([0, 1, 1, 0, 1, 0, 0, 1, 1])
    got = means(states, actions)
    for i, a in enumerate(actions):
        for d in range(2):
            k = se_kernel(states[i : i + 1], inputs[a], ell[a, d], sf2[a, d], (0, 1))
            assert got[i, d] == pytest.approx((k @ coef[a][d])[0], rel=1e-12)
    plain = KernelMeans(inputs, ell, sf2, coef)(states, actions)
    assert not np.allclose(plain, got)


@pytest.mark.parametrize(
    ("periodic", "match"),
    [((3,), r"\[0, 3\)"), ((0, 0), "distinct"), ((-1,), r"\[0, 3\)"), (1, "sequence"),
     # int() truncated these: 1.5 was dimension 1, "01" dimensions 0 and 1
     ((1.5,), "integer"), ("01", "integer"), ((True,), "integer")],
)  # fmt: skip
def test_bad_periodic_dimensions_raise(periodic, match):
    assert kernels.check_periodic((2, 0), 3) == (0, 2)  # sorted
    assert kernels.check_periodic(np.array([1]), 3) == (1,)  # numpy integers
    X = np.zeros((2, 3))
    with pytest.raises(ValueError, match=f"periodic: expected.*{match}"):
        se_kernel(X, X, np.ones(3), 1.0, periodic=periodic)
    with pytest.raises(ValueError, match="periodic"):
        KernelMeans(
            [X], np.ones((1, 1, 3)), np.ones((1, 1)), [np.zeros((1, 2))], periodic
        )
