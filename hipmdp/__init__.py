"""hipmdp: Hidden Parameter MDPs with an IBP-GP model (Doshi-Velez & Konidaris).

Pure numpy/scipy: nothing in this package imports MuJoCo, so it fits transitions from
any simulator.
"""

from hipmdp.data import Transitions
from hipmdp.gibbs import GibbsData, GibbsPriors, GibbsState, run_chains

__all__ = ["Transitions", "GibbsData", "GibbsPriors", "GibbsState", "run_chains"]
