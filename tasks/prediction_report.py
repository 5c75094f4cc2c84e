"""Artefacts of the cartpole prediction run: weights.png, cartpole.rrd, report.md."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from hipmdp.data import Transitions
from hipmdp.planning import LearnedModel
from tasks import cartpole
from tasks.experiment import (
    count,
    describe_environment,
    fmt_ci,
    markdown_table,
    run_time_line,
    weights_figure,
    write_text,
    z_table,
)
from tasks.prediction import (
    PREDICTION_METHODS,
    added_text,
    best_baseline,
    coverage_text,
    entity,
    fit_options_text,
    mse_table,
    ratio_text,
    unseen_section,
)
from tasks.recording import Recording, offset_steps, recording_line


def write_artefacts(path: Path, config, metrics: dict, hip, splits) -> None:
    """weights.png and cartpole.rrd (first HiP-MDP run)."""
    _weights_figure(path / "weights.png", config, metrics)
    if config.record:
        record(path / "cartpole.rrd", config, metrics, hip, splits)


def _weights_figure(file: Path, config, metrics: dict) -> None:
    n_test = len(config.test_settings)
    weights_figure(
        file,
        np.array(config.train_settings),
        np.asarray(metrics["training_weights"][0])[1:],  # row 0: mean dynamics
        np.array(config.test_settings),
        np.asarray(metrics["test_belief_means"]).reshape(n_test, -1),
        ("pole mass (kg)", "pole half-length (m)"),
        "Cart-pole latent weights against mass and length (run 0)",
    )


def record(file: Path, config, metrics: dict, hip, splits) -> None:
    """Per test setting (the ``episode`` timeline, the setting's index): the belief
    filtered over the train transitions (the ``transition`` timeline), the first
    gathered episode posed in 3D with the HiP-MDP's one-step predictions (the
    ``step`` timeline), and each method's MSE. Both ``transition`` and ``step``
    count on from one setting to the next, so that scrubbing plays the settings
    in turn."""
    import rerun.blueprint as rrb

    blueprint = rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/belief", name="weight belief (±2σ)"),
                rrb.TimeSeriesView(origin="/mse", name="MSE per test setting"),
            ),
            rrb.Vertical(
                rrb.Spatial3DView(origin="/rollout", name="cart-pole"),
                rrb.TextDocumentView(origin="/notes", name="what this shows"),
            ),
        ),
        collapse_panels=True,
    )
    with Recording(file, application_id="hipmdp_cartpole", blueprint=blueprint) as rec:
        rec.text("/notes", _NOTES)
        setting = np.arange(len(splits))
        per_setting = metrics["per_setting_mse"]
        for m in per_setting:
            mse = np.asarray(per_setting[m])
            for d in (2, 3):  # Δẋ and Δθ̇, the dimensions the parameters act on
                rec.scalars(f"/mse/{d}/{entity(m)}", mse[:, d], episode=setting)
        # the cart's drawn size (box geom half-sizes), the same on every instance
        nominal = cartpole.make_model(None)
        cart_half = tuple(float(v) for v in nominal.geom("cart").size)
        pole_radius = float(nominal.geom("pole").size[0])  # the pole's capsule geom
        firsts = [_first_episode(split.episodes) for split in splits]
        transitions = offset_steps([len(split.train) + 1 for split in splits])
        steps = offset_steps([len(first) + 1 for first in firsts])
        settings = zip(config.test_settings, splits, firsts, strict=True)
        for e, (p, split, first) in enumerate(settings):
            params = cartpole.CartpoleParams(
                cart_mass=1.0, pole_mass=p[0], pole_half_length=p[1]
            )
            belief = hip.prior()
            means, sds = [belief.mean], [np.sqrt(np.diag(belief.cov))]
            for t in range(len(split.train)):
                belief = hip.update(belief, split.train.take([t]))
                means.append(belief.mean)
                sds.append(np.sqrt(np.diag(belief.cov)))
            means, sds = np.array(means), np.array(sds)
            truth = {"pole_mass": p[0], "pole_half_length": p[1]}
            rec.belief(means, sds, truth, episode=e, step=transitions[e],
                       timeline="transition")  # fmt: skip
            model = LearnedModel(hip, belief, first.angle_dims)
            predicted = model.predict(first.states, first.actions)
            # the real poses s_0 .. s_T, the predicted s_1 .. s_T beside them
            real = np.concatenate([first.states, first.next_states[-1:]])
            real_points = cartpole.link_points(real, params)
            step = steps[e]
            rec.capsules("/rollout/real", real_points[:, 1:], pole_radius,
                         episode=e, step=step, color=(40, 110, 220))  # fmt: skip
            rec.boxes("/rollout/cart", real_points[:, 0], cart_half,
                      episode=e, step=step, color=(180, 130, 80))  # fmt: skip
            rec.strips("/rollout/predicted", cartpole.link_points(predicted, params),
                       episode=e, step=step[1:], color=(200, 40, 40),
                       radius=0.015)  # fmt: skip


def _first_episode(data: Transitions) -> Transitions:
    ends = np.flatnonzero(data.dones) if data.dones is not None else []
    return data.head(int(ends[0]) + 1 if len(ends) else len(data))


_NOTES = """\
# Cartpole one-step prediction

