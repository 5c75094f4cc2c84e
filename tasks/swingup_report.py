"""Artefacts of the acrobot swing-up run: figures, the rerun recording, report.md."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from tasks import acrobot
from tasks.experiment import (
    count,
    describe_environment,
    fmt_ci,
    markdown_table,
    run_time_line,
    save_figure,
    weights_figure,
    within_threshold,
    write_text,
    z_table,
)
from tasks.prediction import (
    added_text,
    coverage_text,
    fit_options_text,
    mse_table,
    ratio_text,
    unseen_section,
)
from tasks.recording import Recording, offset_steps, recording_line
from tasks.transfer import LABELS

COLORS = {"true": (60, 60, 60), "average": (230, 120, 30), "hipmdp": (40, 110, 220)}
#: Colours of methods added with ``--method``, in turn.
ADDED_COLORS = ((40, 160, 80), (150, 60, 180), (190, 160, 20), (20, 160, 170))


def label(method: str) -> str:
    """A method's name in tables and legends (an added method's own name)."""
    return LABELS.get(method, method)


def color(method: str, methods: list[str]) -> tuple[int, int, int]:
    """A method's colour; added methods take ADDED_COLORS in their order."""
    if method in COLORS:
        return COLORS[method]
    added = [m for m in methods if m not in COLORS]
    return ADDED_COLORS[added.index(method) % len(ADDED_COLORS)]


def write_artefacts(path: Path, config, metrics: dict, trials: list, hip) -> None:
    """learning_curves.png, weights.png and acrobot.rrd."""
    _learning_curves(path / "learning_curves.png", metrics)
    _weights_figure(path / "weights.png", config, metrics, hip)
    if config.record:
        record(path / "acrobot.rrd", config, metrics, trials)


def _learning_curves(file: Path, metrics: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    methods = list(metrics["returns"])  # METHODS, then any added with --method
    for m in methods:
        c = metrics["returns"][m]
        mean, low, high = (np.asarray(c[k], float) for k in ("mean", "low", "high"))
        ep = np.arange(1, len(mean) + 1)
        rgb = np.array(color(m, methods)) / 255
        ax.plot(ep, mean, label=label(m), color=rgb, marker="o", markersize=3)
        ax.fill_between(ep, low, high, color=rgb, alpha=0.15, linewidth=0)
    target = metrics.get("near_optimal_target")
    if target is not None:  # the threshold "episodes to within 10%" counts by
        final, margin = target["true_model_final_mean_return"], target["margin"]
        ax.axhline(
            within_threshold(final, margin), color="0.4", linestyle="--", linewidth=1,
            label=f"within {margin:.0%} of the true model's final mean",
        )  # fmt: skip
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # episodes are whole
    ax.set_xlabel("real episode")
    ax.set_ylabel("return (−steps to goal)")
    n = metrics["returns"][methods[0]].get("n_trials")
    over = f" over {count(n, 'trial')}" if n else ""
    ax.set_title(
        f"Acrobot swing-up on new instances\n(mean, 95% t-interval{over} per method)",
        fontsize=11,
    )
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, frameon=False,
              fontsize=9)  # fmt: skip
    fig.tight_layout()
    save_figure(fig, file)


def _weights_figure(file: Path, config, metrics: dict, hip) -> None:
    n_test = len(config.test_masses)
    test_w = [metrics["test_belief_means"][str(i)] for i in range(n_test)]
    weights_figure(
        file,
        np.array(config.train_masses),
        np.asarray(hip.weights)[1:],  # feature 0 is the mean dynamics (w = 1)
        np.array(config.test_masses),
        np.array(test_w).reshape(n_test, -1),
        ("m1 (kg)", "m2 (kg)"),
        "Latent weights against the true masses",
    )


