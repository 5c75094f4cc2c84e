"""Did a rerun reproduce a run, and if not, where do the two part?

    python -m tasks.compare_runs runs/acrobot_swingup runs/my_rerun [--show 10]

Reads two finished experiment folders (any experiment: they need ``config.json``
and ``metrics.json``; a ``tasks.acrobot_refit`` folder, ``config.json`` alone) and
reports, from the first place results can part to the last:

1. ``config``: the settings whose values differ (a different config is a
   different experiment, not a failed reproduction);
2. ``environment``: what ran (``metrics.json``'s ``environment``: versions, git
   commit, CPU, SIMD and BLAS kernels) where it differs, or ``unrecorded`` for
   a run from before it was recorded;
3. ``arrays``: every array of every ``.npz`` file that both folders hold (the
   batch data, the fitted models, ``trials.npz``): identical, or the largest
   absolute difference, or the shapes and how the entries both hold compare;
4. ``metrics``: the values in ``metrics.json`` (timings and environment aside)
   that both runs have and that differ, summarised per top-level key by count
   and largest relative difference (every value, with both sides, in
   ``--out``). A metric added since (``ADDED_METRICS``) that one run has and the
   other lacks is named, not compared: the run without it is taken to be older
   than the metric; so is a pair added since (``ADDED_PAIRS``: ``NAME -
   average``) of a method both runs added.
5. ``extra``: the entries of a method one run added (``--method``, named in its
   config) and the other did not: its metric values (counted per top-level key)
   and its rows of ``trials.npz`` (compared on the methods both runs ran). The
   verdict is then "identical where both runs have results" when everything
   else is identical. Anything else one run lacks is a difference, a method
   in one ``trials.npz`` alone that its run's config does not name as added
   included (``methods_differ``).

Settings that only change how a run is shown or scheduled (``progress``,
``workers``, ``record``) are not counted as differences.

Identical configs and environments should give identical arrays and metrics
(README, Reproducibility). Where only the environment differs, round-off is the
likely cause: the fitted model parts by ~1e-10 and the learned models' control
returns by as much as the swing-up's chaos allows, while data and the true
simulator's returns stay identical. The comparison is also written as JSON with
``--out FILE``. The exit status is diff's: 0 when the verdict is identical (where
both runs have results), 1 when the results differ, 2 for a usage error.
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from hipmdp.data import load_npz
from tasks.experiment import (
    ADDED_FIT_FIELDS,
    check_out_file,
    plain_text,
    printable_output,
    read_json_object,
    sort_blas,
    with_added_fields,
    write_json,
)

#: Metrics that say how long a run took, never what it found.
IGNORED_METRICS = ("seconds",)
#: Metrics added to metrics.json since the first runs: where one run has one and
#: the other (written before it existed) lacks it, it is not compared, and the
#: report says so.
ADDED_METRICS = ("per_setting_loglik", "mse_ratio_to_best_baseline_interval")
#: Built-in methods that an added method (``--method``) has been paired with
#: since the first runs: ``NAME - average`` (2026-12-05). Where one run has such
#: a pair of a method both runs added and the other run lacks it, it is not
#: compared, as an ``ADDED_METRICS`` metric.
ADDED_PAIRS = ("average",)
#: Settings that change how a run is shown or scheduled, never its results.
PRESENTATION = ("progress", "workers", "record")


class Comparison(NamedTuple):
    """What :func:`main` returns; each field as in the module docstring.

    ``config``, ``environment`` and ``metrics`` map a dotted key to ``[a, b]``;
    ``arrays`` maps ``file:array`` to ``"identical"``, ``{"max_abs_diff": x,
    "n_differ": k, "size": n}`` (numbers), ``{"json": differences}`` (a JSON
    string) or ``{"shapes": [a, b], "overlap": ...}`` (``compare_arrays``), or
    for a file's ``methods`` where the two runs ran different ones,
    ``{"methods_only_in": [a's, b's]}`` (the file's other arrays with a row per
    method are then compared on the shared methods);
    ``only_in`` lists the ``.npz`` files that one folder has and the other lacks;
    ``extra``, per run folder, the metric keys (dotted) that only it has;
    ``not_compared``, the metrics (of ``ADDED_METRICS``) and the pairs (of
    ``ADDED_PAIRS``, dotted up to the pair) that one run has and the other, older
    one lacks.
    """

    config: dict[str, list]
    environment: dict[str, list] | str
    arrays: dict[str, Any]
    metrics: dict[str, list]
    only_in: dict[str, list[str]]
    not_compared: tuple[str, ...] = ()
    extra: dict[str, list[str]] = {}

    @property
    def shared_identical(self) -> bool:
        """Every file, array and metric equal but an added method's (config and
        environment aside): the methods both runs ran gave the same results."""
        return (
            not self.metrics
            and not any(self.only_in.values())
            and all(v == "identical" or _is_extra(v) for v in self.arrays.values())
        )

    @property
    def identical(self) -> bool:
        """Every array and every metric equal, and neither run has more (config
        and environment aside)."""
        return (
            self.shared_identical
            and not any(self.extra.values())
            and all(v == "identical" for v in self.arrays.values())
        )


def _is_extra(value: Any) -> bool:
    """An ``arrays`` entry that says what one run has more, not a difference."""
    return isinstance(value, dict) and "methods_only_in" in value


def added_methods(config: dict) -> set[str]:
    """The names of the methods a run added (``--method NAME=module:attribute``)."""
    return {str(spec).split("=", 1)[0] for spec in config.get("methods") or ()}


def _missing_part(key: str, matches, other: dict) -> str | None:
    """Walk the dotted metric ``key``, which one run has, through ``other`` (the
    other run's metrics) to the first part that ``matches``: ``key`` up to that
    part if ``other`` holds the dict it would be a key of, without it; None if
    no part matches, or ``other`` parts from ``key`` before one does (a shorter
    list, a None for a dict: a difference)."""
    parts = key.split(".")
    node: Any = other
    for i, part in enumerate(parts):
        if not isinstance(node, dict):
            return None
        if matches(part):
            return ".".join(parts[: i + 1]) if part not in node else None
        if part not in node:
            return None
        node = node[part]
    return None


def _method_entry(key: str, methods: set[str], other: dict) -> bool:
    """Whether the dotted metric ``key``, which one run has and ``other`` (the
    other run's metrics) lacks, is an entry of a method only the first run
    added: a part of it names one of ``methods`` (alone, or in a pair ``x -
    y``) and ``other`` holds the dict that part would be a key of, without it.
    Anything else one run lacks (a shorter list, a None for a dict) is a
    difference."""

    def named(part: str) -> bool:
        return part in methods or any(x in methods for x in part.split(" - "))

    return bool(methods) and _missing_part(key, named, other) is not None


def added_pairs(methods) -> set[str]:
    """The pairs (``ADDED_PAIRS``) that runs made since pair ``methods`` (added
    ones' names) with: ``{"NAME - average", ...}``."""
    return {f"{m} - {b}" for m in methods for b in ADDED_PAIRS}


def _added_pair(key: str, methods: set[str], other: dict) -> str | None:
    """If the dotted metric ``key``, which one run has and ``other`` (the other
    run's metrics) lacks, is in a pair added since (``ADDED_PAIRS``) of one of
    ``methods`` (added by both runs), and ``other`` holds the dict that pair
    would be a key of, without it: ``key`` up to the pair
    (``"paired_difference.NAME - average"``). Else None."""
    return _missing_part(key, added_pairs(methods).__contains__, other)


def flatten(x: Any, prefix: str = "", lists: bool = True) -> dict[str, Any]:
    """Nested dicts and lists as ``{"a.b.0": leaf}``; with ``lists=False`` a list
    is a leaf (``{"a.b": [...]}``)."""
    if isinstance(x, dict) and x:
        items = x.items()
    elif isinstance(x, list) and x and lists:
        items = enumerate(x)
    else:  # a leaf, or an empty container (kept: {"a": []} is not {})
        return {prefix: x}
    out: dict[str, Any] = {}
    for k, v in items:
        out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k), lists))
    return out


