"""Test-session settings, applied before any test module imports numpy."""

import os

# See tasks/__init__.py: one BLAS thread per process, headless MuJoCo.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault("MUJOCO_GL", "disable")
