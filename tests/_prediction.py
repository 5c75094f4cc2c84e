"""Checks the two experiments' smoke tests share on their prediction tables."""

from __future__ import annotations

from tasks.prediction import COVERAGE_LEVELS, PREDICTION_METHODS


def assert_coverage_schema(metrics: dict, dims, report: str) -> None:
    """``metrics["coverage"]``: a share in [0, 1] per method, level and dimension,
    the wider interval covering at least as much; the report prints the table."""
    coverage = metrics["coverage"]
    assert set(coverage) == set(PREDICTION_METHODS)
    levels = [f"{level:g}" for level in COVERAGE_LEVELS]
    for by_level in coverage.values():
        assert list(by_level) == levels
        for level in levels:
            assert set(by_level[level]) == set(dims)
            assert all(0 <= v["mean"] <= 1 for v in by_level[level].values())
        for d in dims:  # each setting's 95% share is at least its 50% share
            assert by_level["0.95"][d]["mean"] >= by_level["0.5"][d]["mean"]
    assert "central 50% / 95% Gaussian" in report