def differences(
    a: dict, b: dict, skip: tuple[str, ...] = (), lists: bool = True
) -> dict[str, list]:
    """Dotted keys whose leaves differ, ``[a's, b's]`` (None where absent), as
    :func:`flatten` names them (with ``lists=False``, a list is one value:
    ``methods: [[], ["x=m:A"]]``); keys whose last part is in ``skip`` are left
    out."""
    fa, fb = flatten(a, lists=lists), flatten(b, lists=lists)
    return {
        k: [fa.get(k), fb.get(k)]
        for k in sorted(fa.keys() | fb.keys())
        if fa.get(k) != fb.get(k) and k.rsplit(".", 1)[-1] not in skip
    }


def _read_json(run: Path, name: str, required: bool = True) -> dict:
    path = run / name
    if not path.is_file():
        if not required:
            return {}
        raise FileNotFoundError(f"{run}: no {name}; expected a finished run folder")
    return read_json_object(path)  # an error names the file


def read_run(run: Path) -> tuple[dict, dict, dict | None]:
    """``(config, metrics, environment)`` of a run folder; an experiment's config
    lacking fields added since gets their old values (``with_added_fields``). A
    refit folder (``tasks.acrobot_refit``) has no metrics.json and keeps its
    environment in ``config["refit"]``; timings and the environment are taken out
    of both."""
    config = _read_json(run, "config.json")
    if "seed" in config and "fit" in config:  # an experiment's, as its fields say
        config = with_added_fields(config)  # what an older run's missing ones were
    metrics = _read_json(run, "metrics.json", required="refit" not in config)
    env = metrics.pop("environment", None)
    if "refit" in config:
        if not isinstance(config["refit"], dict):
            raise ValueError(f"{run / 'config.json'}: refit: expected an object")
        env = config["refit"].pop("environment", env)
    if env is not None and not isinstance(env, dict):  # was an AttributeError
        where = "config.json: refit." if "refit" in config else "metrics.json: "
        raise ValueError(f"{run / where}environment: expected an object")
    if env and isinstance(env.get("blas"), list):  # a run before the order was fixed
        env["blas"] = sort_blas(env["blas"])
    for key in IGNORED_METRICS:
        metrics.pop(key, None)
    return config, metrics, env


