"""Shared by the simulator tests: MuJoCo's RK4 against an accurate ODE solve."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import Any

import mujoco
import numpy as np
from scipy.integrate import solve_ivp


def assert_fourth_order(
    module: ModuleType,
    accelerations: Callable[[np.ndarray, float, Any], np.ndarray],
    params: Any,
    scale: list[float],
    *,
    seed: int = 1,
    max_error: float = 1e-5,
) -> None:
    """For 5 random states and actions: one action of `module`'s model (a task
    module with `make_model`, `ACTIONS`, `CONTROL_TIMESTEP`) at its own step h,
    h/2 and h/4, against a DOP853 solve at 1e-13 of `accelerations(s, u,
    params)`; each halving must divide the error by 2⁴ = 16 within a factor √2,
    so neither a third- nor a fifth-order method passes (8√2 < ratio < 16√2),
    nor an error that stops shrinking because the model differs from the
    equations. The error at h must be below `max_error`, the accuracy the
    modules' docstrings state (a too coarse step converges at fourth order too)."""
    rng = np.random.default_rng(seed)
    for _ in range(5):
        s = rng.uniform(-1, 1, 4) * scale
        u = rng.choice(module.ACTIONS)
        exact = solve_ivp(
            lambda t, y, u=u: np.r_[y[2:], accelerations(y, u, params)],
            (0.0, module.CONTROL_TIMESTEP),
            s,
            method="DOP853",
            rtol=1e-13,
            atol=1e-13,
        ).y[:, -1]
        errors = []
        for k in (1, 2, 4):
            model = module.make_model(params)
            n_sub = round(module.CONTROL_TIMESTEP / model.opt.timestep)  # its own
            model.opt.timestep /= k
            data = mujoco.MjData(model)
            data.qpos[:], data.qvel[:], data.ctrl[0] = s[:2], s[2:], u
            mujoco.mj_step(model, data, n_sub * k)
            errors.append(np.abs(np.r_[data.qpos, data.qvel] - exact).max())
        ratios = np.array(errors[:-1]) / np.array(errors[1:])
        assert np.all((8 * np.sqrt(2) < ratios) & (ratios < 16 * np.sqrt(2))), errors
        assert errors[0] < max_error, errors
