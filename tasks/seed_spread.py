"""How far do an experiment's headline numbers move when only the seed changes?

    python -m tasks.seed_spread runs/paper_seed0 runs/paper_seed1 runs/paper_seed2
    python -m tasks.seed_spread runs/cp_seed* --out spread.json

Every interval a run reports is over its own trials or test settings, given one
batch of data and one fit (README, "What the numbers answer for"). Another seed
draws another batch, another fit and other trials. This reads finished folders of
one experiment (``acrobot_swingup`` or ``cartpole_prediction``) whose configs
differ only in ``seed`` (and in how the run was shown or scheduled) and gives, for
each headline number:

- per seed: the value with the run's own 95% interval, where it has one;
- ``across seeds``: the mean of the per-seed values with a Student-t 95% interval
  over seeds (the seed as the unit). Ratios are averaged on the log scale (a
  geometric mean); episode counts get their median and range;
- ``sd / SE``: the between-seed standard deviation over the median of the runs'
  own standard errors (interval half-width over its t quantile), on the same
  scale. Near 1, a run's standard error already accounts for what a new seed
  changes; well above 1, the batch and the fit move the number more than the
  run's interval shows. With few seeds it is rough: from 3 seeds the true sd is
  0.5-6.3 times the estimate (95%, chi-square with 2 df), from 5 seeds 0.6-2.9
  times. Where a run's interval is over test settings (``by_setting``, the
  prediction numbers), its SE already holds the setting-to-setting variation,
  and every seed has the same settings, so the ratio tends to be below 1 there.

MSE ratios are against one baseline per dimension for every seed: the first
run's best (lowest mean MSE), named in the row. The cart-pole's ratio of means is
then the paper's measure on the first run and comparable across seeds. Each
seed's cell gives the run's 95% percentile bootstrap over its test settings
(``mse_ratio_to_best_baseline_interval``; drawn again, from the run's seed, where
the run's own best baseline is another). A bootstrap interval gives no standard
error, so these rows have no ``sd / SE``.

The table is printed as Markdown; ``--out FILE`` also writes every value as JSON.
There an episode count of "never" (a median, minimum or maximum beyond the last
episode) is ``null``, as JSON has no infinity; ``never`` says how many seeds
never got there.

Swing-up runs with a method added (``--method NAME=...``), some from before its
``NAME - average`` pair (2026-12-05, ``tasks.compare_runs.ADDED_PAIRS``): that
pair's rows are left out for every run, and the table says so
(``not_in_every_run`` in the JSON).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from scipy import stats

from tasks.cartpole_prediction import ratio_intervals
from tasks.compare_runs import (
    PRESENTATION,
    added_methods,
    added_pairs,
    differences,
    read_run,
)
from tasks.experiment import (
    check_out_file,
    fmt_ci,
    fmt_value,
    markdown_table,
    mean_ci,
    plain_text,
    printable_output,
    write_json,
)
from tasks.prediction import best_baseline

#: Top-level config keys that may differ between the runs, besides PRESENTATION:
#: the seed, and the run's label.
LABELS = ("seed", "name")


class Headline(NamedTuple):
    """One number of a run: ``get(metrics)`` (``get(metrics, config)`` where
    ``with_config``) gives a point value, None (not available; for counts, not
    reached) or an interval ``{"mean", "low", "high", "n"}`` (``n`` None: an
    interval that gives no standard error, a bootstrap's). ``scale``: how it is
    averaged across seeds: ``"linear"``, ``"log"`` (ratios), or ``"count"``
    (episode counts: median and range)."""

    label: str
    get: Callable[..., Any]
    scale: str = "linear"
    with_config: bool = False


def _ratio(metrics: dict, baseline: str, dim: str) -> dict | None:
    r = metrics["mse_ratio_per_setting"][baseline][dim]
    if r is None:
        return None
    return {"mean": r["geometric_mean"], "low": r["low"], "high": r["high"],
            "n": r["n"]}  # fmt: skip


def _ratio_of_means(
    metrics: dict, baseline: str, dim: str, config: dict
) -> dict | float | None:
    base = metrics["mse"][baseline][dim]["mean"]
    if not base > 0:
        return None
    value = metrics["mse"]["hipmdp"][dim]["mean"] / base
    interval = _bootstrap(metrics, baseline, dim, config)
    if interval is None:
        return value
    return {"mean": value, "low": interval["low"], "high": interval["high"],
            "n": None}  # fmt: skip


def _bootstrap(metrics: dict, baseline: str, dim: str, config: dict) -> dict | None:
    """The run's 95% bootstrap interval of its ratio of means to ``baseline``
    (`tasks.cartpole_prediction.ratio_intervals`): the one it stored, where its
    own best baseline is ``baseline``; else drawn as the run drew its own, from
    its seed. None for a run from before the intervals, or without one."""
    stored = metrics.get("mse_ratio_to_best_baseline_interval")
    if not stored or "per_setting_mse" not in metrics:
        return None
    if best_baseline(metrics["mse"], dim) == baseline:
        return stored[dim]
    rng = np.random.default_rng(np.random.SeedSequence(config["seed"], spawn_key=(4,)))
    return ratio_intervals(
        metrics["per_setting_mse"], metrics["mse"], rng=rng, baselines={dim: baseline}
    )[dim]


def _ratios(
    metrics: dict, what: str, get: Callable, with_config: bool = False
) -> list[Headline]:
    """One row per dimension: ``get(m, baseline, dim)`` (``get(m, baseline, dim,
    config)`` where ``with_config``), the HiP-MDP's MSE over the dimension's best
    baseline in ``metrics`` (the first run's)."""
    return [
        Headline(
            f"HiP-MDP MSE / {b}'s, {d} ({what})",
            lambda m, *c, b=b, d=d: get(m, b, d, *c),
            "log",
            with_config,
        )
        for d in metrics["mse"]["hipmdp"]
        for b in [best_baseline(metrics["mse"], d)]
    ]


def _prediction(metrics: dict) -> list[Headline]:
    """The one-step prediction numbers both experiments report."""
    out = _ratios(metrics, "per-setting geometric mean", _ratio)
    out += [
        Headline(
            f"log-likelihood, HiP-MDP - {b}",
            lambda m, b=b: m["loglik_difference"][b],
        )
        for b in metrics["loglik_difference"]
    ]
    if metrics.get("unseen"):
        out += [
            Headline(
                f"log-likelihood on unseen settings, HiP-MDP - {b}",
                lambda m, b=b: m["unseen"]["loglik_difference"][b],
            )
            for b in metrics["unseen"]["loglik_difference"]
        ]
    return out


def _acrobot(metrics: dict) -> list[Headline]:
    methods = list(metrics["episodes_to_near_optimal"])
    out = [
        Headline(
            f"episodes to near-optimal, {m}",
            lambda x, m=m: x["episodes_to_near_optimal"][m],
            "count",
        )
        for m in methods
    ]
    if len(metrics["margin_to_target"]["hipmdp"]["mean"]) >= 2:
        out.append(
            Headline(
                "HiP-MDP margin to the 10% target, episode 2",
                lambda x: {
                    k: (v[1] if isinstance(v, list) else v)
                    for k, v in x["margin_to_target"]["hipmdp"].items()
                },
            )  # fmt: skip
        )
    for pair in metrics["paired_difference"]:
        out.append(
            Headline(
                f"return, {pair} (trials)",
                lambda x, p=pair: x["paired_difference"][p]["all_episodes"],
            )
        )
        out.append(
            Headline(
                f"return, {pair} (settings)",
                lambda x, p=pair: x["paired_difference"][p]["by_setting"],
            )
        )
    out += _prediction(metrics)
    out.append(Headline("latent features", lambda x: x["n_latent_features"]))
    return out


def _cartpole(metrics: dict) -> list[Headline]:
    out = _ratios(metrics, "ratio of means", _ratio_of_means, with_config=True)
    out += _prediction(metrics)
    out.append(
        Headline(
            "latent features (mean over fits)",
            lambda m: float(np.mean(m["n_latent_features"])),
        )  # fmt: skip
    )
    return out


#: Per experiment: a metrics.json key that only it writes, and its headline
#: numbers from one run's metrics.
EXPERIMENTS: dict[str, tuple[str, Callable[[dict], list[Headline]]]] = {
    "acrobot_swingup": ("episodes_to_near_optimal", _acrobot),
    "cartpole_prediction": ("mse_ratio_to_best_baseline", _cartpole),
}


def experiment_of(metrics: dict) -> str | None:
    """Which experiment wrote ``metrics`` (by a key only it writes; a run's
    ``name`` is its folder's label and may be anything), or None."""
    for name, (key, _) in EXPERIMENTS.items():
        if key in metrics:
            return name
    return None


def _settings(config: dict) -> dict[str, Any]:
    """A config without its LABELS (``read_run`` has given it the fields an older
    run lacks)."""
    return {k: v for k, v in config.items() if k not in LABELS}


def read_runs(
    runs: Sequence[str | Path],
) -> tuple[str, list[dict], list[dict], list[str | None]]:
    """``(experiment, configs, metrics, git commits)`` of the run folders, checked
    to be seeds of one experiment: the same experiment, configs equal but for
    LABELS and PRESENTATION (a field an older run lacks counts as its old value),
    distinct seeds. Raises ValueError naming what differs. (The commits may
    differ: :func:`report` says so.)"""
    if len(runs) < 2:
        raise ValueError(f"runs: expected at least 2 run folders, got {len(runs)}")
    read = [read_run(Path(r)) for r in runs]
    configs = [c for c, _, _ in read]
    metrics = [m for _, m, _ in read]
    commits = [(env or {}).get("git_commit") for _, _, env in read]
    kinds = [experiment_of(m) for m in metrics]
    if None not in kinds and len(set(kinds)) > 1:
        raise ValueError(
            "runs: expected runs of one experiment, got runs of "
            + " and ".join(sorted(set(kinds)))
            + ": "
            + ", ".join(f"{r}: {k}" for r, k in zip(runs, kinds, strict=True))
        )
    if len(set(kinds)) != 1 or kinds[0] is None:
        raise ValueError(
            f"runs: expected runs of one of {sorted(EXPERIMENTS)}, got "
            + ", ".join(
                f"{r}: {k or 'another'}" for r, k in zip(runs, kinds, strict=True)
            )
        )
    seeds = [c.get("seed") for c in configs]
    for run, seed in zip(runs, seeds, strict=True):
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise ValueError(
                f"{run}: config.json: expected an integer seed, got {seed!r}"
            )
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"runs: expected distinct seeds, got {seeds}")
    for run, config in zip(runs[1:], configs[1:], strict=True):
        a, b = _settings(configs[0]), _settings(config)
        differ = differences(a, b, PRESENTATION, lists=False)
        if differ:
            raise ValueError(
                f"{run}: its config differs from {runs[0]}'s in more than the seed: "
                + ", ".join(
                    f"{k} ({_at(a, k)} vs {_at(b, k)})" for k in list(differ)[:5]
                )
            )
    return kinds[0], configs, metrics, commits


def _at(config: dict, key: str) -> str:
    """The value at a dotted ``key`` of ``config`` (as
    :func:`tasks.compare_runs.flatten` names it), as repr; "absent" where the
    config has none (``differences`` gives None there, as for a null)."""
    value: Any = config
    for part in key.split("."):
        if isinstance(value, dict) and part in value:
            value = value[part]
        elif isinstance(value, list) and part.isdigit() and int(part) < len(value):
            value = value[int(part)]
        else:
            return "absent"
    return repr(value)


def _interval(value: Any, label: str, run: str) -> dict[str, Any]:
    """``{"value", "low", "high", "n"}`` (None where the run gives no interval:
    a single number, or an interval of one sample, whose bounds are null; ``n``
    None for an interval without a standard error, a bootstrap's)."""
    if isinstance(value, dict):
        try:
            if value["n"] is None:
                return {"value": float(value["mean"]), "low": float(value["low"]),
                        "high": float(value["high"]), "n": None}  # fmt: skip
            n = int(value["n"])
            bounds = [value["low"], value["high"]]
            if n < 2 and bounds == [None, None]:  # experiment.mean_ci of one sample
                return {"value": float(value["mean"]), "low": None, "high": None,
                        "n": n}  # fmt: skip
            return {"value": float(value["mean"]), "low": float(value["low"]),
                    "high": float(value["high"]), "n": n}  # fmt: skip
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(
                f"{run}: {label}: expected an interval of numbers "
                f"{{mean, low, high, n}}, got {value!r} ({err})"
            ) from None
    if value is None:
        return {"value": None, "low": None, "high": None, "n": None}
    try:
        return {"value": float(value), "low": None, "high": None, "n": None}
    except (TypeError, ValueError):
        raise ValueError(f"{run}: {label}: expected a number, got {value!r}") from None


def _across(per_seed: list[dict], scale: str) -> dict[str, Any]:
    """The per-seed values summarised over seeds (module docstring)."""
    values = [p["value"] for p in per_seed]
    if scale == "count":
        finite = sorted(v for v in values if v is not None)
        never = len(values) - len(finite)
        ordered = finite + [np.inf] * never
        return {
            "median": float(np.median(ordered)) if ordered else None,
            "min": ordered[0] if ordered else None,
            "max": ordered[-1] if ordered else None,
            "never": never,
        }
    if any(v is None for v in values):
        return {"mean": None, "low": None, "high": None, "n": len(values),
                "sd": None, "sd_over_se": None}  # fmt: skip
    f = np.log if scale == "log" else (lambda v: np.asarray(v, float))
    x = f(np.asarray(values, float))
    ci = {k: float(v) for k, v in mean_ci(x).items()}
    ses = [
        (f(p["high"]) - f(p["low"])) / 2 / stats.t.ppf(0.975, p["n"] - 1)
        for p in per_seed
        if p["low"] is not None and p["n"] is not None and p["n"] >= 2
    ]
    sd = float(np.std(x, ddof=1))
    out = {"mean": ci["mean"], "low": ci["low"], "high": ci["high"], "n": len(x)}
    if scale == "log":
        out = {k: (float(np.exp(v)) if k != "n" else v) for k, v in out.items()}
    se = float(np.median(ses)) if ses else 0.0
    out["sd"] = sd
    out["sd_over_se"] = sd / se if se > 0 else None
    return out


def _older(run: str, err: Exception, label: str = "a headline number") -> str:
    return (
        f"{run}: metrics.json lacks {label} ({err!r}); a run from an older "
        "hipmdp? Rerun it with this version"
    )


def _older_pairs(config: dict, metrics: list[dict]) -> tuple[list[dict], list[str]]:
    """The swing-up runs' metrics without the pairs added since
    (``compare_runs.ADDED_PAIRS``: ``NAME - average`` of an added method) that
    some runs have and others, older, lack; and those pairs. Their rows would
    otherwise be left out where the first run lacks them, and a later run
    lacking them refused."""
    pairs = added_pairs(added_methods(config))
    held = [
        set(m["paired_difference"]) if isinstance(m.get("paired_difference"), dict)
        else set()
        for m in metrics
    ]  # fmt: skip
    older = sorted(p for p in pairs if any(p in h for h in held) and
                   not all(p in h for h in held))  # fmt: skip
    if not older:
        return metrics, []
    return [
        m | {"paired_difference": {k: v for k, v in m["paired_difference"].items()
                                   if k not in older}}
        if isinstance(m.get("paired_difference"), dict) else m
        for m in metrics
    ], older  # fmt: skip


def main(runs: Sequence[str | Path], out: str | Path | None = None) -> dict[str, Any]:
    """Check the runs (:func:`read_runs`) and summarise their headline numbers;
    ``{"experiment", "seeds", "runs", "git_commits", "numbers": [{"label",
    "scale", "per_seed", "across_seeds"}]}`` (and ``"not_in_every_run"``, the
    pairs left out as some runs are older than them, if any). Also written as
    JSON to ``out``."""
    if out is not None:
        check_out_file(out, runs)
    runs = [str(r) for r in runs]
    name, configs, metrics, commits = read_runs(runs)
    older: list[str] = []
    if name == "acrobot_swingup":
        metrics, older = _older_pairs(configs[0], metrics)
    try:
        headlines = EXPERIMENTS[name][1](metrics[0])
    except (KeyError, IndexError, TypeError) as err:
        raise ValueError(_older(runs[0], err)) from None
    numbers = []
    for h in headlines:
        per_seed = []
        for run, m, c in zip(runs, metrics, configs, strict=True):
            try:
                value = h.get(m, c) if h.with_config else h.get(m)
            except (KeyError, IndexError, TypeError) as err:
                raise ValueError(_older(run, err, h.label)) from None
            per_seed.append(_interval(value, h.label, run))
        numbers.append({"label": h.label, "scale": h.scale, "per_seed": per_seed,
                        "across_seeds": _across(per_seed, h.scale)})  # fmt: skip
    result = {
        "experiment": name,
        "seeds": [c["seed"] for c in configs],
        "runs": runs,
        "git_commits": commits,
        "numbers": numbers,
    }
    if older:  # some runs are older than these pairs
        result["not_in_every_run"] = older
    if out is not None:
        write_json(out, result)
    return result


def _cell(p: dict[str, Any], scale: str) -> str:
    if p["value"] is None:
        return "never" if scale == "count" else "n/a"
    if scale == "count":
        return f"{p['value']:g}"
    if p["low"] is None:
        return fmt_value(p["value"])
    return fmt_ci({"mean": p["value"], "low": p["low"], "high": p["high"]})


def _across_cell(a: dict[str, Any], scale: str) -> tuple[str, str]:
    if scale == "count":
        if a["median"] is None or a["min"] == np.inf:
            return "never", ""
        top = "never" if a["max"] == np.inf else f"{a['max']:g}"
        median = "never" if a["median"] == np.inf else f"{a['median']:g}"
        return f"median {median} ({a['min']:g}-{top})", ""
    if a["mean"] is None:
        return "n/a", ""
    ratio = "" if a["sd_over_se"] is None else f"{a['sd_over_se']:.2g}"
    return fmt_ci(a), ratio


def report(result: dict[str, Any]) -> str:
    """The Markdown table of :func:`main`'s result."""
    header = ["number"] + [f"seed {s}" for s in result["seeds"]]
    header += ["across seeds", "sd / SE"]
    rows = []
    for n in result["numbers"]:
        cells = [_cell(p, n["scale"]) for p in n["per_seed"]]
        rows.append([n["label"], *cells, *_across_cell(n["across_seeds"], n["scale"])])
    commits = result.get("git_commits") or [None] * len(result["runs"])
    code = ""
    if len(set(commits)) > 1:  # a difference between seeds may be one of code
        made = ", ".join(
            f"{run}: {c[:8] if c else 'not recorded'}"
            for run, c in zip(result["runs"], commits, strict=True)
        )
        code = f"Note: the runs were made at different commits ({made}).\n\n"
    if result.get("not_in_every_run"):
        code += (
            "Note: left out, as some runs are older than them: "
            + ", ".join(result["not_in_every_run"])
            + ".\n\n"
        )
    return (
        f"{result['experiment']}: {len(result['seeds'])} seeds "
        f"({', '.join(result['runs'])})\n\n"
        + code
        + few_seeds(len(result["seeds"]))
        + markdown_table(header, rows)
    )


def few_seeds(n: int) -> str:
    """A note on how wide the across-seeds intervals are with ``n`` < 5 seeds
    (the Student-t quantile grows fast as degrees of freedom fall); "" from 5."""
    if n >= 5:
        return ""
    t, t5 = stats.t.ppf(0.975, n - 1), stats.t.ppf(0.975, 4)
    return (
        f"Note: with {n} seeds an across-seeds interval is the mean ± {t:.3g} "
        f"standard errors (Student t, {n - 1} degree{'s' * (n > 2)} of freedom), "
        f"so it is wide; 5 seeds give ± {t5:.3g}.\n\n"
    )


def cli(argv: list[str] | None = None) -> int:
    printable_output()
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m tasks.seed_spread",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("runs", nargs="+", help="finished run folders, one per seed")
    parser.add_argument("--out", default=None, help="also write the result as JSON")
    args = parser.parse_args(argv)
    try:
        result = main(args.runs, out=args.out)
    except (ValueError, FileNotFoundError) as err:
        parser.error(str(err))
    print(report(result))
    return 0


if __name__ == "__main__":
    sys.exit(cli())
