"""Simulator side: MuJoCo models rewritten per instance, dm_control tasks, data
gathering and the runnable experiments."""

import os

# Headless by default: dm_control picks a GL backend at import time and GLFW warns
# when there is no display. Nothing here renders unless the user asks for it.
os.environ.setdefault("MUJOCO_GL", "disable")

# One BLAS thread per process unless the user says otherwise. Our matrices are small
# (hundreds to a few thousand rows) and experiments run one process per core;
# OpenBLAS's spinning worker threads then cost far more than they give (a 300 x 300
# Cholesky: 12 ms with two threads on a loaded two-core machine, 1.8 ms with one).
# This only takes effect if numpy has not been imported yet, as with `python -m`.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
