"""Simulator side: MuJoCo models rewritten per instance, dm_control tasks, data
gathering and the runnable experiments."""

import os

# Headless by default: dm_control picks a GL backend at import time and GLFW warns
# when there is no display. Nothing here renders unless the user asks for it.
os.environ.setdefault("MUJOCO_GL", "disable")
