"""Instance parameter distributions and train / interpolation / extrapolation splits.

Symbols: `p` varied parameters, `θ` a point of them, shape `(p,)`; `O` the outer box
`Π_j [low_j, high_j]` given by the varied ranges; `I` the inner box, the central
fraction `f` of `O` in every coordinate, `Π_j [c_j - f w_j / 2, c_j + f w_j / 2]`
with `c_j` the centre and `w_j = high_j - low_j` the width; `θ₀` the nominal values
(the dataclass defaults); `σ` the relative scale of the normal distribution.

Distributions (all draws from one `rng`):

- `grid`: `np.linspace(low_j, high_j, K)` per parameter, all `K^p` combinations (the
  first parameter varies slowest);
- `uniform`: `θ_j ~ U[low_j, high_j]` independently;
- `relative-normal`: `θ_j ~ N(θ₀_j, (σ θ₀_j)²)` *truncated* to its interval (drawn
  exactly by the inverse CDF of the truncated normal, not clipped: clipping would put
  probability mass on the bounds), as contextual-RL benchmarks vary a parameter
  relative to its default.

Splits (`split`):

- `all`: the whole box `O`;
- `train`: the distribution restricted to the inner box `I`;
- `interpolation`: held-out points inside `I` — for `uniform`/`relative-normal`
  independent draws restricted to `I` (a separate stream, so they are not the
  training points); for `grid` the grid points inside `I` are split like a
  checkerboard: index sum even → `train`, odd → `interpolation` (points on the
  boundary of `I`, to 1e-9 of the width, count as inside);
- `extrapolation`: `O \\ I`, points with at least one coordinate outside `I` (drawn in
  `O` and rejected while inside `I`; for `grid`, the grid points outside `I`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np
from scipy import special

from tasks._common import parameter_matrix

Array = np.ndarray

KINDS = ("grid", "uniform", "relative-normal")
SPLITS = ("all", "train", "interpolation", "extrapolation")
#: Rejection rounds for `extrapolation` before giving up (each draws ≥ 64 points).
MAX_REJECTION_ROUNDS = 1000
#: The most points a grid may have (`K^p`): refused before any is built.
MAX_GRID_POINTS = 10_000_000


@dataclasses.dataclass(frozen=True)
class Distribution:
    """What instances to draw.

    Attributes:
        params_type: the domain's parameter dataclass (`AcrobotParams`, ...).
        vary: `{name: (low, high)}`, the outer box `O`; other fields stay nominal.
        kind: one of `KINDS`.
        split: one of `SPLITS`.
        grid: `K`, points per parameter (`kind == "grid"` only).
        sigma: `σ`, relative standard deviation (`kind == "relative-normal"`).
        inner_fraction: `f ∈ (0, 1)`, the inner box's share of each range.

    Raises:
        ValueError: for an unknown name, `low > high`, a range outside the
            parameter's documented bounds, or an option that does not fit `kind`.
    """

    params_type: type
    vary: Mapping[str, tuple[float, float]]
    kind: str = "uniform"
    split: str = "all"
    grid: int | None = None
    sigma: float = 0.1
    inner_fraction: float = 0.5

    def __post_init__(self) -> None:
        fields = {f.name: f for f in dataclasses.fields(self.params_type)}
        if not self.vary:
            raise ValueError("vary must name at least one parameter")
        vary = {}
        for name, bounds in self.vary.items():
            if name not in fields:
                raise ValueError(
                    f"vary: {name!r} is not a parameter of "
                    f"{self.params_type.__name__}; they are {sorted(fields)}"
                )
            low, high = (float(x) for x in bounds)
            if not low <= high:
                raise ValueError(f"vary: {name} range [{low}, {high}] has low > high")
            for value in (low, high):  # the dataclass checks the documented bounds
                self.params_type(**{name: value})
            vary[name] = (low, high)
        object.__setattr__(self, "vary", vary)
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if self.split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {self.split!r}")
        if (self.kind == "grid") != (self.grid is not None):
            raise ValueError("grid (points per parameter K) goes with kind 'grid' only")
        if self.grid is not None:
            if (
                isinstance(self.grid, bool)
                or not isinstance(self.grid, int | np.integer)
                or self.grid < 1
            ):
                raise ValueError(f"grid must be a positive int, got {self.grid!r}")
            object.__setattr__(self, "grid", int(self.grid))  # JSON-ready
            size = self.grid ** len(vary)
            if size > MAX_GRID_POINTS:
                raise ValueError(
                    f"grid: K^p = {self.grid}^{len(vary)} = {size:,} points, more "
                    f"than {MAX_GRID_POINTS:,}; use a smaller --grid"
                )
        for name in ("sigma", "inner_fraction"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(
                value, int | float | np.number
            ):
                raise ValueError(f"{name} must be a number, got {value!r}")
            object.__setattr__(self, name, float(value))  # JSON-ready
        if not (np.isfinite(self.sigma) and self.sigma > 0):
            raise ValueError(f"sigma must be a positive number, got {self.sigma!r}")
        if not 0 < self.inner_fraction < 1:
            raise ValueError(
                f"inner_fraction must be in (0, 1), got {self.inner_fraction!r}"
            )
        if self.kind == "relative-normal":  # its scale is σ θ₀: θ₀ must be > 0
            for name, value in zip(self.names, self.nominal(), strict=True):
                if not value > 0:
                    raise ValueError(
                        f"vary: {name}'s nominal value is {value:g}; "
                        "'relative-normal' scales σ by the nominal, so it needs a "
                        "positive one (use kind 'uniform')"
                    )
        if self.split == "extrapolation" and np.all(self.widths == 0):
            raise ValueError(
                "split 'extrapolation' needs a range with low < high: every varied "
                "range is a single point, so no point lies outside the inner box"
            )

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.vary)

    @property
    def lows(self) -> Array:
        """`low_j`, shape `(p,)`."""
        return np.array([lo for lo, _ in self.vary.values()])

    @property
    def highs(self) -> Array:
        """`high_j`, shape `(p,)`."""
        return np.array([hi for _, hi in self.vary.values()])

    @property
    def widths(self) -> Array:
        """`w_j = high_j - low_j`, shape `(p,)`."""
        return self.highs - self.lows

    def inner_box(self) -> tuple[Array, Array]:
        """`I`: `(c - f w / 2, c + f w / 2)`, two arrays of shape `(p,)`."""
        centre = (self.lows + self.highs) / 2
        half = self.inner_fraction * self.widths / 2
        return centre - half, centre + half

    def nominal(self) -> Array:
        """`θ₀`, the defaults of the varied fields, shape `(p,)`."""
        defaults = {f.name: f.default for f in dataclasses.fields(self.params_type)}
        return np.array([defaults[name] for name in self.names], dtype=float)

    def far_from_nominal(self, limit: float = 2.0) -> list[str]:
        """For `relative-normal`: the varied parameters whose nominal value lies
        more than `limit` σ outside the box their draws are truncated to (the
        inner box for `train` and `interpolation`, else the outer one), each
        as a sentence. Their draws then crowd the box's edge nearest the
        nominal: legal, but rarely what was meant. Empty for other kinds."""
        if self.kind != "relative-normal":
            return []
        inner = self.split in ("train", "interpolation")
        lows, highs = self.inner_box() if inner else (self.lows, self.highs)
        box = "inner box" if inner else "range"
        out = []
        for name, nominal, lo, hi in zip(
            self.names, self.nominal(), lows, highs, strict=True
        ):
            scale = self.sigma * abs(nominal)
            gap = max(lo - nominal, nominal - hi, 0.0)
            if gap > limit * scale:
                out.append(
                    f"{name}: the nominal {nominal:g} lies {gap / scale:.1f}σ outside "
                    f"the {box} [{lo:g}, {hi:g}]; its draws crowd the edge at "
                    f"{lo if nominal < lo else hi:g}"
                )
        return out

    def as_json(self) -> dict[str, Any]:
        """The fields that determine the draws, as JSON-ready values (options that
        do not apply to `kind` or `split` are None)."""
        return {
            "kind": self.kind,
            "split": self.split,
            "vary": {name: list(bounds) for name, bounds in self.vary.items()},
            "grid": self.grid,
            "sigma": self.sigma if self.kind == "relative-normal" else None,
            "inner_fraction": None if self.split == "all" else self.inner_fraction,
        }


class Instances(NamedTuple):
    """Drawn instances: `params` the dataclasses, length `n`; `values` all their
    fields (`ParameterTable` columns), shape `(n, n_fields)`; `varied` the varied
    coordinates `θ`, shape `(n, p)`."""

    params: list[Any]
    values: Array
    varied: Array


def draw(
    distribution: Distribution, n: int | None, *, rng: np.random.Generator
) -> Instances:
    """Draw the instances of `distribution`'s split.

    Args:
        distribution: the distribution and split.
        n: how many instances; must be None for `grid` (the grid decides).
        rng: the stream for every draw.

    Returns:
        `Instances`; for `grid`, in grid order filtered by the split.

    Raises:
        ValueError: for a bad `n`, or a split the grid leaves empty, or an
            extrapolation region the relative normal almost never reaches.
    """
    if distribution.kind == "grid":
        if n is not None:
            raise ValueError("n must be None for a grid (it has K^p points)")
        varied = _grid(distribution)
    else:
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
            raise ValueError(f"n must be a positive int, got {n!r}")
        varied = _sample(distribution, int(n), rng=rng)
    if len(varied) == 0:
        raise ValueError(
            f"the {distribution.split!r} split of a grid with K = {distribution.grid} "
            "has no points; use a larger --grid"
        )
    params = [
        distribution.params_type(**dict(zip(distribution.names, row, strict=True)))
        for row in varied
    ]
    values = parameter_matrix(params)
    return Instances(params, values, varied)


def in_box(points: Array, lows: Array, highs: Array, tol: float | Array = 0.0) -> Array:
    """Whether each row of `points` `(n, p)` lies in the closed box widened by
    `tol` on every side; shape `(n,)`."""
    lows, highs = np.asarray(lows) - tol, np.asarray(highs) + tol
    return np.all((points >= lows) & (points <= highs), axis=1)


def _grid(distribution: Distribution) -> Array:
    """Grid points of the split, shape `(n, p)` (see the module docstring)."""
    axes = [
        np.linspace(lo, hi, distribution.grid)
        for lo, hi in zip(distribution.lows, distribution.highs, strict=True)
    ]
    shape = (distribution.grid,) * len(axes)  # itertools.product's order: C order
    indices = np.stack(np.unravel_index(np.arange(np.prod(shape)), shape), axis=1)
    points = np.stack([axis[indices[:, j]] for j, axis in enumerate(axes)], axis=1)
    if distribution.split == "all":
        return points
    # Grid points on the inner boundary count as inside despite rounding.
    inside = in_box(points, *distribution.inner_box(), tol=1e-9 * distribution.widths)
    even = indices.sum(axis=1) % 2 == 0
    keep = {
        "train": inside & even,
        "interpolation": inside & ~even,
        "extrapolation": ~inside,
    }[distribution.split]
    return points[keep]


def _sample(distribution: Distribution, n: int, *, rng: np.random.Generator) -> Array:
    """`n` random points of the split, shape `(n, p)`."""
    if distribution.split in ("train", "interpolation"):
        lows, highs = distribution.inner_box()
        # Independent streams per split: interpolation points are not training ones.
        stream = rng.spawn(2)[distribution.split == "interpolation"]
        return _draw_box(distribution, lows, highs, n, rng=stream)
    if distribution.split == "all":
        return _draw_box(
            distribution, distribution.lows, distribution.highs, n, rng=rng
        )
    inner = distribution.inner_box()
    kept: list[Array] = []
    count = 0
    for _ in range(MAX_REJECTION_ROUNDS):
        batch = _draw_box(
            distribution, distribution.lows, distribution.highs, max(n, 64), rng=rng
        )
        batch = batch[~in_box(batch, *inner)]
        kept.append(batch)
        count += len(batch)
        if count >= n:
            return np.concatenate(kept)[:n]
    raise ValueError(
        f"extrapolation: only {count} of {MAX_REJECTION_ROUNDS * max(n, 64)} draws "
        f"fell outside the inner box; sigma {distribution.sigma} is too small for "
        "these ranges (increase --sigma or --inner-fraction)"
    )


def _draw_box(
    distribution: Distribution,
    lows: Array,
    highs: Array,
    n: int,
    *,
    rng: np.random.Generator,
) -> Array:
    """`n` draws of the distribution restricted to the box `[lows, highs]`, `(n, p)`.

    Uniform: `θ_j ~ U[low_j, high_j]`. Relative normal: with `μ = θ₀`, `s = σ θ₀`,
    `a = (low - μ) / s`, `b = (high - μ) / s`, `θ_j = μ_j + s_j Φ⁻¹(u)` with
    `u ~ U[Φ(a_j), Φ(b_j)]`: the normal truncated to `[low_j, high_j]` exactly. An
    interval above the mean is drawn as the mirror image of `[-b, -a]`, where `Φ`
    keeps its precision (small values, not values close to 1). An interval
    more than about 37 σ from the mean, where `Φ(b)` is subnormal or 0, is drawn in
    log space, `log(Φ(a) + u (Φ(b) - Φ(a))) = log Φ(b) + log(u + (1 - u) Φ(a) /
    Φ(b))`; there the plain formula gave `Φ⁻¹(0) = -∞` and, clipped, every draw
    on the bound farthest from the mean. (Elsewhere the plain formula is kept: the
    two differ by round-off, and earlier draws stay as they were.)
    """
    if distribution.kind == "uniform":
        return rng.uniform(lows, highs, size=(n, len(lows)))
    mu = distribution.nominal()
    scale = distribution.sigma * mu
    u = rng.uniform(size=(n, len(lows)))
    a, b = (lows - mu) / scale, (highs - mu) / scale
    flip = a > 0
    a, b = np.where(flip, -b, a), np.where(flip, -a, b)
    cdf_a, cdf_b = special.ndtr(a), special.ndtr(b)
    z = special.ndtri(cdf_a + u * (cdf_b - cdf_a))
    far = cdf_b < np.finfo(float).tiny
    if np.any(far):
        log_a, log_b = special.log_ndtr(a), special.log_ndtr(b)
        ratio = np.exp(log_a - log_b)  # Φ(a) / Φ(b), in [0, 1]
        with np.errstate(divide="ignore"):  # u = 0 and Φ(a) = 0: z = -∞, clipped
            z_far = special.ndtri_exp(log_b + np.log(u + (1.0 - u) * ratio))
        z = np.where(far, z_far, z)
    points = mu + scale * np.where(flip, -z, z)
    points = np.where(highs == lows, lows, points)  # a range of one point
    return np.clip(points, lows, highs)  # guards the last ulp of the inverse CDF