def record(file: Path, config, metrics: dict, trials: list) -> None:
    """The rerun recording of the traced trial (setting 0, trial 0), all methods."""
    import rerun.blueprint as rrb

    m1, m2 = config.test_masses[0]
    params = config.params(m1, m2)
    methods = list(metrics["returns"])  # METHODS, then any added with --method
    blueprint = rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/belief", name="weight belief (±2σ)"),
                rrb.TimeSeriesView(origin="/returns", name="return per episode"),
            ),
            rrb.Vertical(
                *(
                    rrb.Spatial3DView(origin=f"/rollout/{m}", name=label(m))
                    for m in methods
                ),
                rrb.TextDocumentView(origin="/notes", name="what this shows"),
            ),
        ),
        collapse_panels=True,
    )
    traced = {r.method: r for r in trials if r.traces}
    # the links drawn as the model's capsule geoms, posed from the simulator
    link_radius = float(acrobot.make_model(params).geom("link_1").size[0])
    with Recording(file, application_id="hipmdp_acrobot", blueprint=blueprint) as rec:
        rec.text("/notes", _NOTES.format(m1=m1, m2=m2))
        for m in methods:
            c = metrics["returns"][m]
            ep = np.arange(1, len(c["mean"]) + 1)  # numbered as report.md's
            rec.scalars(f"/returns/{m}", c["mean"], episode=ep)
        for m, result in traced.items():
            steps = offset_steps([len(t.states) for t in result.traces])
            for e, (trace, step) in enumerate(zip(result.traces, steps, strict=True)):
                real = acrobot.link_points(trace.states, params)
                rec.capsules(
                    f"/rollout/{m}/real", real, link_radius, episode=e + 1,
                    step=step, color=color(m, methods),
                )  # fmt: skip
                if trace.predicted is not None:  # None: a policy, without a model
                    pred = acrobot.link_points(trace.predicted, params)
                    rec.strips(
                        f"/rollout/{m}/predicted", pred, episode=e + 1,
                        step=step[1:], color=(200, 40, 40), radius=0.015,
                    )  # fmt: skip
                if trace.belief_mean is not None:
                    rec.belief(
                        trace.belief_mean, trace.belief_std, {"m1": m1, "m2": m2},
                        episode=e + 1, step=step,
                    )  # fmt: skip


_NOTES = """\
# Acrobot swing-up transfer

Test instance m1 = {m1} kg, m2 = {m2} kg (first test setting, first trial).

- **weight belief**: the HiP-MDP's belief over each latent weight, filtered one
  transition at a time (mean and ±2σ), beside the true masses (`/belief/true`).
- **return per episode**: mean return over all trials, per method.
- **rollouts**: the acrobot posed from the simulator state of each real step (coloured)
  and, in red, the position the method's model predicted for that step from the
  previous real state (none for a policy added with `--method`, which has no
  model).

Timelines: `episode` (the real episode, numbered from 1 as in `report.md`) and
`step` (the trial's steps, counted on across its episodes, so that scrubbing
it plays the episodes in turn; each method's trial has its own episode
lengths, so the same step can fall in different episodes for two methods).
"""