def compare_arrays(a: np.ndarray, b: np.ndarray) -> Any:
    """``"identical"`` (NaN equal to NaN), or how the two differ: the shapes,
    with, where both have the same number of axes and some entries, the leading
    block both hold (``overlap``: its shape and this comparison of it; rows
    line up only where both runs gave them the same seeds: a rerun with other
    ``--trials`` runs other trials on every setting but the first, README
    Reproducibility); the dtypes, where they cannot be compared;
    the JSON settings, for a JSON string; else the largest absolute difference
    (float64; over the entries that are numbers in both) and how many entries
    differ, NaN placement included."""
    if a.shape != b.shape:
        out: dict[str, Any] = {"shapes": [list(a.shape), list(b.shape)]}
        if a.ndim == b.ndim and a.ndim and min(a.shape + b.shape):
            common = tuple(min(m, n) for m, n in zip(a.shape, b.shape, strict=True))
            block = tuple(slice(n) for n in common)
            out["overlap"] = {
                "shape": list(common),
                "comparison": compare_arrays(a[block], b[block]),
            }
        return out
    if a.dtype.kind == "U" and b.dtype.kind == "U" and a.ndim == 0:
        try:  # a JSON string, e.g. a model's metadata: compare its settings
            ja, jb = json.loads(str(a)), json.loads(str(b))
        except json.JSONDecodeError:
            ja, jb = str(a), str(b)
        if isinstance(ja, dict) and isinstance(jb, dict):
            ja, jb = _model_meta(ja), _model_meta(jb)
            ja, jb = _without_one_sided_records(ja, jb)
            diff = differences(ja, jb, PRESENTATION)
            return "identical" if not diff else {"json": diff}
    numeric = a.dtype.kind in "iufcb" and b.dtype.kind in "iufcb"
    if not numeric and (
        a.dtype.kind != b.dtype.kind or a.dtype.kind == "V" and a.dtype != b.dtype
    ):
        return {"dtypes": [str(a.dtype), str(b.dtype)]}
    if np.array_equal(a, b, equal_nan=numeric and a.dtype.kind in "fc"):
        return "identical"
    out = _count(a, b)
    if numeric:
        kind = complex if "c" in (a.dtype.kind + b.dtype.kind) else np.float64
        x, y = a.astype(kind), b.astype(kind)
        both = ~(np.isnan(x) | np.isnan(y))
        diff = np.abs(x[both] - y[both])
        out = {"max_abs_diff": float(diff.max()) if diff.size else 0.0} | out
    return out


