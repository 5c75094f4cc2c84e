"""Shared by the experiments' smoke tests: tasks.seed_spread reads a real run."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tasks import seed_spread
from tasks.experiment import write_json


def assert_reads_the_run(out: Path, tmp_path: Path, experiment: str) -> dict:
    """Run seed_spread on ``out`` and a copy under seed + 1 whose log-likelihood
    leads are 1 higher; check that every number is read from its own run.
    Returns the result."""
    other = tmp_path / "other_seed"
    shutil.copytree(out, other)
    config = json.loads((other / "config.json").read_text())
    write_json(other / "config.json", config | {"seed": config["seed"] + 1})
    metrics = json.loads((out / "metrics.json").read_text())
    shifted = json.loads((other / "metrics.json").read_text())
    for ci in shifted["loglik_difference"].values():
        ci.update(
            {k: ci[k] + 1.0 for k in ("mean", "low", "high") if ci[k] is not None}
        )
    write_json(other / "metrics.json", shifted)
    result = seed_spread.main([out, other])
    assert result["experiment"] == experiment
    labels = {n["label"] for n in result["numbers"]}
    assert len(labels) == len(result["numbers"])
    for n in result["numbers"]:
        first, second = n["per_seed"]
        if n["label"].startswith("log-likelihood, HiP-MDP - "):
            method = n["label"].removeprefix("log-likelihood, HiP-MDP - ")
            assert first["value"] == metrics["loglik_difference"][method]["mean"]
            assert second["value"] == pytest.approx(first["value"] + 1.0)
            assert n["across_seeds"]["sd"] == pytest.approx(np.sqrt(0.5))
            continue
        assert first == second, n["label"]
        if n["scale"] != "count":
            assert np.isfinite(first["value"]), n["label"]
            assert n["across_seeds"]["sd"] == 0.0
    # a header, a rule and a row per number
    assert seed_spread.report(result).count("\n|") == len(labels) + 2
    return result