def write_report(path: Path, config, metrics: dict[str, Any]) -> None:
    """report.md: the tables in plain language."""
    ep = metrics["episodes_to_near_optimal"]
    target = metrics["near_optimal_target"]["true_model_final_mean_return"]
    n = metrics["near_optimal_target"]["final_window"]
    window = "episode" if n == 1 else f"{n} episodes"
    curves = metrics["returns"]
    n_ep = len(curves["true"]["mean"])
    show = sorted({0, min(1, n_ep - 1), min(4, n_ep - 1), n_ep - 1})
    methods = list(curves)  # METHODS, then any added with --method
    rows = [
        [label(m)]
        + [
            fmt_ci({k: curves[m][k][e] for k in ("mean", "low", "high")}, 4)
            for e in show
        ]
        + [ep[m] if ep[m] is not None else f"not within {n_ep}"]
        for m in methods
    ]
    transfer = markdown_table(
        ["method"] + [f"episode {e + 1}" for e in show] + ["episodes to near-optimal"],
        rows,
    )

    def at_episode(ci: dict, e: int) -> str:
        """A per-episode interval's cell at episode index ``e``."""
        return fmt_ci({k: ci[k][e] for k in ("mean", "low", "high")}, 4)

    n_show = min(2, n_ep)
    margins = metrics["margin_to_target"]
    margin_table = markdown_table(
        ["method"] + [f"episode {e + 1}" for e in range(n_show)],
        [
            [label(m)] + [at_episode(margins[m], e) for e in range(n_show)]
            for m in margins
        ],
    )
    paired = metrics["paired_difference"]
    paired_table = markdown_table(
        ["difference", "all episodes", "setting as unit"]
        + [f"episode {e + 1}" for e in range(n_show)],
        [
            [pair, fmt_ci(d["all_episodes"], 4), fmt_ci(d["by_setting"], 4)]
            + [at_episode(d["per_episode"], e) for e in range(n_show)]
            for pair, d in paired.items()
        ],
    )
    per_setting = metrics["paired_difference_per_setting"]
    setting_table = markdown_table(
        ["(m1, m2)", *per_setting],
        [
            [f"({rows[0]['masses'][0]:g}, {rows[0]['masses'][1]:g})"]
            + [fmt_ci(r, 4) for r in rows]
            for rows in zip(*per_setting.values(), strict=True)
        ],
    )
    medians = metrics["median_returns"]
    ep_median = metrics["episodes_to_near_optimal_median"]
    median_table = markdown_table(
        ["method"] + [f"episode {e + 1}" for e in show] + ["episodes to near-optimal"],
        [
            [label(m)]
            + [f"{medians[m][e]:.4g}" for e in show]
            + [ep_median[m] if ep_median[m] is not None else f"not within {n_ep}"]
            for m in methods
        ],
    )
    split = metrics["step_limit_split"]
    split_table = markdown_table(
        ["pair", "gap in mean return", "episodes before the limit", "episodes at it"],
        [
            [k]
            + [
                "n/a" if v[f] is None else f"{v[f]:+.1f}"
                for f in ("gap", "below_limit", "limit")
            ]
            for k, v in split["pairs"].items()
        ],
    )
    limit = metrics["step_limit_rate"]
    limit_table = markdown_table(
        ["method"] + [f"episode {e + 1}" for e in range(n_ep)],
        [[label(m)] + [f"{x:.0%}" for x in limit[m]] for m in methods],
    )

    ll = metrics["loglik_difference"]
    ll_rows = [[m, fmt_ci(v)] for m, v in ll.items()]
    unseen_text = unseen_section(metrics)
    policies = [m for m in methods if m not in metrics["mse"]]
    pre = added_text(config.methods, policies)  # before the MSE table, or ""
    s = metrics["seconds"]
    inertia = (
        "Each link's moment of inertia stays at the book's 1 kg·m² as its mass "
        "changes (`--book-inertia`)."
        if config.book_inertia
        else "Each link's moment of inertia follows its mass (I = m l²)."
    )
    fit_options = fit_options_text(config.fit)
    fit_options = f" {fit_options}" if fit_options else ""
    targets = "\n".join(f"- {line}" for line in target_lines(metrics))
    n_test = len(config.test_masses)
    these_settings = "this setting" if n_test == 1 else f"these {n_test} settings"
    text = f"""# Acrobot swing-up transfer ({config.preset} preset, seed {config.seed})

{count(n_test, "test mass setting")} × {count(config.n_trials, "trial")} per method;
HiP-MDP fitted on {metrics["n_batch_transitions"]} batch transitions from
{len(config.train_masses)} training settings; {metrics["n_latent_features"]} latent
features inferred. {inertia}{fit_options}

## Against the targets

The targets (README, Experiments): the HiP-MDP within 10% of the true model's
final mean return by episode 2, and clearly ahead of the average model. Each is
met or missed only where its 95% interval lies wholly on one side of 0.

{targets}

## Returns per real episode (mean [95% interval]; return = −steps to the goal)

{transfer}

"Near-optimal" is within 10% of the true model's final mean return ({target:.1f},
its mean over the last {window}). "Episodes to near-optimal" is the first
episode whose mean return reaches that line: one crossing, without an interval,
so where a curve hovers around the line the margins below say more.
Per trial, each method's return minus 10% below the true model's final return on
the same trial (mean [95% interval] over trials; above 0: within 10%):

{margin_table}

## Paired differences in return (mean [95% interval] over trials)

Each trial's return minus the other method's on the same instance and seeds;
"all episodes" is the difference of the two trials' mean returns over all
{n_ep} real episodes. An interval above 0 means the first method is clearly ahead.
Its unit is the trial, so it answers for {these_settings};
"setting as unit" is the same mean with an interval over the settings' means,
which answers for new settings drawn like these (wider when the difference
varies from setting to setting; with few settings it can come out narrower by
chance). Every interval is conditional on this run's one
batch and one fit.

{paired_table}

The same over all episodes, on each test setting alone:

{setting_table}

Share of real episodes that ran to the {config.transfer.max_steps}-step limit
(each such episode has a return of −{config.transfer.max_steps}):

{limit_table}

How much of each gap in mean return (over all episodes) is those episodes: the
difference of the means over the episodes that ended before the limit, and the
rest (`step_limit_split` in `metrics.json`):

{split_table}

The same on per-episode medians, which those episodes do not decide; near-optimal
is then within 10% of the true model's final median
({metrics["true_model_final_median_return"]:.1f}):

{median_table}

## One-step prediction error on test settings (MSE of Δs)

{pre}{config.mse_train} train and {config.mse_test} test transitions per setting
({config.split} split). Mean over settings [95% interval over settings]:

{mse_table(metrics["mse"])}

{ratio_text(metrics)}

Test log-likelihood over {config.mse_test} test transitions, HiP-MDP minus method
(positive favours the HiP-MDP; interval over settings):

{markdown_table(["method", "difference"], ll_rows)}

{coverage_text(metrics.get("coverage"))}

{unseen_text}

## Approximation floor (the same protocol on training settings)

Not a lower bound for the table above: other transitions are scored, and with
few settings one that reaches fast states can lead every method's error.

{mse_table(metrics["approximation_floor"]) if metrics["approximation_floor"] else "—"}

## Latent structure

z, the features each (action, dimension) uses:

{z_table(metrics["z"], list(metrics["mse"]["hipmdp"]))}

{run_time_line(s)}

{describe_environment(metrics.get("environment"))}

Figures: `learning_curves.png`, `weights.png`. {recording_line(config, "acrobot.rrd")}
"""
    write_text(path / "report.md", text)