def _model_meta(meta: dict) -> dict:
    """A HiP-MDP model file's metadata (``HipMDP.save``) with the fields an older
    model lacks at the values it ran with, as ``hipmdp.load`` reads them; any
    other JSON as it is."""
    if "format_version" not in meta or not isinstance(meta.get("info"), dict):
        return meta
    out = {"filter_weights": ADDED_FIT_FIELDS["filter_weights"], **meta}
    config = meta["info"].get("config")
    if isinstance(config, dict):
        out["info"] = {**meta["info"], "config": {**ADDED_FIT_FIELDS, **config}}
    return out


#: Records of a model's ``info`` that describe its data, not how it behaves,
#: added since some models were saved: compared where both models have them (two
#: runs' batch data are compared in ``batch.npz`` anyway), else left out.
ADDED_RECORDS = ("data_sha256",)


def _without_one_sided_records(a: dict, b: dict) -> tuple[dict, dict]:
    """Two model metadata with the :data:`ADDED_RECORDS` that only one holds
    taken out of both (an older model lacks them: no difference of results)."""
    ia, ib = a.get("info"), b.get("info")
    if not (isinstance(ia, dict) and isinstance(ib, dict)):
        return a, b
    drop = {k for k in ADDED_RECORDS if (k in ia) != (k in ib)}
    if not drop:
        return a, b
    return tuple(
        {**m, "info": {k: v for k, v in info.items() if k not in drop}}
        for m, info in ((a, ia), (b, ib))
    )


def _count(a: np.ndarray, b: np.ndarray) -> dict[str, int]:
    """How many entries differ, of how many (NaN equal to NaN)."""
    same = a == b
    if a.dtype.kind in "fc" and b.dtype.kind in "fc":
        same |= np.isnan(a) & np.isnan(b)
    return {"n_differ": int(np.count_nonzero(~same)), "size": int(a.size)}


def _compare_files(fa: Path, fb: Path) -> dict[str, Any]:
    """Every array of two ``.npz`` files, by ``file:array``. Where both hold a
    1-D ``methods`` array naming different methods, the arrays with one row per
    method are compared on the methods both have, in the first file's order."""
    out: dict[str, Any] = {}
    with load_npz(fa) as za, load_npz(fb) as zb:
        try:
            rows = _shared_methods(za, zb)
        except ValueError:  # a damaged methods array: reported below, unreadable
            rows = None
        for key in sorted(set(za.files) | set(zb.files)):
            name = f"{fa.name}:{key}"
            if key not in za.files or key not in zb.files:
                out[name] = {"only_in": str(fa.parent if key in za else fb.parent)}
                continue
            try:
                a, b = za[key], zb[key]
                if rows is not None and key == "methods":
                    ma, mb = a.tolist(), b.tolist()
                    only = [
                        [m for m in ma if m not in mb],
                        [m for m in mb if m not in ma],
                    ]
                    # the same methods in another order: rows matched by name
                    out[name] = {"methods_only_in": only} if any(only) else "identical"
                    continue
                out[name] = compare_arrays(*_on_shared(a, b, key, rows))
            except (ValueError, TypeError) as err:  # e.g. an object array (pickle)
                out[name] = {"unreadable": str(err)}
    return out


#: Arrays with one row per entry of their file's ``methods`` (``trials.npz``).
PER_METHOD = ("returns", "steps")


def _shared_methods(za, zb) -> tuple[tuple[list[int], int], ...] | None:
    """Per file, the row indexes of the methods both files name (``methods``, 1-D
    strings), in the first file's order, and how many methods the file names;
    None if either names none, they name the same, or they share none (then the
    files simply differ)."""
    if "methods" not in za.files or "methods" not in zb.files:
        return None
    ma, mb = za["methods"], zb["methods"]
    if ma.ndim != 1 or mb.ndim != 1 or ma.dtype.kind != "U" or mb.dtype.kind != "U":
        return None
    if np.array_equal(ma, mb):
        return None
    names_a, names_b = ma.tolist(), mb.tolist()
    shared = [m for m in names_a if m in names_b]
    if not shared:
        return None
    return (
        ([names_a.index(m) for m in shared], len(names_a)),
        ([names_b.index(m) for m in shared], len(names_b)),
    )


