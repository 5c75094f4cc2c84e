"""Checks the two experiments' smoke tests share on their prediction tables."""

from __future__ import annotations

import dataclasses

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


def assert_names_fit_choices(run, write_report, config, folder, sep: str) -> None:
    """A run made with ``--filter-weights training`` or ``--new-features
    multiple_try`` says so in its report.md, each choice in its sentence (both,
    in that order), after ``sep``, and is otherwise the report at the defaults:
    ``run``'s (``main``'s results at ``config``), which names neither.
    ``write_report(folder, config, metrics)`` is the experiment's; the reports
    are written in ``folder`` from ``run``'s metrics."""
    default_report = (run.out / "report.md").read_text()

    def write(config, folder):
        write_report(folder, config, in_memory(run.metrics))

    factor = "The filter takes its model-error factor at the squared training"
    step = "The sampler takes the multiple-try new-feature step, exact at any"
    assert factor not in default_report and step not in default_report
    write(config, folder)  # the run's own report again, from its metrics
    assert (folder / "report.md").read_text() == default_report
    for changes, said in [
        ({"new_features": "multiple_try"}, [step]),
        ({"filter_weights": "training"}, [factor]),
        (
            {"new_features": "multiple_try", "filter_weights": "training"},
            [factor, step],
        ),
    ]:
        fit = dataclasses.replace(config.fit, **changes)
        write(dataclasses.replace(config, fit=fit), folder)
        text = (folder / "report.md").read_text()
        assert [s for s in (factor, step) if s in text] == said, changes
        flags = [f"`--{k.replace('_', '-')} {v}`" for k, v in changes.items()]
        assert all(flag in text for flag in flags), (flags, changes)
        if len(said) == 2:
            assert text.index(factor) < text.index(step)
        start = text.index(said[0]) - len(sep)  # where the sentences begin
        assert text[start:].startswith(sep), changes
        end = text.index(").", text.index(said[-1])) + 2  # where they end
        assert text[:start] + text[end:] == default_report, changes


def in_memory(metrics):
    """A run's metrics as ``main`` held them before writing metrics.json, as
    far as its report reads them: an interval's JSON null bounds back to NaN
    (an interval over one setting has none)."""
    if isinstance(metrics, dict):
        return {
            k: float("nan") if v is None and k in ("low", "high") else in_memory(v)
            for k, v in metrics.items()
        }
    if isinstance(metrics, list):
        return [in_memory(v) for v in metrics]
    return metrics
