"""Instance distributions: the grid and its splits partition it, draws land where
each split says, the relative normal is the truncated normal (not clipped), and bad
ranges stop with a message."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from scipy import stats

from tasks._common import parameter_matrix
from tasks.acrobot import AcrobotParams
from tasks.cartpole import CartpoleParams
from tasks.distributions import MAX_GRID_POINTS, Distribution, draw, in_box

MASSES = {"link_mass_1": (0.6, 1.4), "link_mass_2": (0.8, 1.2)}


def dist(**kwargs):
    return Distribution(AcrobotParams, kwargs.pop("vary", MASSES), **kwargs)


def test_grid_splits_partition_the_grid_like_a_checkerboard():
    full = draw(dist(kind="grid", grid=5), None, rng=np.random.default_rng(0)).varied
    assert full.shape == (25, 2)
    np.testing.assert_allclose(full[:5, 1], np.linspace(0.8, 1.2, 5))  # last fastest
    axes = (np.linspace(0.6, 1.4, 5), np.linspace(0.8, 1.2, 5))
    np.testing.assert_array_equal(full, list(itertools.product(*axes)))
    parts = {
        split: draw(dist(kind="grid", grid=5, split=split), None, rng=None).varied
        for split in ("train", "interpolation", "extrapolation")
    }
    joined = np.concatenate(list(parts.values()))
    assert sorted(map(tuple, joined)) == sorted(map(tuple, full))  # a partition
    # Inner box: the central half, [0.8, 1.2] x [0.9, 1.1]: the 3 x 3 middle points.
    inner = dist(kind="grid", grid=5).inner_box()
    np.testing.assert_allclose(inner, [[0.8, 0.9], [1.2, 1.1]])
    assert len(parts["train"]) == 5 and len(parts["interpolation"]) == 4
    # Some points lie on the inner boundary: compare with a rounding tolerance.
    assert in_box(parts["train"], *inner, tol=1e-9).all()
    assert in_box(parts["interpolation"], *inner, tol=1e-9).all()
    assert not in_box(parts["extrapolation"], *inner, tol=1e-9).any()
    # Interpolation points sit between training points: the centre is training,
    # its four neighbours are held out.
    np.testing.assert_allclose(parts["train"][2], [1.0, 1.0])
    np.testing.assert_allclose(
        parts["interpolation"], [[0.8, 1.0], [1.0, 0.9], [1.0, 1.1], [1.2, 1.0]]
    )


@pytest.mark.parametrize("kind", ["uniform", "relative-normal"])
def test_random_splits_land_in_their_regions(kind):
    rng = np.random.default_rng(1)
    d = {s: dist(kind=kind, split=s, sigma=0.3) for s in ("train", "interpolation")}
    train = draw(d["train"], 500, rng=np.random.default_rng(2)).varied
    held_out = draw(d["interpolation"], 500, rng=np.random.default_rng(2)).varied
    outside = draw(dist(kind=kind, split="extrapolation", sigma=0.3), 500, rng=rng)
    inner = d["train"].inner_box()
    assert in_box(train, *inner).all() and in_box(held_out, *inner).all()
    assert not np.isin(held_out, train).any()  # same seed, yet other points
    assert not in_box(outside.varied, *inner).any()
    assert in_box(outside.varied, [0.6, 0.8], [1.4, 1.2]).all()
    # Every instance keeps the unvaried lengths nominal.
    np.testing.assert_array_equal(outside.values[:, 2:], 1.0)
    assert outside.params[0] == AcrobotParams(*outside.values[0])


@pytest.mark.parametrize("kind", ["uniform", "relative-normal"])
@pytest.mark.parametrize("split", ["all", "train", "interpolation", "extrapolation"])
def test_draws_follow_their_law_on_the_splits_region(kind, split):
    """Each parameter's law on the split's box (U[low, high], or N(θ₀, (σ θ₀)²)
    truncated to it, from scipy), independently, restricted to the split's
    region: the inner box [0.8, 1.2] x [0.9, 1.1] for train and interpolation,
    the outer [0.6, 1.4] x [0.8, 1.2] for all, the outer minus the inner for
    extrapolation. Counts in an 8 x 8 grid of equal cells of the box (the inner
    box is exactly the outer one's central 4 x 4) against the law's cell
    probabilities: Pearson's chi-square, false-alarm probability 1e-4. A share
    or a mean alone missed one u drawn for both coordinates (every point on the
    diagonal) and strips of the ring drawn one side at a time."""
    n, k = 4000, 8
    d = dist(kind=kind, split=split, sigma=0.3)
    points = draw(d, n, rng=np.random.default_rng(3)).varied
    inner = split in ("train", "interpolation")
    lows, highs = d.inner_box() if inner else (d.lows, d.highs)
    p = []  # per parameter: its law's probability of each of the k cells
    for lo, hi, mu in zip(lows, highs, d.nominal(), strict=True):
        edges = np.linspace(lo, hi, k + 1)
        if kind == "uniform":
            cdf = (edges - lo) / (hi - lo)
        else:
            s = d.sigma * mu
            cdf = stats.truncnorm.cdf(edges, (lo - mu) / s, (hi - mu) / s, mu, s)
        p.append(np.diff(cdf))
    share = np.outer(*p)
    region = np.ones((k, k), dtype=bool)
    if split == "extrapolation":
        region[2:6, 2:6] = False
    cell = np.clip(np.floor((points - lows) / (highs - lows) * k), 0, k - 1)
    counts = np.zeros((k, k))
    np.add.at(counts, tuple(cell.astype(int).T), 1)
    assert counts[~region].sum() == 0
    want = n * share[region] / share[region].sum()
    assert stats.chisquare(counts[region], want).pvalue > 1e-4


@pytest.mark.parametrize(
    ("low", "high", "sigma"),
    [
        (0.05, 0.3, 0.5),  # around the mean
        (0.15, 0.4, 0.5),  # wholly above it
        (1.0, 2.0, 0.2),  # 45 σ above it: Φ underflows
        (0.02, 0.09, 0.002),  # 50 σ below it
        # 40 σ below, 0.05 σ wide: Φ(a) / Φ(b) = 0.14 is not negligible there
        (0.092, 0.09201, 0.002),
    ],
)
def test_relative_normal_is_the_truncated_normal_around_the_nominal(low, high, sigma):
    """Pole mass ~ N(0.1, (σ · 0.1)²) truncated to [low, high]: sample mean and
    variance within 4 standard errors of scipy's truncated-normal moments, its
    law scipy's by Kolmogorov-Smirnov (false-alarm probability 1e-4), and no point
    stacked on a bound (clipping would put 16% on the lower one in the first
    case, 84% in the second, and all on the far one in the last two)."""
    d = Distribution(
        CartpoleParams, {"pole_mass": (low, high)}, kind="relative-normal", sigma=sigma
    )
    n = 4000
    x = draw(d, n, rng=np.random.default_rng(4)).varied[:, 0]
    s = sigma * 0.1
    law = stats.truncnorm((low - 0.1) / s, (high - 0.1) / s, loc=0.1, scale=s)
    assert abs(x.mean() - law.mean()) < 4 * law.std() / np.sqrt(n)
    # Var of the sample variance ≈ (μ₄ - σ⁴) / n; μ₄ from the sample (scipy's
    # integral is NaN this far out in the tail)
    mu4 = np.mean((x - x.mean()) ** 4)
    assert abs(x.var() - law.var()) < 4 * np.sqrt((mu4 - law.var() ** 2) / n)
    assert stats.kstest(x, law.cdf).pvalue > 1e-4
    assert x.min() > low and x.max() < high


class EndsOfU:
    """Stands in for the Generator: every `uniform` draw is one of `u`, in turn
    (the relative normal draws `u ~ U[0, 1)` once per point)."""

    def __init__(self, u):
        self.u = np.asarray(u)

    def uniform(self, size):
        return np.resize(self.u, size)


def test_relative_normal_draws_at_the_ends_of_u_stay_in_the_box():
    """u = 0 (and just above, which `Generator.uniform` can return) is the lower
    bound itself: pole mass ~ N(0.1, 0.01²) on [0.01, 2.0], whose inverse CDF
    at Φ(a), a = -9, gave 0.01 - 1.9e-17, outside it."""
    d = Distribution(CartpoleParams, {"pole_mass": (0.01, 2.0)}, kind="relative-normal")
    x = draw(d, 3, rng=EndsOfU([0.0, 5e-324, 1e-300])).varied[:, 0]
    assert np.all((x >= 0.01) & (x <= 2.0))
    np.testing.assert_allclose(x, 0.01, rtol=1e-12)


def test_same_rng_same_draws_and_a_degenerate_range_stays_put():
    a = draw(dist(kind="relative-normal"), 10, rng=np.random.default_rng(7)).values
    b = draw(dist(kind="relative-normal"), 10, rng=np.random.default_rng(7)).values
    np.testing.assert_array_equal(a, b)
    fixed = {"link_mass_1": (1.1, 1.1), "link_mass_2": (0.8, 1.2)}
    for kind in ("uniform", "relative-normal"):
        v = draw(dist(kind=kind, vary=fixed), 20, rng=np.random.default_rng(0)).varied
        np.testing.assert_array_equal(v[:, 0], 1.1)


@pytest.mark.parametrize("params_type", [AcrobotParams, CartpoleParams])
def test_values_are_every_field_of_every_instance_in_order(params_type):
    """`values` against the plain reference, `dataclasses.astuple` per row."""
    names = [f.name for f in dataclasses.fields(params_type)]
    vary = {names[0]: (0.7, 1.3), names[-1]: (0.9, 1.1)}
    drawn = draw(Distribution(params_type, vary), 50, rng=np.random.default_rng(3))
    want = np.array([dataclasses.astuple(p) for p in drawn.params], dtype=float)
    np.testing.assert_array_equal(drawn.values, want)
    assert drawn.values.shape == (50, len(names))
    assert len(np.unique(drawn.values[:, -1])) == 50  # the varied fields, not copies


def test_parameter_matrix_takes_one_type_and_any_field_count():
    @dataclasses.dataclass(frozen=True)
    class One:
        mass: float = 1.0

    np.testing.assert_array_equal(parameter_matrix([One(2.0), One(3.0)]), [[2], [3]])
    with pytest.raises(
        ValueError, match="expected only One, got AcrobotParams at index 1"
    ):
        parameter_matrix([One(), AcrobotParams()])
    with pytest.raises(ValueError, match="at least one"):
        parameter_matrix([])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"vary": {"pole_mass": (0.1, 0.2)}}, "not a parameter of AcrobotParams"),
        ({"vary": {"link_mass_1": (1.2, 0.9)}}, "low > high"),
        ({"vary": {"link_mass_1": (0.1, 1.0)}}, "lower bound 0.2"),
        ({"vary": {"link_mass_1": (1.0, 9.0)}}, "upper bound 5.0"),
        ({"vary": {}}, "at least one parameter"),
        ({"kind": "grid"}, "grid (points per parameter K)"),
        ({"kind": "uniform", "grid": 3}, "grid (points per parameter K)"),
        ({"kind": "sobol"}, "kind must be one of"),
        ({"split": "test"}, "split must be one of"),
        ({"sigma": -1.0}, "sigma must be a positive"),
        ({"inner_fraction": 0.0}, "inner_fraction must be in (0, 1)"),
        ({"sigma": "0.1"}, "sigma must be a number"),
        ({"sigma": True}, "sigma must be a number"),
        ({"sigma": float("inf")}, "sigma must be a positive"),
        ({"inner_fraction": "0.5"}, "inner_fraction must be a number"),
        ({"kind": "grid", "grid": 2.5}, "grid must be a positive int"),
        ({"kind": "grid", "grid": 0}, "grid must be a positive int"),
        ({"kind": "grid", "grid": True}, "grid must be a positive int"),
        # built as a list of 25 million tuples (2.7 GB) before failing
        ({"kind": "grid", "grid": 5000}, "K^p = 5000^2 = 25,000,000 points"),
        (
            {"vary": {"link_mass_1": (1.0, 1.0)}, "split": "extrapolation"},
            "no point lies outside",
        ),
    ],
)
def test_impossible_distributions_are_rejected(kwargs, message):
    with pytest.raises(ValueError) as error:
        dist(**kwargs)
    assert message in str(error.value)


@pytest.mark.parametrize("nominal", [0.0, -1.0])
def test_relative_normal_refuses_a_nominal_that_is_not_positive(nominal):
    # its scale σ θ₀ would be 0 (every draw NaN) or negative (the truncation
    # interval's ends swapped); the uniform draws do not use the nominal
    Offset = dataclasses.make_dataclass(
        "Offset", [("x", float, dataclasses.field(default=nominal))], frozen=True
    )
    with pytest.raises(ValueError, match="x's nominal value is .*positive"):
        Distribution(Offset, {"x": (-0.5, 0.5)}, kind="relative-normal")
    uniform = Distribution(Offset, {"x": (-0.5, 0.5)})
    assert np.all(np.abs(draw(uniform, 5, rng=np.random.default_rng(0)).values) <= 0.5)


def test_draw_rejects_bad_counts_and_unreachable_regions():
    with pytest.raises(ValueError, match="positive int"):
        draw(dist(), 0, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="must be None for a grid"):
        draw(dist(kind="grid", grid=2), 4, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="has no points"):
        draw(dist(kind="grid", grid=2, split="train"), None, rng=None)
    # σ = 0.1% of nominal: the truncated normal almost never leaves the inner box.
    tight = dist(kind="relative-normal", sigma=0.001, split="extrapolation")
    with pytest.raises(ValueError, match="too small"):
        draw(tight, 5, rng=np.random.default_rng(0))


def test_a_nominal_far_outside_the_truncation_box_is_named(capsys, tmp_path):
    """The default cart-pole ranges' inner box, [0.1625, 0.3875] kg, excludes the
    nominal pole mass 0.1 by 3.1σ at σ = 0.2: every train draw sits at the edge.
    Named (and warned of by tasks.generate, before any work); a box holding the
    nominal, or another kind, gives nothing."""
    from tasks import generate

    vary = {"pole_mass": (0.05, 0.5), "pole_half_length": (0.25, 1.0)}
    far = Distribution(
        CartpoleParams, vary, kind="relative-normal", split="train", sigma=0.2
    )
    (message,) = far.far_from_nominal()
    assert message.startswith("pole_mass: the nominal 0.1 lies 3.1σ outside")
    masses = draw(far, 200, rng=np.random.default_rng(0)).varied[:, 0]
    # what the message warns of: half the draws within 0.01 of the edge, of 0.225,
    # none beyond it (the law itself is checked above, against truncnorm)
    assert masses.min() >= 0.1625 and np.median(masses) < 0.1625 + 0.01
    assert dataclasses.replace(far, split="all").far_from_nominal() == []
    assert dataclasses.replace(far, kind="uniform").far_from_nominal() == []
    near = dataclasses.replace(far, vary=vary | {"pole_mass": (0.05, 0.2)})
    assert near.far_from_nominal() == []
    generate.main([
        "--domain", "cartpole", "--distribution", "relative-normal", "--sigma",
        "0.2", "--split", "train", "--instances", "2", "--max-steps", "5",
        "--out", str(tmp_path / "run"), "--no-progress",
    ])  # fmt: skip
    assert "warning: pole_mass: the nominal 0.1 lies 3.1σ" in capsys.readouterr().err


def test_grid_size_limit_is_inclusive_and_one_point_per_parameter_is_a_grid():
    """K^p = MAX_GRID_POINTS is allowed (the limit is "the most points"; nothing
    is built on construction); K = 1 is a positive int, one point per parameter."""
    one = {"link_mass_1": (0.6, 1.4)}
    assert dist(kind="grid", grid=MAX_GRID_POINTS, vary=one).grid == MAX_GRID_POINTS
    assert draw(dist(kind="grid", grid=1), None, rng=None).varied.shape == (1, 2)


def test_extrapolation_draws_n_points_and_a_fixed_range_stays_put():
    """Extrapolation keeps the draws outside the inner box and returns exactly
    n (it draws in rounds of at least 64, so more than n). One fixed range is
    fine while another has a width: every point is then outside the inner box
    along the other."""
    fixed = {"link_mass_1": (1.1, 1.1), "link_mass_2": (0.8, 1.2)}
    for kind in ("uniform", "relative-normal"):
        d = dist(kind=kind, vary=fixed, split="extrapolation", sigma=0.3)
        v = draw(d, 5, rng=np.random.default_rng(0)).varied
        assert v.shape == (5, 2)
        np.testing.assert_array_equal(v[:, 0], 1.1)
        # the inner box along link_mass_2 is [0.9, 1.1]
        assert np.all((v[:, 1] < 0.9) | (v[:, 1] > 1.1))


def test_in_box_is_closed():
    """A point on a face of the box is inside it (as the docstring says: the
    closed box); one just past a face is not."""
    lows, highs = [0.8, 0.9], [1.2, 1.1]
    points = np.array([[0.8, 0.9], [1.2, 1.1], [1.0, 1.1 + 1e-12], [0.8 - 1e-12, 1.0]])
    np.testing.assert_array_equal(in_box(points, lows, highs), [1, 1, 0, 0])


def test_far_from_nominal_uses_the_box_the_draws_are_truncated_to():
    """Interpolation draws are truncated to the inner box as train ones are; a
    nominal above the box is as far as one below, and the message names the edge
    the draws crowd. Cart-pole pole mass (nominal 0.1) over [0.05, 0.5] at σ = 0.2
    (scale 0.02): inner box [0.1625, 0.3875], gap 0.0625 = 3.125σ. Cart mass
    (nominal 1.0) over [0.1, 0.5] at σ = 0.1 (scale 0.1): gap 0.5 = 5σ."""
    vary = {"pole_mass": (0.05, 0.5), "pole_half_length": (0.25, 1.0)}
    held_out = Distribution(
        CartpoleParams, vary, kind="relative-normal", split="interpolation", sigma=0.2
    )
    assert held_out.far_from_nominal() == [
        "pole_mass: the nominal 0.1 lies 3.1σ outside the inner box "
        "[0.1625, 0.3875]; its draws crowd the edge at 0.1625"
    ]
    above = Distribution(
        CartpoleParams, {"cart_mass": (0.1, 0.5)}, kind="relative-normal", sigma=0.1
    )
    assert above.far_from_nominal() == [
        "cart_mass: the nominal 1 lies 5.0σ outside the range [0.1, 0.5]; its "
        "draws crowd the edge at 0.5"
    ]


def test_as_json_gives_only_the_options_that_apply():
    """What the manifest records: σ only for the relative normal, the inner
    fraction only for a split that uses the inner box."""
    plain = dist().as_json()
    assert plain == {
        "kind": "uniform",
        "split": "all",
        "vary": {"link_mass_1": [0.6, 1.4], "link_mass_2": [0.8, 1.2]},
        "grid": None,
        "sigma": None,
        "inner_fraction": None,
    }
    normal = dist(kind="relative-normal", split="train", sigma=0.3).as_json()
    assert (normal["sigma"], normal["inner_fraction"]) == (0.3, 0.5)