def _verdict(ci: dict, above: str, below: str, neither: str) -> str:
    """``above`` where the 95% interval lies above 0, ``below`` where it lies
    below, else ``neither`` (also for an interval of one sample)."""
    low, high = ci["low"], ci["high"]
    if low is None or high is None or np.isnan(low) or np.isnan(high):
        return neither
    return above if low > 0 else below if high < 0 else neither


def target_lines(metrics: dict[str, Any]) -> list[str]:
    """The two targets (README, Experiments), each with its 95% interval and
    whether that settles it: the HiP-MDP's per-trial margin to 10% of the true
    model at episode 2 (none for a one-episode run) and its paired lead over
    the average model over all episodes."""
    lines = []
    margin = metrics["margin_to_target"]["hipmdp"]
    if len(metrics["returns"]["true"]["mean"]) >= 2:
        ci = {k: (v[1] if np.ndim(v) else v) for k, v in margin.items()}
        verdict = _verdict(ci, "met", "missed", "not settled")
        lines.append(
            "HiP-MDP within 10% of the true model by episode 2, margin per trial: "
            f"{fmt_ci(ci, signed=True)} ({verdict})"
        )
    ahead = metrics["paired_difference"]["hipmdp - average"]["all_episodes"]
    verdict = _verdict(ahead, "clearly ahead", "clearly behind", "not clearly ahead")
    lines.append(
        "HiP-MDP - average model, mean return over all episodes: "
        f"{fmt_ci(ahead, signed=True)} ({verdict})"
    )
    return lines


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """What the command prints when the run ends: each method's mean return at
    episodes 1, 2 and the last, the targets (:func:`target_lines`), and the
    episodes to near-optimal."""
    returns = metrics["returns"]
    n_episodes = len(returns["true"]["mean"])
    shown = sorted({0, min(1, n_episodes - 1), n_episodes - 1})
    width = max(len(label(m)) for m in returns)
    n_trials = returns["true"]["n_trials"]
    lines = [
        f"mean return per real episode over {n_trials} trials "
        f"(episode {', '.join(str(e + 1) for e in shown)}):"
    ]
    for m, r in returns.items():
        values = "  ".join(f"{r['mean'][e]:8.1f}" for e in shown)
        lines.append(f"  {label(m):<{width}}  {values}")
    lines += target_lines(metrics)
    reached = ", ".join(
        f"{label(m)} {'never' if e is None else e}"
        for m, e in metrics["episodes_to_near_optimal"].items()
    )
    lines.append(f"episodes to within 10% of the true model (one crossing): {reached}")
    return lines
