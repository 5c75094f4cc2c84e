"""Side-by-side measurement shared by the benchmarks.

Two things timed one after the other on a shared machine see different loads: a
ratio of single timings moved by ±5–20% from run to run. `paired` measures every
side `repeats` times in turn, the order reversed on every other repeat (a drift in
the machine's speed then falls on all sides alike), and the scripts report medians
and the median of the repeats' ratios. Each side is called once untimed before (a
warm-up; in the scripts that compare outputs, the comparing call is the warm-up).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping

import numpy as np


def seconds(fn: Callable[[], object], n: int = 1) -> float:
    """Wall-clock seconds of one call of fn(): the median of n calls in a row."""
    times = []
    for _ in range(n):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def paired(
    measure: Mapping[str, Callable[[], float]],
    repeats: int,
    *,
    warm_up: Mapping[str, Callable[[], object]] | None = None,
) -> dict[str, np.ndarray]:
    """``repeats`` measurements of each side, taken in turn.

    measure: side name → a call returning one measurement (seconds, or a rate);
    repeats: measurements per side; warm_up: side name → an untimed call made once
    before the repeats (``None``: the caller has warmed every side up). The sides
    are measured in their order on even repeats and in reverse on odd ones.
    Returns side name → its measurements, shape (repeats,), in repeat order, so
    that ``a[i] / b[i]`` is a ratio measured side by side.
    """
    if repeats < 1:
        raise ValueError(f"repeats: expected >= 1, got {repeats}")
    for call in (warm_up or {}).values():
        call()
    names = list(measure)
    out: dict[str, list[float]] = {name: [] for name in names}
    for r in range(repeats):
        for name in names if r % 2 == 0 else names[::-1]:
            out[name].append(float(measure[name]()))
    return {name: np.array(values) for name, values in out.items()}


def ratio_text(num: np.ndarray, den: np.ndarray, digits: int | None = None) -> str:
    """The median of the paired ratios num[i] / den[i], with their range if more
    than one: '4.21x (4.02-4.37)'; thousands separated by commas. digits: after
    the point; None: 2 below 10, 1 below 100, else 0."""
    r = np.asarray(num) / np.asarray(den)
    med = float(np.median(r))
    if digits is None:
        digits = 2 if med < 10 else 1 if med < 100 else 0
    text = f"{med:,.{digits}f}x"
    if r.size > 1:
        text += f" ({r.min():,.{digits}f}-{r.max():,.{digits}f})"
    return text
