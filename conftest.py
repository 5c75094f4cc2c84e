"""Test-session settings, applied before any test module imports numpy.

Importing `tasks` sets its process defaults (one BLAS thread, headless MuJoCo; see
tasks/__init__.py); numpy is not loaded yet when pytest reads this file.

Hypothesis runs derandomized (its examples follow from each test's source, not
from a fresh seed or from failures replayed out of a local `.hypothesis/`
folder) and without its per-example deadline, which a loaded machine can miss:
the suite gives the same result on every run and machine.
"""

import os
from pathlib import Path

try:  # the test extra: without it pytest's own error is "unrecognized arguments: -n"
    import hypothesis  # noqa: F401
    import xdist  # noqa: F401
except ImportError as error:
    package = {"xdist": "pytest-xdist"}.get(error.name, error.name)
    raise ImportError(
        f"{package} is missing: the tests need the test extra, "
        "pip install -e '.[test]' (README, Quick start)"
    ) from None

import tasks  # noqa: F401

# isort: split

# the suite checks recordings: a developer's exported RERUN=off (README's way to
# skip them) would turn them off; the tests of RERUN=off set it themselves
os.environ.pop("RERUN", None)

import pytest
from hypothesis import settings

settings.register_profile("hipmdp", derandomize=True, database=None, deadline=None)
settings.load_profile("hipmdp")


@pytest.fixture(autouse=True)
def _no_models_from_another_test(monkeypatch):
    """Each test starts with empty per-process model slots (the pool initializers'
    state, set in this process when a test runs trials with one worker), so no
    test can pass on what an earlier one installed."""
    from tasks import acrobot_energy, acrobot_identified, transfer

    monkeypatch.setattr(transfer, "_MODELS", {})
    monkeypatch.setattr(acrobot_identified, "_STATE", {})
    monkeypatch.setattr(acrobot_energy, "_STATE", {})


@pytest.fixture(scope="session")
def _tiny_swingup_once(tmp_path_factory):
    """``tests._swingup.traced_main(TINY)``, made as a user calling ``main``
    after ``import numpy`` would (OpenBLAS at two threads): the tests of the
    BLAS thread limit inside ``main`` compare it with a run made at one."""
    from threadpoolctl import threadpool_limits

    from tests._swingup import traced_main
    from tests.test_acrobot_swingup import TINY

    with threadpool_limits(limits=2):
        return traced_main(TINY, tmp_path_factory.mktemp("tiny_swingup"))


@pytest.fixture(scope="module")
def tiny_swingup(_tiny_swingup_once, tmp_path_factory):
    """The session's run of ``tests.test_acrobot_swingup.TINY``, the module's own
    copy (folder and metrics) of one made once per session, that is once per
    pytest-xdist worker that needs it (the checks that read a finished run each
    made the same run, eight times over; a run's files hold no path of its)."""
    import copy
    import shutil

    results, trials = _tiny_swingup_once
    out = tmp_path_factory.mktemp("swingup") / "run"
    shutil.copytree(results.out, out)
    metrics = copy.deepcopy(results.metrics)
    return _tiny_swingup_once._replace(
        results=results._replace(out=out, metrics=metrics),
        trials=copy.deepcopy(trials),
    )


@pytest.fixture(scope="module")
def tiny_swingup_run(tiny_swingup) -> Path:
    """The folder of the module's copy of the session's TINY run (above)."""
    return tiny_swingup.results.out