def _on_shared(a: np.ndarray, b: np.ndarray, key: str, rows) -> tuple:
    """``a`` and ``b`` cut to the shared methods' rows if ``key`` is an array of
    one row per method (``PER_METHOD``); else as they are."""
    if rows is None or key not in PER_METHOD:
        return a, b
    for x, (_, n_methods) in zip((a, b), rows, strict=True):
        if x.ndim == 0 or x.shape[0] != n_methods:  # a damaged file
            raise ValueError(
                f"{key}: expected a row per entry of its file's methods "
                f"({n_methods}), got shape {x.shape}"
            )
    (rows_a, _), (rows_b, _) = rows
    return a[rows_a], b[rows_b]


def main(run_a: str | Path, run_b: str | Path, out: str | Path | None = None):
    """Compare two run folders; see the module docstring."""
    if out is not None:
        check_out_file(out, [run_a, run_b])
    a, b = Path(run_a), Path(run_b)
    config_a, metrics_a, env_a = read_run(a)
    config_b, metrics_b, env_b = read_run(b)
    config = differences(config_a, config_b, PRESENTATION, lists=False)
    environment = differences(env_a, env_b) if env_a and env_b else "unrecorded"
    not_compared = tuple(
        key for key in ADDED_METRICS if (key in metrics_a) != (key in metrics_b)
    )
    for key in not_compared:  # one run is older than the metric
        metrics_a.pop(key, None)
        metrics_b.pop(key, None)
    flat_a, flat_b = flatten(metrics_a), flatten(metrics_b)
    added_a, added_b = added_methods(config_a), added_methods(config_b)
    newer_pairs: dict[str, str] = {}  # key: its pair's prefix
    for key in flat_a.keys() ^ flat_b.keys():
        other = metrics_b if key in flat_a else metrics_a
        pair = _added_pair(key, added_a & added_b, other)
        if pair is not None:  # one run is older than the pair
            newer_pairs[key] = pair
    not_compared += tuple(sorted(set(newer_pairs.values())))
    extra = {
        str(a): [k for k in sorted(flat_a.keys() - flat_b.keys())
                 if _method_entry(k, added_a - added_b, metrics_b)],
        str(b): [k for k in sorted(flat_b.keys() - flat_a.keys())
                 if _method_entry(k, added_b - added_a, metrics_a)],
    }  # fmt: skip
    apart = set().union(*extra.values())
    absent = object()  # unlike any value, None included
    metrics = {
        k: [flat_a.get(k), flat_b.get(k)]
        for k in sorted(flat_a.keys() | flat_b.keys())
        if k not in apart
        and k not in newer_pairs
        and flat_a.get(k, absent) != flat_b.get(k, absent)
    }
    names_a = {p.name for p in a.glob("*.npz")}
    names_b = {p.name for p in b.glob("*.npz")}
    arrays: dict[str, Any] = {}
    for name in sorted(names_a & names_b):
        arrays |= _compare_files(a / name, b / name)
    for name, value in arrays.items():
        if _is_extra(value):
            a_only, b_only = value["methods_only_in"]
            if not (
                set(a_only) <= added_a - added_b and set(b_only) <= added_b - added_a
            ):  # a method no config names as added: the runs' methods differ
                arrays[name] = {"methods_differ": value["methods_only_in"]}
    only_in = {str(a): sorted(names_a - names_b), str(b): sorted(names_b - names_a)}
    result = Comparison(
        config, environment, arrays, metrics, only_in, not_compared, extra
    )
    if out is not None:
        verdicts = {
            "identical": result.identical,
            "shared_identical": result.shared_identical,
        }
        write_json(out, result._asdict() | verdicts)
    return result


