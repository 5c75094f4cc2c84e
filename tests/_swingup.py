"""A swing-up run that also hands back its trial results."""

from __future__ import annotations

from typing import Any, NamedTuple

import pytest


class TracedRun(NamedTuple):
    """What ``tasks.acrobot_swingup.main`` returned, and the trial results it
    wrote (in its order), as ``swingup_report.write_artefacts`` got them:
    states, predictions and beliefs that the run's files do not hold."""

    results: Any
    trials: tuple


def traced_main(config, out) -> TracedRun:
    """``main(config, out)``, keeping the trial results it writes."""
    from tasks import swingup_report
    from tasks.acrobot_swingup import main

    trials, write = [], swingup_report.write_artefacts

    def keep_trials(path, config, metrics, results, hip):
        trials.extend(results)
        return write(path, config, metrics, results, hip)

    with pytest.MonkeyPatch.context() as m:
        m.setattr(swingup_report, "write_artefacts", keep_trials)
        results = main(config, out)
    return TracedRun(results, tuple(trials))
