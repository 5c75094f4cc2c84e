"""One-step prediction on new instances: the HiP-MDP against three GP baselines.

The paper's Table 1 protocol. For each evaluation instance: gather transitions along
trajectories (a Sarsa(λ) agent learning on the instance, as the batch data were
gathered), split them at random into ``n_train`` transitions that the methods may
use and ``n_test`` held-out ones, and score each method's predicted ``Δs`` on the
held-out ones:

- ``hipmdp``: the weight belief filtered on the train transitions (with several
  independently fitted models — the paper's repeated MCMC runs — the scores are
  averaged over them; feature labels differ between runs, scores do not);
- ``batch only``: one GP on all batch data (the average model; the same for every
  instance);
- ``train only``: one GP on the instance's train transitions (its own
  hyperparameters, fitted on those);
- ``batch + train``: one GP on batch and train data (the batch-only model's
  hyperparameters; every train transition kept).

Reported per output dimension: mean-squared error with a 95% interval over
evaluation instances, the test log-likelihood difference to the HiP-MDP, and the
coverage of each method's central 50% and 95% predictive intervals (how far the
predictive variance the log-likelihood rests on matches the errors). Run on
training instances the same protocol gives the approximation floor (DESIGN §7): the
error a method makes on instances it was fitted on.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import Any, NamedTuple

import numpy as np

from hipmdp import baselines
from hipmdp.data import Transitions, gaussian_loglik
from tasks.agents import Domain, learn
from tasks.experiment import fmt_bounds, fmt_ci, markdown_table, mean_ci

Array = np.ndarray

PREDICTION_METHODS = ("hipmdp", "batch only", "train only", "batch + train")
#: Central predictive intervals whose coverage is reported (:func:`coverage`).
COVERAGE_LEVELS = (0.5, 0.95)
#: How a test setting's gathered transitions are split (:func:`gather_split`).
SPLITS = ("random", "time")


def entity(method: str) -> str:
    """A method's name in recordings' entity paths ("batch + train" ->
    "batch_train"); no two methods of a run share one (``tasks.methods``)."""
    return method.replace(" + ", "_").replace(" ", "_")


def check_split(split: str) -> None:
    """Raise ValueError unless ``split`` is one of SPLITS."""
    if split not in SPLITS:
        raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")


def add_split_argument(parser) -> None:
    """The experiments' ``--split`` flag (default None: the preset's, random)."""
    parser.add_argument(
        "--split",
        choices=SPLITS,
        default=None,
        help="train/test split of each test setting's transitions: random (our "
        "reading of the paper's; default) or time (the first to train on, the "
        "last to test on)",
    )


class InstanceScores(NamedTuple):
    """Scores on one instance: ``mse[method]`` shape (D,), ``loglik[method]`` (sum
    over held-out transitions), ``coverage[method]`` shape (len(COVERAGE_LEVELS),
    D) (:func:`coverage`)."""

    mse: dict[str, Array]
    loglik: dict[str, float]
    coverage: dict[str, Array]


def coverage(
    mean: Array, var: Array, observed: Array, levels: Sequence[float] = COVERAGE_LEVELS
) -> Array:
    """Share of ``observed`` (n, D) inside the central Gaussian predictive interval
    ``mean ± z·sqrt(var)`` of each level (z the standard normal's quantile at
    ``(1 + level) / 2``), per dimension: shape (len(levels), D). Above the level,
    the predictive variance is wider than the errors; below it, narrower.

    Raises:
        ValueError: unless ``mean``, ``var`` and ``observed`` have one shape
            (n, D), ``var > 0`` and every level is in (0, 1).
    """
    from scipy.stats import norm

    levels = np.asarray(levels, dtype=float)
    if levels.ndim != 1 or not np.all((levels > 0) & (levels < 1)):
        raise ValueError(f"levels: expected values in (0, 1), got {levels.tolist()}")
    mean, var, observed = (np.asarray(x, dtype=float) for x in (mean, var, observed))
    if mean.ndim != 2 or not mean.shape == var.shape == observed.shape:
        raise ValueError(
            "mean, var, observed: expected one shape (n, D), got "
            f"{mean.shape}, {var.shape}, {observed.shape}"
        )
    if not np.all(var > 0):
        raise ValueError("var: expected values > 0")
    z = norm.ppf((1 + levels) / 2)
    scaled = np.abs(observed - mean) / np.sqrt(var)
    return np.mean(scaled[None] <= z[:, None, None], axis=1)


class Split(NamedTuple):
    """Train and held-out test transitions of one instance, and all gathered ones."""

    train: Transitions
    test: Transitions
    episodes: Transitions


def gather_split(
    domain: Domain,
    params: Any,
    n_train: int,
    n_test: int,
    *,
    rng: np.random.Generator,
    n_episodes: int = 3,
    max_steps: int | None = None,
    max_episodes: int = 500,
    split: str = "random",
) -> Split:
    """Transitions along Sarsa trajectories on ``params``, split at random (our
    reading of the paper's "50 (different) test points", whose choice it does not
    describe) or, with ``split="time"``, in time: the
    first ``n_train`` transitions to train on and the last ``n_test`` to test on,
    so that no test transition has a train transition a step away (unless
    exactly ``n_train + n_test`` were gathered) and the test is a prediction of
    the instance's later behaviour.

    One agent learns for at least ``n_episodes`` episodes, and on (an episode at a
    time) until it has seen ``n_train + n_test`` transitions: a fresh cart-pole
    agent's first episodes last a dozen steps.

    Returns a :class:`Split`: ``n_train`` and ``n_test`` disjoint transitions and
    all the gathered transitions (``episodes``, in time order).

    Raises:
        ValueError: if ``max_episodes`` episodes are not enough.
    """
    check_split(split)
    env_seed, agent_seed, split_seed = np.random.SeedSequence(
        int(rng.integers(2**63))
    ).spawn(3)
    env = domain.make_env(
        params,
        seed=np.random.default_rng(env_seed),
        max_steps=max_steps or domain.max_steps,
    )
    agent_rng = np.random.default_rng(agent_seed)
    result = learn(env, domain, n_episodes, rng=agent_rng)
    parts, seen, episodes = [result.transitions], len(result.transitions), n_episodes
    while seen < n_train + n_test and episodes < max_episodes:
        result = learn(env, domain, 1, rng=agent_rng, state=result.state)
        parts.append(result.transitions)
        seen, episodes = seen + len(result.transitions), episodes + 1
    if seen < n_train + n_test:
        raise ValueError(
            f"n_train + n_test: {n_train + n_test} transitions asked, only {seen}"
            f" gathered in {episodes} episodes"
        )
    data = Transitions.concatenate(parts)
    if split == "time":
        n = len(data)
        train, test = np.arange(n_train), np.arange(n - n_test, n)
        return Split(data.take(train), data.take(test), data)
    order = np.random.default_rng(split_seed).permutation(len(data))
    return Split(
        data.take(order[:n_train]), data.take(order[n_train : n_train + n_test]), data
    )


def score_instance(
    hips: Sequence,
    average: baselines.GPBaseline,
    batch: Transitions,
    train: Transitions,
    test: Transitions,
    *,
    rng: np.random.Generator,
    n_max: int = 2000,
    added: Sequence[Any] = (),
    key: tuple[int, ...] = (0, 0),
) -> InstanceScores:
    """MSE per dimension, test log-likelihood and predictive-interval coverage
    (:func:`coverage`) of every method on ``test``.

    ``hips``: one or more fitted HiP-MDPs; their scores are averaged (its
    coverage is the mean of each fit's, not that of their mixture). ``added``:
    fitted methods added with ``--method`` (``tasks.methods.Added``), scored after
    the built-in ones with their own streams (``key``: (table, setting)), so
    ``rng`` and the built-in scores do not depend on them.
    """
    # every GP measures angles as the average model does (FitConfig.periodic)
    train_gp = baselines.train_only(
        train, rng=rng, n_actions=average.n_actions, periodic=average.hyper.periodic
    )
    both_gp = baselines.batch_plus_train(
        batch, train, rng=rng, hyper=average.hyper, n_max=n_max
    )
    beliefs = [hip.update(hip.prior(), train) for hip in hips]
    predictions = {  # (mean, variance) of Δs
        "batch only": average.predict(test.states, test.actions),
        "train only": train_gp.predict(test.states, test.actions),
        "batch + train": both_gp.predict(test.states, test.actions),
    }
    hip_predictions = [
        h.predict(test.states, test.actions, b)
        for h, b in zip(hips, beliefs, strict=True)
    ]
    loglik = {
        "hipmdp": float(
            np.mean(
                [h.log_likelihood(test, b) for h, b in zip(hips, beliefs, strict=True)]
            )
        ),
        "batch only": float(average.log_likelihood(test)),
        "train only": float(train_gp.log_likelihood(test)),
        "batch + train": float(both_gp.log_likelihood(test)),
    }
    deltas = test.deltas
    for method in added:
        mean, var = method.predict(train, test, key)
        predictions[method.name] = mean, var
        loglik[method.name] = gaussian_loglik(deltas, mean, var)
    mse = {m: np.mean((p - deltas) ** 2, axis=0) for m, (p, _) in predictions.items()}
    mse["hipmdp"] = np.mean(
        [np.mean((p - deltas) ** 2, axis=0) for p, _ in hip_predictions], axis=0
    )
    covered = {m: coverage(p, v, deltas) for m, (p, v) in predictions.items()}
    covered["hipmdp"] = np.mean(
        [coverage(p, v, deltas) for p, v in hip_predictions], axis=0
    )
    return InstanceScores(mse=mse, loglik=loglik, coverage=covered)


def summarise(
    scores: Sequence[InstanceScores],
    dim_names: Sequence[str],
    seen: Sequence[bool] | None = None,
) -> dict[str, Any]:
    """Intervals over instances (the unit is the test setting): ``mse[method][dim]``,
    ``loglik_difference[method]`` (HiP-MDP minus method; > 0 favours the HiP-MDP)
    and ``coverage[method][level][dim]`` (level as ``"0.95"``; the share of
    held-out Δ inside the central predictive interval), and ``per_instance``, the
    same values setting by setting. ``per_setting_mse[method]`` (setting,
    dimension) and ``per_setting_loglik[method]`` (setting; the test log-likelihood
    in nats, summed over the setting's held-out Δ) are what metrics.json stores,
    so that two runs on the same settings can be compared setting by setting.

    ``seen[i]``: whether instance i has the parameters of a training instance (the
    test grids include the training settings, as in the paper). Given, the result
    also has ``seen`` and ``unseen``: the intervals on the other settings alone
    (None if there are none), the claim about parameters never seen in training.

    The methods are the built-in ones and those added with ``--method``, as
    every score has them.
    """
    added = [
        m for m in (scores[0].mse if scores else ()) if m not in PREDICTION_METHODS
    ]
    methods = [*PREDICTION_METHODS, *added]
    for s in scores:
        if set(s.mse) != set(methods):
            raise ValueError(
                f"scores: expected the methods {methods} on every instance, "
                f"got {list(s.mse)}"
            )
    per_instance = {
        "mse": {
            m: {name: [float(s.mse[m][d]) for s in scores]
                for d, name in enumerate(dim_names)}
            for m in methods
        },
        "loglik_difference": {
            m: [float(s.loglik["hipmdp"] - s.loglik[m]) for s in scores]
            for m in methods
            if m != "hipmdp"
        },
        "coverage": {
            m: {f"{level:g}": {name: [float(s.coverage[m][k, d]) for s in scores]
                               for d, name in enumerate(dim_names)}
                for k, level in enumerate(COVERAGE_LEVELS)}
            for m in methods
        },
    }  # fmt: skip
    out = _intervals(per_instance, range(len(scores)))
    out["per_instance"] = per_instance
    out["per_setting_mse"] = {  # [setting][dimension], as metrics.json stores it
        m: [s.mse[m].tolist() for s in scores] for m in methods
    }
    out["per_setting_loglik"] = {  # [setting], nats; the HiP-MDP's: mean over fits
        m: [float(s.loglik[m]) for s in scores] for m in methods
    }
    out["mse_ratio_per_setting"] = mse_ratios(per_instance["mse"])
    if seen is not None:
        seen = [bool(x) for x in seen]
        if len(seen) != len(scores):
            raise ValueError(f"seen: expected {len(scores)} flags, got {len(seen)}")
        others = [i for i, x in enumerate(seen) if not x]
        out["seen"] = seen
        out["unseen"] = _intervals(per_instance, others) if others else None
    return out


def mse_ratios(per_setting: dict[str, dict[str, list[float]]]) -> dict[str, Any]:
    """The HiP-MDP's MSE over each baseline's, setting by setting, per dimension:
    the geometric mean of the per-setting ratios with a 95% interval (a t-interval
    on their logs, the setting as the unit), and on how many settings the
    HiP-MDP is lower. Paired, and not led by the settings with the largest MSE,
    as a ratio of mean MSEs is. ``per_setting[method][dimension]``: MSEs."""
    hip = per_setting["hipmdp"]
    out: dict[str, Any] = {}
    for m, dims in per_setting.items():
        if m == "hipmdp":
            continue
        out[m] = {}
        for d, base in dims.items():
            a, b = np.asarray(hip[d], float), np.asarray(base, float)
            ok = (a > 0) & (b > 0)
            if not ok.any():
                out[m][d] = None
                continue
            ci = mean_ci(np.log(a[ok] / b[ok]))
            out[m][d] = {
                "geometric_mean": float(np.exp(ci["mean"])),
                "low": float(np.exp(ci["low"])),
                "high": float(np.exp(ci["high"])),
                "n": int(ok.sum()),
                "hipmdp_lower": int(np.sum(a[ok] < b[ok])),  # of the n
            }
    return out


def _intervals(per_instance: dict[str, Any], rows: Sequence[int]) -> dict[str, Any]:
    """``mse``, ``loglik_difference`` and ``coverage`` intervals over the
    instances ``rows``."""
    rows = list(rows)
    return {
        "mse": {
            m: {name: mean_ci(np.asarray(v)[rows]) for name, v in dims.items()}
            for m, dims in per_instance["mse"].items()
        },
        "loglik_difference": {
            m: mean_ci(np.asarray(v)[rows])
            for m, v in per_instance["loglik_difference"].items()
        },
        "coverage": {
            m: {
                level: {name: mean_ci(np.asarray(v)[rows]) for name, v in dims.items()}
                for level, dims in levels.items()
            }
            for m, levels in per_instance["coverage"].items()
        },
        "n_instances": len(rows),
    }


def score_settings(
    domain: Domain,
    hips: Sequence,
    average: baselines.GPBaseline,
    batch: Transitions,
    instances: Sequence[Any],
    *,
    n_train: int,
    n_test: int,
    seed: np.random.SeedSequence,
    split: str = "random",
    desc: str = "prediction",
    progress: bool = False,
    added: Sequence[Any] = (),
    table: int = 0,
    n_episodes: int = 3,
    n_max: int = 2000,
    splits: list[Split] | None = None,
) -> list[InstanceScores]:
    """:func:`gather_split` (with ``split`` and ``n_episodes``) and
    :func:`score_instance` (with ``n_max``) on each instance in turn, each with
    its own stream spawned from ``seed``; ``added`` methods are scored with keys
    ``(table, i)`` for instance ``i``. Each instance's split is appended to
    ``splits`` where given."""
    from tqdm.auto import tqdm

    scores = []
    streams = seed.spawn(len(instances))
    for i, (params, stream) in enumerate(
        zip(tqdm(instances, desc=desc, disable=not progress), streams, strict=True)
    ):
        rng = np.random.default_rng(stream)
        parts = gather_split(
            domain, params, n_train, n_test, rng=rng, n_episodes=n_episodes,
            split=split,
        )  # fmt: skip
        if splits is not None:
            splits.append(parts)
        try:
            scores.append(
                score_instance(
                    hips,
                    average,
                    batch,
                    parts.train,
                    parts.test,
                    rng=rng,
                    n_max=n_max,
                    added=added,
                    key=(table, i),
                )
            )
        except Exception as err:  # which setting, to find it again
            err.add_note(
                f"(scoring {desc}: setting {i} of 0-{len(instances) - 1}, {params}; "
                f"{len(parts.train)} train and {len(parts.test)} test transitions)"
            )
            raise
    return scores


def mse_table(mse: dict[str, Any]) -> str:
    """``mse[method][dimension]`` intervals as a markdown table; a t-interval
    that reaches below 0, which an MSE cannot, is marked † and explained under
    the table."""

    def cell(ci: dict[str, Any]) -> str:
        return fmt_ci(ci) + (" †" if ci["low"] < 0 else "")

    dims = list(next(iter(mse.values())))
    table = markdown_table(
        ["method", *dims], [[m] + [cell(mse[m][d]) for d in dims] for m in mse]
    )
    if not any(mse[m][d]["low"] < 0 for m in mse for d in dims):
        return table
    return (
        f"{table}\n\n† The intervals are Student-t over settings; one that reaches "
        "below 0 means a few settings carry most of that mean, and it says little. "
        "The per-setting ratios are the better guide there."
    )


def coverage_table(coverage: dict[str, Any], levels: list[str]) -> str:
    """``coverage[method][level][dimension]`` intervals as a markdown table: per
    dimension, each level's mean share over settings, levels joined by " / "."""
    dims = list(coverage[next(iter(coverage))][levels[0]])
    return markdown_table(
        ["method", *dims],
        [
            [m] + [" / ".join(f"{c[lv][d]['mean']:.2f}" for lv in levels) for d in dims]
            for m, c in coverage.items()
        ],
    )


def coverage_text(coverage: dict[str, Any] | None) -> str:
    """The coverage table with what it measures, or "" for a run without it."""
    if not coverage:
        return ""
    levels = list(next(iter(coverage.values())))
    pct = " / ".join(f"{float(lv):.0%}" for lv in levels)
    nominal = " / ".join(f"{float(lv):.2f}" for lv in levels)
    return f"""Share of the held-out Δ inside each method's central {pct} Gaussian
predictive intervals (mean over settings, and over fits for the HiP-MDP; with
95% t-intervals over settings in `metrics.json`, `coverage`). A calibrated
predictive gives {nominal}; above: the predictive variance is wider than the
errors; below: narrower. The log-likelihoods rest on these variances.

{coverage_table(coverage, levels)}"""


def unseen_section(metrics: dict[str, Any]) -> str:
    """The MSE table and log-likelihood differences on the test settings whose
    parameters no training instance has (the test grids include the training
    settings, as in the paper)."""
    seen, unseen = metrics.get("test_settings_seen"), metrics.get("unseen")
    if seen is None:
        return ""
    n_seen = sum(seen)
    head = (
        f"{n_seen} of the {len(seen)} test settings are training settings (the "
        "HiP-MDP has their dynamics among its training instances)."
    )
    if unseen is None:
        return head + " No test setting is new."
    if n_seen == 0:  # the tables above are the new settings' already
        return (
            f"None of the {len(seen)} test settings is a training setting: the "
            "tables above are all on settings the HiP-MDP was not trained on."
        )
    ll = markdown_table(
        ["method", "difference"],
        [[m, fmt_ci(v)] for m, v in unseen["loglik_difference"].items()],
    )
    ratios = unseen.get("mse_ratio_to_best_baseline")
    ratio_text = (
        "\n\nHiP-MDP MSE divided by the best baseline's there: "
        + ", ".join(
            f"{d} {v:.2g}" if v is not None else f"{d} —" for d, v in ratios.items()
        )
        + "."
        if ratios
        else ""
    )
    return f"""{head} On the {unseen["n_instances"]} others alone: the MSE,

{mse_table(unseen["mse"])}

then the test log-likelihood, HiP-MDP minus method:

{ll}{ratio_text}"""


def added_text(methods: Sequence[str], policies: Collection[str] = ()) -> str:
    """A paragraph naming the methods added with ``--method`` ("" if none), to
    put before a table; the names in ``policies`` are said to be policies, which
    no prediction table scores."""
    if not methods:
        return ""
    policy = ", a policy, so not in the prediction tables"
    named = ", ".join(
        f"{name} (`{target}`{policy if name in policies else ''})"
        for name, _, target in (m.partition("=") for m in methods)
    )
    return (
        f"Added with `--method` (see `tasks/methods.py`): {named}. The best "
        "baseline below is the best of the paper's three.\n\n"
    )


def fit_options_text(fit) -> str:
    """A sentence per choice of the fit (``hipmdp.FitConfig``) that a run's
    flags changed from the default ("" if none), for its report."""
    out = []
    if fit.filter_weights == "training":
        out.append(
            "The filter takes its model-error factor at the squared training "
            "weights' average, not at the prior mean (`--filter-weights training`)."
        )
    if fit.new_features == "multiple_try":
        out.append(
            "The sampler takes the multiple-try new-feature step, exact at any "
            "number N_w of weight draws, not the paper's "
            "(`--new-features multiple_try`)."
        )
    return " ".join(out)


def best_baseline(mse: dict[str, Any], dimension: str) -> str:
    """The paper's baseline (one of ``PREDICTION_METHODS`` other than the HiP-MDP)
    with the lowest mean MSE on ``dimension`` (``mse[method][dim]`` intervals, as
    :func:`summarise` gives them). Methods added with ``--method`` are not
    candidates, so the headline ratio means the same in every run."""
    return min(
        (m for m in PREDICTION_METHODS[1:] if m in mse),
        key=lambda m: mse[m][dimension]["mean"],
    )


def ratio_text(table: dict[str, Any]) -> str:
    """One line per dimension: the HiP-MDP's per-setting MSE ratio to the best
    baseline (lowest mean MSE) of that dimension, as :func:`mse_ratios` gives it."""
    mse, ratios = table["mse"], table.get("mse_ratio_per_setting")
    if not ratios:
        return ""
    lines = []
    for d in mse["hipmdp"]:
        best = best_baseline(mse, d)
        r = ratios[best][d]
        if r is None:
            continue
        lines.append(
            f"- {d}: {r['geometric_mean']:.3g} "
            f"{fmt_bounds(r['low'], r['high'], lambda v: f'{v:.3g}')} "
            f"against {best}; lower on {r['hipmdp_lower']} of {r['n']} settings"
        )
    return (
        "HiP-MDP MSE over the best baseline's, setting by setting (geometric mean "
        "[95% interval over settings]):\n\n" + "\n".join(lines)
    )
