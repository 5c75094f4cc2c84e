"""hipmdp: Hidden Parameter MDPs with an IBP-GP model (Doshi-Velez & Konidaris).

Pure numpy/scipy: nothing in this package imports MuJoCo, so it fits transitions from
any simulator.
"""

from hipmdp.data import Transitions
from hipmdp.filter import Belief
from hipmdp.fitting import NEW_FEATURES, FitConfig, fit
from hipmdp.fourier import FourierBasis
from hipmdp.gibbs import GibbsData, GibbsPriors, GibbsState, run_chains
from hipmdp.model import FILTER_WEIGHTS, HipMDP, load
from hipmdp.planning import (
    DynamicsModel,
    LearnedModel,
    PlanningTask,
    PlanResult,
    SimulatedEpisodes,
    StepwiseModel,
    plan,
)
from hipmdp.sarsa import SarsaConfig, SarsaState


def _installed_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hipmdp")
    except PackageNotFoundError:  # imported from a source tree not installed
        return "0+unknown"


#: The installed distribution's version (``pyproject.toml``): name it, and the
#: commit, when you cite results (README, Citing).
__version__ = _installed_version()

__all__ = [
    "FILTER_WEIGHTS",
    "NEW_FEATURES",
    "Belief",
    "DynamicsModel",
    "FitConfig",
    "FourierBasis",
    "GibbsData",
    "GibbsPriors",
    "GibbsState",
    "HipMDP",
    "LearnedModel",
    "PlanResult",
    "PlanningTask",
    "SarsaConfig",
    "SarsaState",
    "SimulatedEpisodes",
    "StepwiseModel",
    "Transitions",
    "fit",
    "load",
    "plan",
    "run_chains",
]