def _show(items: dict, limit: int, pairs: bool = False) -> list[str]:
    """``key: value`` lines, at most ``limit``; with ``pairs``, each value is
    ``[a's, b's]``, shown as ``a's vs b's``."""
    lines = [
        f"  {k}: {v[0]!r} vs {v[1]!r}" if pairs else f"  {k}: {v}"
        for k, v in list(items.items())[:limit]
    ]
    if len(items) > limit:
        lines.append(f"  … and {len(items) - limit} more (--show N, or --out FILE)")
    return lines


def metric_groups(metrics: dict[str, list]) -> dict[str, str]:
    """Differing metrics by top-level key: how many values, and the largest
    relative difference |a − b| / max(|a|, |b|) among the numbers."""
    groups: dict[str, list] = {}
    for key, pair in metrics.items():
        groups.setdefault(key.split(".", 1)[0], []).append(pair)
    out = {}
    for name, pairs in groups.items():
        rel = [
            abs(x - y) / max(abs(x), abs(y))
            for x, y in pairs
            if isinstance(x, int | float) and isinstance(y, int | float) and x != y
        ]
        text = f"{len(pairs)} value{'s' * (len(pairs) != 1)}"
        out[name] = text + (
            f", largest relative difference {max(rel):.2g}" if rel else ""
        )
    return out


def report(result: Comparison, limit: int = 10) -> str:
    """The comparison as plain text."""
    lines = ["config: " + ("the same" if not result.config else "differs in")]
    lines += _show(result.config, limit, pairs=True)
    env = result.environment
    if isinstance(env, str):
        lines.append(f"environment: {env} in at least one run")
    else:
        lines.append("environment: " + ("the same" if not env else "differs in"))
        lines += _show(env, limit, pairs=True)
    same = [k for k, v in result.arrays.items() if v == "identical"]
    parted = {
        k: v for k, v in result.arrays.items() if v != "identical" and not _is_extra(v)
    }
    lines.append(f"arrays: {len(same)} identical, {len(parted)} differ")
    lines += _show(parted, limit)
    for name, v in result.arrays.items():
        if _is_extra(v):
            a_only, b_only = v["methods_only_in"]
            lines.append(
                f"  {name}: compared on the methods both ran"
                + (f"; only the first ran {a_only}" if a_only else "")
                + (f"; only the second ran {b_only}" if b_only else "")
            )
    lines += [
        f"  only in {run}: {', '.join(n)}" for run, n in result.only_in.items() if n
    ]
    lines.append(
        "metrics: "
        + ("the same" if not result.metrics else f"{len(result.metrics)} values differ")
        + " (of those both runs have)"
    )
    lines += _show(metric_groups(result.metrics), limit)
    for run, keys in result.extra.items():
        if keys:
            groups = Counter(key.split(".", 1)[0] for key in keys)
            counts = ", ".join(f"{k} ({n})" for k, n in groups.items())
            lines.append(f"  only in {run}: {len(keys)} values: {counts}")
    if result.not_compared:
        lines.append(
            "  not compared (one run is older than them): "
            + ", ".join(result.not_compared)
        )
    if result.identical:
        verdict = "identical results"
    elif result.shared_identical:
        verdict = (
            "identical where both runs have results (the entries of methods only "
            "one run added aside)"
        )
    else:
        verdict = "the results differ"
    lines.append("verdict: " + verdict)
    return "\n".join(lines)


def cli(argv: list[str] | None = None) -> int:
    printable_output()
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m tasks.compare_runs",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("run_a", help="a finished run folder")
    parser.add_argument("run_b", help="another one")
    parser.add_argument("--show", type=int, default=10, help="rows per section")
    parser.add_argument("--out", default=None, help="also write the comparison JSON")
    args = parser.parse_args(argv)
    if args.show < 1:
        parser.error(f"--show: expected >= 1, got {args.show}")
    try:
        result = main(args.run_a, args.run_b, out=args.out)
    except (ValueError, OSError) as err:  # OSError: e.g. a file that is a folder
        parser.error(str(err))  # (status 2: a traceback's 1 would read "differ")
    print(report(result, args.show))
    # as diff's: 0 the same (where both runs have results, as identical ones
    # are), 1 they differ, 2 trouble (argparse's usage errors)
    return 0 if result.shared_identical else 1


if __name__ == "__main__":
    sys.exit(cli())