The `episode` timeline is the test setting's index (from 0, in the order of the
pole mass, half-length grid).

- **weight belief** (timeline `transition`): the HiP-MDP's belief over each latent
  weight (mean, ±2σ) while it filters each setting's train transitions, one at a
  time, beside the true pole mass and half-length (`/belief/true`).
- **MSE per test setting** (timeline `episode`): each method's held-out MSE of Δẋ
  (`/mse/2`) and Δθ̇ (`/mse/3`).
- **cart-pole** (timeline `step`): the setting's first gathered episode posed from
  the simulator (the cart a box, the pole blue) and the HiP-MDP's one-step
  predicted pole for each step (red), from the belief after all the setting's
  train transitions (some of this episode's transitions are among them).

`transition` and `step` count on from one setting to the next, so scrubbing
either plays the settings in turn.
"""


def write_report(path: Path, config, metrics: dict[str, Any]) -> None:
    """report.md: the MSE table, log-likelihood differences and latent structure."""
    mse = metrics["mse"]
    dims = list(next(iter(mse.values())))
    table = mse_table(mse)
    intervals = metrics.get("mse_ratio_to_best_baseline_interval") or {}

    def ratio_cell(d: str, v: float | None) -> str:
        if v is None:
            return "—"
        ci = intervals.get(d)
        return f"{v:.2g}" if not ci else f"{v:.2g} [{ci['low']:.2g}, {ci['high']:.2g}]"

    ratios = markdown_table(
        dims,
        [[ratio_cell(d, v) for d, v in metrics["mse_ratio_to_best_baseline"].items()]],
    )
    ll = markdown_table(
        ["method", "HiP-MDP minus method"],
        [[m, fmt_ci(v)] for m, v in metrics["loglik_difference"].items()],
    )
    s = metrics["seconds"]
    n_batch = metrics["n_batch_transitions"]
    title = f"Cartpole one-step prediction ({config.preset} preset, seed {config.seed})"
    settings = count(len(config.test_settings), "test setting")
    fits = count(config.n_runs, "time")
    fit_options = fit_options_text(config.fit)
    fit_options = f"\n{fit_options}" if fit_options else ""
    n_train = len(config.train_settings)
    text = f"""# {title}

{settings} × {config.n_train} train / {config.n_test}
test transitions ({config.split} split); HiP-MDP fitted {fits} on
{n_batch} batch transitions from {n_train} training settings.{fit_options}

## MSE of Δs (mean over test settings [95% interval])

{added_text(config.methods)}{table}

HiP-MDP MSE divided by the best baseline's (below 1: the HiP-MDP is better; the
paper's Table 1 MSEs give 0.3 on Δẋ and 0.17 on Δθ̇), with a 95% bootstrap
interval over the test settings (a percentile bootstrap: over a few settings it
covers less than 95%, and one setting can lead a ratio of means):

{ratios}

{ratio_text(metrics)}

## Test log-likelihood (HiP-MDP minus method, over {config.n_test} test transitions)

Positive favours the HiP-MDP; mean [95% interval] over test settings.

{ll}

{coverage_text(metrics.get("coverage"))}

{unseen_section(metrics)}

## Latent structure

Latent features per run: {metrics["n_latent_features"]}. z of run 0, the
features each (action, dimension) uses:

{z_table(metrics["z"][0], list(metrics["mse"]["hipmdp"]))}

{run_time_line(s)} Figures: `weights.png`.
{recording_line(config, "cartpole.rrd")}

{describe_environment(metrics.get("environment"))}
"""
    write_text(path / "report.md", text)


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """What the command prints when the run ends: per dimension, the HiP-MDP's
    MSE over the best baseline's (a ratio of means, below 1: the HiP-MDP is
    better) with its bootstrap interval over the test settings and that
    baseline's name; then, per method added with ``--method``, its MSE over
    the HiP-MDP's per dimension (a ratio of means)."""
    intervals = metrics.get("mse_ratio_to_best_baseline_interval") or {}
    lines = [
        "HiP-MDP MSE / the best baseline's (95% bootstrap interval over the test "
        "settings; below 1: the HiP-MDP is better):"
    ]
    for d, v in metrics["mse_ratio_to_best_baseline"].items():
        ci = intervals.get(d)
        base = best_baseline(metrics["mse"], d)
        if v is None:
            lines.append(f"  {d}: none ({base} predicts it exactly)")
            continue
        bounds = f" [{ci['low']:.2g}, {ci['high']:.2g}]" if ci else ""
        lines.append(f"  {d}: {v:.2g}{bounds} against {base}")
    mse = metrics["mse"]
    hip = mse["hipmdp"]
    for name in (m for m in mse if m not in PREDICTION_METHODS):  # --method's
        ratios = ", ".join(
            f"{d} {x['mean'] / hip[d]['mean']:.2g}"
            if hip.get(d, {}).get("mean", 0) > 0
            else f"{d} n/a"
            for d, x in mse[name].items()
        )
        lines.append(
            f"{name} (added) MSE / the HiP-MDP's (ratio of means; above 1: the "
            f"HiP-MDP is better): {ratios}"
        )
    return lines
