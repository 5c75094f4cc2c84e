"""The order-n Fourier basis for linear value-function approximation.

Konidaris, Osentoski & Thomas (2011), "Value Function Approximation in Reinforcement
Learning using the Fourier Basis". Symbols:

- ``s``: a state, shape ``(D,)``; ``D`` state dimensions.
- ``x``: the state normalised to the unit cube, ``x_d = (s_d - low_d) / (high_d -
  low_d)`` clipped to ``[0, 1]`` (states outside the documented bounds are clipped,
  not extrapolated, so a feature never leaves ``[-1, 1]``).
- ``c_i``: the ``i``-th coefficient vector, every integer vector in ``{0..n}^D``, so
  there are ``F = (n + 1)^D`` features; ``c_0 = 0`` is the constant feature.
- ``φ_i(s) = cos(π c_i · x)``: the features, each in ``[-1, 1]``.
- ``α_i = α / ‖c_i‖`` (and ``α_0 = α``): the per-feature step sizes; the basis stores
  the factors ``1 / ‖c_i‖`` as ``step_scale``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hipmdp.data import check_integer

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class FourierBasis:
    """Full order-``n`` Fourier basis over a box ``[low, high]`` of states.

    Args:
        order: ``n >= 0``, the largest integer in any coefficient vector.
        low: lower state bounds, shape ``(D,)``.
        high: upper state bounds, shape ``(D,)``, each strictly above ``low``.

    Attributes:
        coefficients: ``C``, the integer coefficient vectors, shape ``(F, D)`` with
            ``F = (n + 1)^D``, in lexicographic order (row 0 is the zero vector).
        step_scale: ``1 / ‖c_i‖`` (1 for ``c_0``), shape ``(F,)``; multiply a base step
            size ``α`` by it to get the per-feature step sizes ``α_i``.
    """

    order: int
    low: Array
    high: Array
    coefficients: NDArray[np.int64] = field(init=False, repr=False)
    step_scale: Array = field(init=False, repr=False)
    _pi_c: Array = field(init=False, repr=False)  # π C, shape (F, D)
    _inv_width: Array = field(init=False, repr=False)  # 1 / (high - low), shape (D,)

    def __post_init__(self) -> None:
        check_integer("order", self.order, 0)
        low = np.array(self.low, dtype=np.float64)
        high = np.array(self.high, dtype=np.float64)
        if low.ndim != 1 or low.shape != high.shape or low.size == 0:
            raise ValueError(
                "low, high: expected two 1-D arrays of the same length D >= 1, got "
                f"shapes {low.shape} and {high.shape}"
            )
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise ValueError("low, high: expected finite bounds")
        if np.any(high <= low):
            raise ValueError(f"high: expected high > low everywhere, got {low}, {high}")
        # a Python int: numpy integer orders would wrap ((2^32 - 1 + 1)^2 == 0 in
        # int64) and slip past the guard
        n_features = (int(self.order) + 1) ** low.size
        if n_features > 1_000_000:
            raise ValueError(
                f"order: (order + 1)^D = {n_features} features is more than 1e6"
            )
        C = np.array(
            list(itertools.product(range(self.order + 1), repeat=low.size)),
            dtype=np.int64,
        ).reshape(n_features, low.size)
        norm = np.linalg.norm(C, axis=1)
        scale = np.ones(n_features)
        scale[norm > 0] = 1.0 / norm[norm > 0]
        low.flags.writeable = False
        high.flags.writeable = False
        C.flags.writeable = False
        scale.flags.writeable = False
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)
        object.__setattr__(self, "coefficients", C)
        object.__setattr__(self, "step_scale", scale)
        object.__setattr__(self, "_pi_c", np.pi * C.astype(np.float64))
        object.__setattr__(self, "_inv_width", 1.0 / (high - low))

    @property
    def state_dim(self) -> int:
        """``D``, the state dimension."""
        return self.low.size

    @property
    def n_features(self) -> int:
        """``F = (n + 1)^D``."""
        return self.coefficients.shape[0]

    def normalise(self, states: Array) -> Array:
        """``x = clip((s - low) / (high - low), 0, 1)``, same shape as ``states``."""
        x = (np.asarray(states, dtype=np.float64) - self.low) * self._inv_width
        return np.clip(x, 0.0, 1.0, out=x)

    def __call__(self, states: Array) -> Array:
        """Features ``φ(s) = cos(π C x)``.

        Args:
            states: one state, shape ``(D,)``, or a batch, shape ``(N, D)``.

        Returns:
            ``φ``, shape ``(F,)`` for one state or ``(N, F)`` for a batch; each entry
            in ``[-1, 1]``.
        """
        s = np.asarray(states, dtype=np.float64)
        if s.ndim not in (1, 2) or s.shape[-1] != self.state_dim:
            raise ValueError(
                f"states: expected shape ({self.state_dim},) or (N, {self.state_dim}),"
                f" got {s.shape}"
            )
        if not np.isfinite(s).all():  # per planning step: the cheaper spelling
            bad = np.argwhere(~np.isfinite(s))[0]
            raise ValueError(
                f"states: non-finite value at index {tuple(int(i) for i in bad)}"
            )
        # (N, D) @ (D, F): one matrix product, then one vectorised cosine.
        return np.cos(self.normalise(s) @ self._pi_c.T)
