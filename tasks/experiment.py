"""What every experiment shares: run folders, JSON artefacts, intervals, tables.

An experiment writes ``runs/<name>/``: ``config.json``, ``metrics.json``,
``report.md``, PNG figures, a rerun ``.rrd`` and the fitted model. Every file is
written to a temporary name and renamed, so a killed run leaves no half-written
artefact; and a run first deletes the previous run's files from its folder
(:func:`run_dir`), so a folder never mixes two runs. All randomness of a run is
spawned from one ``np.random.SeedSequence``.
"""

from __future__ import annotations

import argparse
import codecs
import contextlib
import contextvars
import dataclasses
import functools
import json
import os
import pickle
import platform
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg  # noqa: F401  (loads scipy's BLAS, so one_blas_thread limits it)
from scipy import stats
from threadpoolctl import threadpool_info, threadpool_limits

import hipmdp
from hipmdp.data import (
    atomic_temporaries,
    atomic_write,
    check_integer,
    folder_locked,
    lock_folder,
)

Array = np.ndarray


def one_blas_thread(fn: Callable) -> Callable:
    """Run ``fn`` with every BLAS and OpenMP pool of this process at one thread.

    Results must depend on the seed alone. Multithreaded BLAS splits sums in
    another order, and the Gibbs sampler and the chaotic swing-up amplify that
    round-off: the quick swing-up preset, called in-process after ``import
    numpy`` (two OpenBLAS threads), gave HiP-MDP − average +7.2 instead of the
    command's −0.0, with f differing by 7e-10. ``tasks/__init__.py`` sets
    ``OPENBLAS_NUM_THREADS=1`` only if it is imported before numpy, so every
    experiment's ``main`` also limits the loaded libraries (numpy's and scipy's
    OpenBLAS) for its duration; worker processes inherit the limit (fork) or set
    it themselves (:func:`pool_map`). The previous limits are restored after.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1):
            return fn(*args, **kwargs)

    wrapper.one_blas_thread = True  # for tests: which entry points are limited
    return wrapper


BLAS_FIELDS = ("internal_api", "version", "architecture", "num_threads")


def package_versions(names: Sequence[str]) -> dict[str, str | None]:
    """The installed version of each package (None if it is not installed)."""
    versions = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def environment() -> dict[str, Any]:
    """What a run's floating-point results depend on besides its seed and config.

    The same seed and code give bit-identical runs on one machine; on another
    CPU, BLAS and numpy pick other SIMD kernels, whose round-off moves the
    learned models' control returns (the true simulator's do not move). Written
    to ``metrics.json`` so that two runs can be told apart: package versions,
    the git commit of the code (None outside a checkout; ``dirty`` if it has
    uncommitted changes), the CPU, numpy's SIMD extensions and, per loaded BLAS,
    its version, kernel architecture and thread count.
    """
    packages = package_versions(
        ("hipmdp", "numpy", "scipy", "mujoco", "dm-control", "rerun-sdk")
    )
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

        simd = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]
    except ImportError:  # a private module; numpy may move it
        simd = None
    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": _cpu_model(),
        "packages": packages,
        "git_commit": _git_commit(),
        "numpy_simd": simd,
        "blas": sort_blas(
            [
                {k: info.get(k) for k in BLAS_FIELDS}
                for info in threadpool_info()
                if info.get("user_api") == "blas"
            ]
        ),
    }


@contextlib.contextmanager
def writes_metrics(
    path: Path, metrics: dict, seconds: dict, started: float, machine: dict
):
    """Around a run's artefacts (figures, recording): times them as
    ``seconds["artefacts"]``, then writes ``path/metrics.json`` with
    ``metrics["seconds"]`` (``total`` since ``started``) and
    ``metrics["environment"] = machine``, even if an artefact fails: the
    numbers of a run are never lost to a figure."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        seconds["artefacts"] = time.perf_counter() - t0
        seconds["total"] = time.perf_counter() - started
        metrics["seconds"] = seconds
        metrics["environment"] = machine
        write_json(path / "metrics.json", metrics)


def wrote_line(out: Path, recording: str) -> str:
    """The command line's last word on a run: what it wrote in ``out`` (the
    ``recording`` file too, if there is one)."""
    written = "figures, recording" if (out / recording).exists() else "figures"
    return f"wrote {out}/ (report.md, metrics.json, {written})"


class Terminated(BaseException):
    """SIGTERM (what a batch system sends to stop a job) while an experiment or
    ``tasks.generate`` runs (:func:`stops_reported`): what KeyboardInterrupt is
    to Ctrl-C (a BaseException, as it is)."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated


def _listing(folder: Path) -> dict[str, tuple[int, int]]:
    """The (inode, mtime in ns) of each visible entry of ``folder``: an atomic
    write gives its file a new inode, whatever the clocks say."""
    found = {}
    with contextlib.suppress(OSError):
        for f in folder.iterdir():
            if not f.name.startswith("."):
                with contextlib.suppress(OSError):
                    st = f.stat()
                    found[f.name] = (st.st_ino, st.st_mtime_ns)
    return found


@contextlib.contextmanager
def stops_reported(prog: str, out: str | os.PathLike | None, name: str | None = None):
    """Within: Ctrl-C and SIGTERM end an experiment's command with status 130 or
    143 and one line on stderr saying what its run folder ``out`` (None:
    ``runs/<name>``, as :func:`run_dir` takes it) holds, not a
    traceback (or, for SIGTERM, nothing at all). A run stopped after it began
    writing leaves the files it finished, each whole, named in that line: those
    that are new or replaced since the run began (another inode or mtime; no
    clock is compared), ``metrics.json`` among them only if the run stopped
    while making its figures or recording (:func:`writes_metrics`); the next
    run into ``out`` replaces them (:func:`run_dir`). SIGTERM is handled only
    where its handler is the default one (not under a caller that set its
    own) and in the main thread; pool workers put the default back
    (:func:`_init_worker`). A second Ctrl-C or SIGTERM while the line is being
    composed is ignored (in the main thread), so the line is whole."""
    out = Path(out) if out is not None else Path("runs") / str(name)
    previous = None
    if (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    ):
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    before = _listing(out)
    try:
        yield
    except (KeyboardInterrupt, Terminated) as stop:
        code, how = (
            (143, "terminated (SIGTERM)")
            if isinstance(stop, Terminated)
            else (130, "interrupted (Ctrl-C)")
        )
        with stops_ignored():  # a second stop would cut the line short
            after = _listing(out)
            written = sorted(n for n, v in after.items() if before.get(n) != v)
            if written:
                tail = "" if "metrics.json" in written else " and no metrics.json"
                left = (
                    f"{out} holds the files it finished ({', '.join(written)})"
                    f"{tail}; the next run into it replaces them"
                )
            else:
                left = f"it had written nothing to {out}"
                removed = sorted(before.keys() - after.keys())
                if removed:  # run_dir deletes the previous run's files first
                    left += (
                        f", after removing the previous run's ({', '.join(removed)})"
                    )
            print(f"{prog}: {how} before the run ended: {left}", file=sys.stderr)
        raise SystemExit(code) from None
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def stops_ignored() -> Iterator[None]:
    """Within: Ctrl-C and SIGTERM are ignored (in the main thread; elsewhere
    signals cannot be set), for a command composing the line that says how it
    stopped; the handlers are put back on leaving."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {
        signum: signal.signal(signum, signal.SIG_IGN)
        for signum in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        yield
    finally:
        for signum, handler in previous.items():
            if handler is not None:  # None: set outside Python, cannot be put back
                signal.signal(signum, handler)


def sort_blas(blas: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """BLAS libraries in a fixed order (threadpoolctl lists numpy's and scipy's in
    the order the process happened to load them)."""
    return sorted(blas, key=lambda b: [str(b.get(k)) for k in BLAS_FIELDS])


def describe_environment(env: dict[str, Any] | None) -> str:
    """One line of :func:`environment` for a report (empty if ``env`` is None)."""
    if not env:
        return ""
    pk = env["packages"]
    blas = ", ".join(
        f"{b['internal_api']} {b['version']} ({b['architecture']}, "
        f"{b['num_threads']} thread{'s' * (b['num_threads'] != 1)})"
        for b in env["blas"]
    )
    commit = env["git_commit"]
    return (
        f"Machine: {env['cpu']}; numpy {pk['numpy']}, scipy {pk['scipy']}, "
        f"mujoco {pk['mujoco']}; BLAS {blas or 'not found'}; code "
        f"{commit[:12] + commit[40:] if commit else 'not a git checkout'}. The "
        "learned models' results depend on these through round-off "
        "(`environment` in metrics.json)."
    )


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _git_commit() -> str | None:
    """HEAD of the checkout this package runs from, ``+dirty`` if it has
    uncommitted changes to tracked files; None if it is not a git checkout."""
    root = Path(__file__).resolve().parent.parent  # tasks/ sits at the repo's top

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "--no-optional-locks", "-C", str(root), *args],
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout.strip()  # fmt: skip

    try:
        # an install inside some other checkout (site-packages in its .venv) is not
        # this code's checkout
        if Path(git("rev-parse", "--show-toplevel")).resolve() != root:
            return None
        head = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+dirty" if dirty else "")


def to_jsonable(x: Any) -> Any:
    """Dataclasses, numpy scalars/arrays, tuples and paths as plain JSON values."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: to_jsonable(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating | float):
        x = float(x)
        return x if np.isfinite(x) else None  # JSON has no NaN/inf
    if isinstance(x, Path):
        return str(x)
    return x


def _write(path: str | os.PathLike, write: Callable) -> Path:
    """:func:`hipmdp.data.atomic_write` with ``clean``: it also removes the
    temporary files that killed writes of this same file left (a check killed
    while writing its JSON into a run folder left one that no later run
    removed)."""
    return atomic_write(path, write, clean=True)


def printable_output() -> None:
    """Let stdout and stderr print any text; every command line here calls it
    first. Where a stream's encoding is not UTF-8 (a Latin-1 locale such as
    ``LANG=en_US`` on an older system, or ``PYTHONIOENCODING=ascii``), a
    character it lacks (λ, σ, −) is written as an escape (``\\u03bb``): it
    raised ``UnicodeEncodeError``, which stopped ``--help`` and a run's closing
    summary. So did an ASCII stream with ``surrogateescape`` errors (the C locale
    without Python's UTF-8 mode). Streams without ``reconfigure`` (not a text
    file) are left."""
    for stream in (sys.stdout, sys.stderr):
        encoding = getattr(stream, "encoding", None)
        if not encoding or not hasattr(stream, "reconfigure"):
            continue
        try:
            utf8 = codecs.lookup(encoding).name == "utf-8"
        except LookupError:
            utf8 = False
        if not utf8 and stream.errors not in _ERRORS_THAT_PRINT:
            stream.reconfigure(errors="backslashreplace")


#: The error handlers of a text stream that write something for any character.
_ERRORS_THAT_PRINT = frozenset(
    ["backslashreplace", "namereplace", "xmlcharrefreplace", "replace", "ignore"]
)


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON, atomically (:func:`_write`)."""
    text = json.dumps(to_jsonable(obj), indent=2, sort_keys=False) + "\n"
    return _write(path, lambda fh: fh.write(text.encode()))


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write a text file atomically (:func:`_write`)."""
    return _write(path, lambda fh: fh.write(text.encode()))


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Save a matplotlib figure as PNG, atomically (:func:`_write`), and close
    it."""
    import matplotlib.pyplot as plt

    try:
        return _write(path, lambda fh: fig.savefig(fh, format="png", dpi=120))
    finally:
        plt.close(fig)


#: The run folders this process holds the lock of (`run_dir`): descriptors by path.
_RUN_LOCKS: dict[Path, int] = {}


def _busy_message(path: Path) -> str:
    return (
        f"out: another run is writing to {path}; wait for it to end, or choose "
        "another folder (two runs in one folder mix their files)"
    )


def _busy(path: Path) -> bool:
    """Whether another process holds ``path``'s run lock (:func:`run_dir`)."""
    return path.resolve() not in _RUN_LOCKS and folder_locked(path)


def releases_run_folders(fn: Callable) -> Callable:
    """Release, when ``fn`` returns or raises, the run-folder locks that
    :func:`run_dir` took during the call (an experiment's ``main``); a process
    that ends releases them too, however it ends."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        held = set(_RUN_LOCKS)
        try:
            return fn(*args, **kwargs)
        finally:
            for path in set(_RUN_LOCKS) - held:
                os.close(_RUN_LOCKS.pop(path))

    return wrapper


def run_dir(
    out: str | os.PathLike | None, name: str, artefacts: Sequence[str] = ()
) -> Path:
    """``out`` if given, else ``runs/<name>`` under the working directory, made
    if need be.

    A run replaces the previous run of the same experiment in its folder: the
    files matching the glob patterns ``artefacts`` (what the experiment writes)
    are deleted first, so a run that stops early, or writes fewer files
    (``--no-record``, fewer fits), never leaves its folder holding files of two
    runs. So are the temporary files a killed run left (``.<artefact>.*.tmp``:
    :func:`hipmdp.data.atomic_write`'s, the recording's). Other files (a check's
    JSON on the previous run, say) are left, and named on stderr.

    The run holds an exclusive lock on the folder (``flock``) until the
    experiment's ``main`` ends (:func:`releases_run_folders`) or its process
    dies: two runs into one folder at once left one run's config beside the
    other's metrics.

    Raises:
        ValueError: before anything is deleted or written, if ``out`` exists and
            is not a folder, or holds files named like the artefacts without a
            ``config.json`` of a ``name`` run (a folder that is not this
            experiment's run folder), or holds a ``tasks.generate`` dataset
            (``manifest.json``), or cannot be made or written in
            (:func:`check_makeable`), or another run is writing to it.
    """
    path, stale = check_out(out, name, artefacts)
    path.mkdir(parents=True, exist_ok=True)
    if path.resolve() not in _RUN_LOCKS:
        try:
            fd = lock_folder(path, wait=False)
        except BlockingIOError:
            raise ValueError(_busy_message(path)) from None
        if fd is not None:
            _RUN_LOCKS[path.resolve()] = fd
    for file in stale:
        file.unlink()
    for pattern in artefacts:  # what a killed run's atomic writes left behind
        for tmp in atomic_temporaries(path, pattern):
            tmp.unlink(missing_ok=True)
    others = sorted(f.name for f in path.iterdir() if not f.name.startswith("."))
    if stale and others:
        print(
            f"{path}: replaced the previous run's files; kept {', '.join(others)}"
            ", which this run does not write (any made from the previous run "
            "describe that run, not this one)",
            file=sys.stderr,
        )
    return path


def check_out(
    out: str | os.PathLike | None, name: str, artefacts: Sequence[str] = ()
) -> tuple[Path, list[Path]]:
    """:func:`run_dir`'s checks, with no side effect: the folder and the previous
    run's files in it that a run would delete. Raises ``ValueError`` as
    :func:`run_dir`."""
    path = _out_path(out, "folder") if out is not None else Path("runs") / name
    check_folder_out(path)
    if _busy(path):
        raise ValueError(_busy_message(path))
    if (path / "manifest.json").is_file():  # a run wrote beside the data's shards
        raise ValueError(
            f"out: {path} holds a tasks.generate dataset (manifest.json); choose a "
            "new or empty folder"
        )
    stale = sorted({f for pattern in artefacts for f in path.glob(pattern)})
    if stale and _run_name(path / "config.json") != name:
        raise ValueError(
            f"out: {path} holds {', '.join(f.name for f in stale)}, but no "
            f"config.json of a run of {name}; choose a new or empty folder"
        )
    return path, stale


def _out_path(out: str | os.PathLike, kind: str) -> Path:
    """``out`` as a Path, refused if empty (``Path("")`` is the working
    directory)."""
    if not os.fspath(out).strip():
        raise ValueError(f"out: expected a {kind} path, got {os.fspath(out)!r}")
    return Path(out)


def check_makeable(path: Path, name: str = "out") -> None:
    """Raise ``ValueError`` naming ``name`` unless ``path`` can be made: its
    nearest existing ancestor is a folder (the missing ones are made on
    writing), not a file, and a file can be written in it (or in ``path``, if
    that is a folder already): a read-only place would otherwise fail only at
    the end of the work. The probe is an unnamed temporary file, which a kill
    cannot leave behind (``O_TMPFILE``, where the file system has it)."""
    path = Path(path)
    try:
        path.resolve()
    except (RuntimeError, OSError) as err:  # 3.11 raises RuntimeError on a loop
        raise ValueError(
            f"{name}: {path} cannot be resolved ({err}): a symbolic link on it "
            "leads back to itself"
        ) from None
    if path.is_symlink() and not path.exists():
        raise ValueError(
            f"{name}: {path} is a symbolic link to {os.readlink(path)}, which does "
            "not exist; make it first, or give another path"
        )
    ancestor = next(p for p in path.absolute().parents if p.exists())
    if not ancestor.is_dir():
        raise ValueError(
            f"{name}: {ancestor} is not a folder, so {path} cannot be made"
        )
    where = path if path.is_dir() else ancestor
    try:
        with tempfile.TemporaryFile(dir=where):
            pass
    except OSError as err:
        raise ValueError(
            f"{name}: cannot write in {where} ({err.strerror or err}), so {path} "
            "cannot be written"
        ) from None


def check_folder_out(path: Path, name: str = "out") -> None:
    """Raise ``ValueError`` naming ``name`` unless ``path`` is a folder or can be
    made one."""
    if path.exists() and not path.is_dir():
        raise ValueError(f"{name}: {path} exists and is not a folder")
    check_makeable(path, name)


#: Glob patterns of the files an experiment's run writes (each experiment's
#: ``ARTEFACTS`` match them): a check's ``out`` may not replace them.
RUN_FILES = ("config.json", "metrics.json", "report.md", "*.npz", "*.png", "*.rrd")


def check_out_file(
    out: str | os.PathLike, runs: Sequence[str | os.PathLike] = ()
) -> Path:
    """The file ``out`` a command will write, checked before any work: a
    non-empty path that is not a folder and can be made (:func:`check_makeable`),
    and not one of the files of the run folders ``runs`` that the command reads
    (:data:`RUN_FILES`: writing there would replace the run's own config, say).
    Raises ``ValueError`` naming ``out``."""
    path = _out_path(out, "file")
    if path.is_dir():
        raise ValueError(f"out: {path} is a folder; expected a file path")
    for run in runs:
        if path.resolve().parent == Path(run).resolve() and any(
            path.match(pattern) for pattern in RUN_FILES
        ):
            raise ValueError(
                f"out: {path} is one of the run {run}'s own files; choose another name"
            )
    check_makeable(path)
    return path


def _run_name(config_file: Path) -> str | None:
    """The ``name`` in a run's ``config.json``, or None if there is none."""
    try:
        return json.loads(config_file.read_text()).get("name")
    except (OSError, ValueError, AttributeError):
        return None


def mean_ci(x: Sequence[float] | Array, axis: int = 0, level: float = 0.95) -> dict:
    """Mean and Student-t ``level`` confidence interval along ``axis``.

    Returns ``{"mean", "low", "high", "n"}`` (arrays if more than one dimension
    remains). With one sample there is no interval: ``low`` and ``high`` are NaN
    (null in JSON; :func:`fmt_ci` says so), not the point itself, which would read
    as certainty.
    """
    if not 0 < level < 1:
        raise ValueError(f"level: expected a number in (0, 1), got {level!r}")
    x = np.asarray(x, dtype=float)
    n = x.shape[axis]
    mean = x.mean(axis=axis)
    if n < 2:
        none = np.full_like(mean, np.nan) if np.ndim(mean) else np.nan
        return {"mean": mean, "low": none, "high": none, "n": n}
    sem = x.std(axis=axis, ddof=1) / np.sqrt(n)
    half = stats.t.ppf(0.5 + level / 2, df=n - 1) * sem
    return {"mean": mean, "low": mean - half, "high": mean + half, "n": n}


def within_threshold(target: float | Array, margin: float = 0.1) -> float | Array:
    """The lowest return "within ``margin``" of ``target``: returns are negative
    step counts, so ``target - margin * |target|`` (−118.4 for −107.6 and
    10%)."""
    return target - margin * np.abs(target)


def first_episode_within(
    curve: Array, target: float, margin: float = 0.1
) -> int | None:
    """First episode (1-based) whose mean return is within ``margin`` of ``target``
    (at or above :func:`within_threshold`); None if never reached."""
    curve = np.asarray(curve, dtype=float)
    ok = np.flatnonzero(curve >= within_threshold(target, margin))
    return int(ok[0]) + 1 if ok.size else None


def margin_to_target(
    returns: Array, reference: Array, window: int, margin: float = 0.1
) -> dict:
    """Each trial's return, per episode, minus the "within ``margin``" threshold of
    the reference method's final return *on the same trial*: ``returns[i, e] -
    (r_i - margin |r_i|)`` with ``r_i`` the mean of ``reference[i]`` over its last
    ``window`` episodes. Per episode, a ``mean_ci`` over trials; its mean is the
    curve's distance above the threshold that ``first_episode_within`` compares
    with, and its interval says whether "within 10% by episode e" is clear, clearly
    not met, or undecided at this sample size. Above 0: within."""
    returns, reference = np.asarray(returns, float), np.asarray(reference, float)
    if returns.ndim != 2 or returns.shape[0] != reference.shape[0]:
        raise ValueError(
            f"returns, reference: expected (trials, episodes) with the same trials, "
            f"got {returns.shape} and {reference.shape}"
        )
    check_integer("window", window, 1)  # [:, -0:] would be every episode
    final = reference[:, -window:].mean(axis=1)
    return mean_ci(returns - within_threshold(final, margin)[:, None], axis=0)


def paired_difference(
    a: Array, b: Array, level: float = 0.95, groups: Array | None = None
) -> dict:
    """Method ``a`` minus method ``b`` on the same (setting, trial) pairs.

    ``a`` and ``b`` have shape (trials, episodes) with rows in the same (setting,
    trial) order. Returns ``{"all_episodes": mean_ci of each trial's mean return
    difference over its episodes, "per_episode": mean_ci per episode}``; both are
    paired, so what the trials share (instance, start states, seeds) cancels.
    Their unit is the trial: they answer for these settings.

    ``groups`` (trials,), each row's setting: then also ``"by_setting"``, the
    ``all_episodes`` interval with the setting as the unit (a mean over its
    trials per setting), which answers for new settings drawn like these; it is
    wider when the difference varies from setting to setting.
    """
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(
            f"a, b: expected equal shapes (trials, episodes), got {a.shape}, {b.shape}"
        )
    diff = a - b
    out = {
        "all_episodes": mean_ci(diff.mean(axis=1), level=level),
        "per_episode": mean_ci(diff, axis=0, level=level),
    }
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (len(diff),):
            raise ValueError(
                f"groups: expected shape ({len(diff)},), got {groups.shape}"
            )
        means = [diff[groups == g].mean() for g in np.unique(groups)]
        out["by_setting"] = mean_ci(means, level=level)
    return out


def z_table(z: Sequence, dims: Sequence[str]) -> str:
    """The feature matrix ``z`` (features × actions × dimensions, feature 0 the
    mean dynamics) as a Markdown table: a row per feature, a column per action,
    each cell the 0/1 of each dimension in ``dims``' order."""
    z = np.asarray(z, dtype=int)
    if z.ndim != 3 or z.shape[2] != len(dims):
        raise ValueError(f"z: expected (features, actions, {len(dims)}), got {z.shape}")
    rows = [
        ["0 (mean dynamics)" if k == 0 else str(k)]
        + ["".join(str(v) for v in z[k, a]) for a in range(z.shape[1])]
        for k in range(z.shape[0])
    ]
    header = ["feature", *(f"action {a}" for a in range(z.shape[1]))]
    legend = f"Each cell: z for {', '.join(dims)}, in that order."
    return legend + "\n\n" + markdown_table(header, rows)


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub Markdown table."""
    lines = [
        "| " + " | ".join(str(h) for h in header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
    ]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def count(n: int, noun: str) -> str:
    """``n`` and ``noun``, plural (an ``s`` added) unless ``n`` is 1: "1 trial",
    "12 trials"."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def run_time_line(seconds: dict[str, float]) -> str:
    """A report's "Run time" sentence from ``metrics.json``'s ``seconds``: the
    total and every part of at least half a second, in the order measured
    (underscores as spaces), then the rest of the total if at least a second
    (what no part shown timed)."""
    parts = {k: v for k, v in seconds.items() if k != "total" and v >= 0.5}
    rest = seconds["total"] - sum(parts.values())
    words = [f"{k.replace('_', ' ')} {v:.0f} s" for k, v in parts.items()]
    if rest >= 1:
        words.append(f"the rest {rest:.0f} s")
    return f"Run time: {seconds['total']:.0f} s ({', '.join(words)})."


def fmt_value(v: float, digits: int = 3, sign: str = "") -> str:
    """``v`` to ``digits`` significant digits, in scientific notation if small;
    large values (those ``g`` would print with an exponent) whole: 1187, not
    1.19e+03. ``sign="+"`` puts ``+`` before a value that is not negative
    (``+0`` for zero)."""
    v = float(v)
    if abs(v) < 1e-3 and v != 0:
        return f"{v:{sign}.{digits - 1}e}"
    text = f"{v:{sign}.{digits}g}"
    return f"{v:{sign}.0f}" if "e+" in text else text


def fmt_ci(ci: dict, digits: int = 3, signed: bool = False) -> str:
    """``mean [low, high]`` (:func:`fmt_value`), or ``mean [no interval: one
    sample]`` where the bounds are NaN or None (:func:`mean_ci` of one sample);
    ``signed`` puts ``+`` before a mean that is not negative (for differences)."""
    mean = fmt_value(ci["mean"], digits, "+" if signed else "")
    return f"{mean} {fmt_bounds(ci['low'], ci['high'], lambda v: fmt_value(v, digits))}"


def fmt_bounds(low: Any, high: Any, fmt: Callable[[float], str]) -> str:
    """``[low, high]``, each written by ``fmt``, or ``[no interval: one
    sample]`` where a bound is NaN or None (:func:`mean_ci` of one sample)."""
    if low is None or high is None or np.isnan(low) or np.isnan(high):
        return "[no interval: one sample]"
    return f"[{fmt(low)}, {fmt(high)}]"


def seed_value(ss: np.random.SeedSequence) -> tuple[int, tuple[int, ...]]:
    """``(entropy, spawn_key)``: a seed sequence as an immutable value that jobs can
    share (``SeedSequence.spawn`` mutates the object)."""
    return (int(ss.entropy), tuple(int(k) for k in ss.spawn_key))


def trial_seeds(
    ss: np.random.SeedSequence, n_settings: int, n_trials: int
) -> list[list[tuple[int, tuple[int, ...]]]]:
    """``seeds[i][t]``, the :func:`seed_value` of setting ``i``'s trial ``t``: child
    ``i * n_trials + t`` of ``ss`` (spawned here, so ``ss`` gives the same seeds
    only the first time)."""
    children = ss.spawn(n_settings * n_trials)
    return [
        [seed_value(children[i * n_trials + t]) for t in range(n_trials)]
        for i in range(n_settings)
    ]


def pool_map(
    fn,
    jobs: Sequence[Any],
    *,
    workers: int,
    desc: str,
    progress: bool,
    initializer=None,
    initargs: tuple = (),
    label=None,
) -> list:
    """``[fn(job) for job in jobs]`` in order, with a progress bar.

    ``workers == 1`` runs in this process (``initializer`` called here); otherwise a
    process pool of ``workers`` runs the jobs, never more processes than jobs (a
    pool starts all its workers at once). Either way at one BLAS thread (see
    :func:`one_blas_thread`). Results never depend on ``workers``: every job
    carries its own seed. ``label(job)``, if given, names on the bar the job it
    waits for (results come in order: with a pool, later jobs may be running
    too), so a bar that stops moving says which job is slow.
    """
    from concurrent.futures import ProcessPoolExecutor

    workers = max(1, min(workers, len(jobs)))
    if workers == 1:
        with threadpool_limits(limits=1):  # as the workers below
            if initializer is not None:
                initializer(*initargs)
            return _in_order(map(fn, jobs), jobs, desc, progress, label)
    with ProcessPoolExecutor(
        workers,
        initializer=_init_worker,
        initargs=(initializer, initargs, os.getpid()),
    ) as pool:
        # submitted one by one, not by pool.map, whose results cancel their
        # futures when dropped: a future cancelled as the pool's manager thread
        # fails it (the workers ended below) raised InvalidStateError in that
        # thread (CPython gh-107219, fixed in 3.12)
        try:  # (a stop while the jobs are handed out too)
            futures = [pool.submit(_sendable_errors, fn, job) for job in jobs]
            results = (future.result() for future in futures)
            return _in_order(results, jobs, desc, progress, label)
        except BaseException:
            # a job failed (or Ctrl-C, SIGTERM): drop the queued ones rather than
            # run them, and end the running ones
            end_workers(pool)
            raise


def end_workers(pool) -> None:
    """Shut the process pool ``pool`` down now: its workers ended, with the jobs
    they run, and its queued jobs never run (their futures fail with
    BrokenProcessPool). For a run that stops or fails, whose running jobs'
    results would be discarded: waiting for them (the pool's shutdown did, and
    so does the interpreter's exit) kept a run sent SIGTERM alone, not its
    process group, running for minutes after it was told to stop. SIGKILL, not
    SIGTERM: a worker forked a moment before still has :func:`stops_reported`'s
    handler (:func:`_init_worker` puts the default back), which printed its
    traceback; the workers hold nothing to clean up.

    A worker ended while it sends a result leaves part of it in the pipe, and
    the pool's manager thread reads on for the rest until every write end of
    the pipe is closed; this process holds one, so the run hung at exit for
    ever. It is closed here: the manager thread reads the end of the pipe and
    ends. This uses the pool's private attributes (``_processes``,
    ``_result_queue``; Python 3.11-3.14), read with getattr: without them the
    workers are left to finish their jobs, and this process waits for them."""
    workers = list((getattr(pool, "_processes", None) or {}).values())
    results = getattr(pool, "_result_queue", None)  # shutdown drops both
    pool.shutdown(wait=False, cancel_futures=True)
    for process in workers:
        process.kill()
    writer = getattr(results, "_writer", None)
    if writer is not None and workers:
        writer.close()


def _in_order(results, jobs: Sequence[Any], desc: str, progress: bool, label):
    """``list(results)`` (one per job, in order) behind a progress bar that names,
    with ``label``, the job it waits for (:func:`_name_on`)."""
    from tqdm.auto import tqdm

    out = []
    timer = None
    with tqdm(total=len(jobs), desc=desc, disable=not progress) as bar:
        try:
            for job in jobs:
                if label is not None:
                    timer = _name_on(bar, label(job), timer)
                out.append(next(results))
                bar.update()
        finally:
            if timer is not None:
                timer.cancel()
        if label is not None:
            bar.set_postfix_str("", refresh=False)  # drawn as the bar closes
    return out


def _name_on(bar, text: str, timer: threading.Timer | None) -> threading.Timer | None:
    """Show ``text`` on ``bar``: at once, unless the bar was drawn less than its
    ``mininterval`` ago (``TQDM_MININTERVAL=60`` thins a bar to one update a
    minute); then once that has passed, if no other text has replaced it (a job
    that stops the bar is named all the same). Returns the timer that will, if
    any (``timer``, the previous one, is cancelled)."""
    if timer is not None:
        timer.cancel()
    bar.set_postfix_str(text, refresh=False)
    if bar.disable:
        return None
    wait = bar.last_print_t + bar.mininterval - time.time()
    if wait <= 0:
        bar.refresh()
        bar.last_print_t = time.time()
        return None

    def draw() -> None:
        if bar.postfix == text and not bar.disable:
            bar.refresh()
            bar.last_print_t = time.time()

    timer = threading.Timer(wait, draw)
    timer.daemon = True
    timer.start()
    return timer


def _sendable_errors(fn, job):
    """``fn(job)`` in a pool worker. An error that cannot travel back to the
    parent as it is (pickled and rebuilt: an exception whose ``__init__`` takes
    other arguments than it passes on, say) would break the pool and lose its
    message; it is raised instead as a RuntimeError that carries its type,
    message, notes and traceback."""
    try:
        return fn(job)
    except Exception as err:
        try:
            pickle.loads(pickle.dumps(err))
        except Exception:
            kind = f"{type(err).__module__}.{type(err).__qualname__}"
            text = "".join(traceback.format_exception(err))
            raise RuntimeError(
                f"{kind} raised in a worker process, which could not send it back "
                f"as it is:\n{text}"
            ) from None
        raise


def _init_worker(initializer, initargs: tuple, owner: int) -> None:
    """A pool worker's start: :func:`exit_with` the pool's ``owner``, one BLAS
    thread for its lifetime, then ``initializer(*initargs)``."""
    exit_with(owner)
    # a forked worker inherits stops_reported's SIGTERM handler: the pool
    # terminates workers with SIGTERM and must see them die
    if signal.getsignal(signal.SIGTERM) is _raise_terminated:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    threadpool_limits(limits=1)
    if initializer is not None:
        initializer(*initargs)


def exit_with(owner: int, every: float = 0.5) -> None:
    """In a pool worker: end this process (``os._exit``) once the process
    ``owner``, whose pool it serves, is gone, or this process's parent has
    changed (the owner died, and the worker was handed to another process).

    A pool's workers wait for their next job on a pipe they hold both ends of,
    so an owner killed without a chance to shut its pool down (SIGKILL, the
    out-of-memory killer) left them idle for ever (a forkserver's workers kept
    the forkserver up too). A daemon thread checks every ``every`` seconds;
    a job that is running is cut short, as the owner will never read its
    result. Where ``/proc`` tells, an owner that is dead but not yet waited for
    (a zombie, which ``os.kill(owner, 0)`` still reaches) is gone too, as is
    another process given its pid (another start time).
    """
    parent = os.getppid()
    started = _process_stat(owner)

    def gone() -> bool:
        try:
            os.kill(owner, 0)
        except (ProcessLookupError, PermissionError):  # PermissionError: its
            return True  # pid now belongs to another user
        if os.getppid() != parent:
            return True
        if started is None:  # no /proc: the signal's answer is all there is
            return False
        now = _process_stat(owner)
        return now is None or now[0] in "ZX" or now[1] != started[1]

    def watch() -> None:
        while not gone():
            time.sleep(every)
        os._exit(1)

    threading.Thread(target=watch, name=f"exit-with-{owner}", daemon=True).start()


def _process_stat(pid: int) -> tuple[str, str] | None:
    """The state (``R``, ``S``, ``Z``...) and start time of process ``pid``
    (``/proc/PID/stat``), or None where there is none to read."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2 :].split()  # after the command's name
    return fields[0], fields[19]  # stat's 3rd and 22nd fields


def check_settings(config: Any, train: str, test: str, make, what: str) -> None:
    """Normalise ``config.<train>`` and ``config.<test>`` to tuples of float pairs,
    each checked by ``make(*pair)`` (the domain's parameter validation); at least
    two training settings. ``what`` names a pair's entries in errors."""
    for name in (train, test):
        pairs = tuple(tuple(float(v) for v in p) for p in getattr(config, name))
        if not pairs or any(len(p) != 2 for p in pairs):
            raise ValueError(f"{name}: expected {what} pairs, got {pairs}")
        for p in pairs:
            make(*p)
        object.__setattr__(config, name, pairs)
    if len(getattr(config, train)) < 2:
        raise ValueError(f"{train}: expected at least two settings")


def check_positive(config: Any, names: Sequence[str]) -> None:
    """Raise ``ValueError`` naming the first of ``names`` that is not >= 1."""
    check_counts(**{name: getattr(config, name) for name in names})


def check_counts(**values: Any) -> None:
    """Raise ``ValueError`` naming the first keyword whose value is not an integer
    >= 1."""
    for name, value in values.items():
        check_integer(name, value, 1)


def check_run_fields(config: Any) -> None:
    """The fields every experiment's config has: ``seed`` (an integer >= 0, as
    ``numpy.random.SeedSequence`` takes), ``fit`` (a ``hipmdp.FitConfig``),
    ``record`` and ``progress`` (bools). Raise ``ValueError`` naming the field."""
    check_integer("seed", config.seed, 0)
    if not isinstance(config.fit, hipmdp.FitConfig):
        raise ValueError(
            f"fit: expected a hipmdp.FitConfig, got {type(config.fit).__name__}"
        )
    for name in ("record", "progress"):
        if not isinstance(getattr(config, name), bool):
            raise ValueError(
                f"{name}: expected True or False, got {getattr(config, name)!r}"
            )


def seed_argument(text: str) -> int:
    """argparse type of ``--seed``: an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def path_argument(text: str) -> Path:
    """argparse type of a path to write (``--out``): not empty (``Path("")`` would
    be the working directory)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a path, got {text!r}")
    return Path(text)


def run_parser(prog: str, doc: str, progress: bool = True):
    """The argument parser of a check on a finished run: ``prog``, the module
    docstring ``doc`` as its description, the positional ``run`` folder and,
    with ``progress`` (a check that shows progress bars), ``--no-progress``."""
    parser = argparse.ArgumentParser(
        prog=prog,
        description=plain_text(doc),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("run", help="a finished acrobot_swingup run folder")
    if progress:
        parser.add_argument(
            "--no-progress", action="store_true", help="no progress bars"
        )
    return parser


_INPUTS_CHECKED = contextvars.ContextVar("inputs_checked", default=False)


def inputs_checked() -> None:
    """Mark, inside :func:`run_or_exit`, that the command's inputs are checked
    and its work begins: a later error is a failure of the work (or a bug), shown
    with its traceback, not a usage error."""
    _INPUTS_CHECKED.set(True)


def run_or_exit(parser, fn: Callable[[], Any]) -> Any:
    """``fn()``, with a ValueError or FileNotFoundError raised before ``fn`` calls
    :func:`inputs_checked` (bad input, a folder that is not a run) reported as
    ``parser``'s usage error (exit status 2); one raised after it propagates,
    traceback and all."""
    token = _INPUTS_CHECKED.set(False)
    try:
        return fn()
    except (ValueError, FileNotFoundError) as err:
        if _INPUTS_CHECKED.get():
            raise
        parser.error(str(err))
    finally:
        _INPUTS_CHECKED.reset(token)


def plain_text(doc: str) -> str:
    """A docstring's text for a terminal (``--help``): ``name``, :func:`name`
    (reStructuredText's literals and cross-references) and `name` (Markdown's
    code) as name."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", doc).replace("``", "")
    return re.sub(r"`([^`\n]+)`", r"\1", text)


def by_preset(presets: dict[str, Any], field: str) -> str:
    """A ``--help`` default that comes from the preset: ``field`` of each of
    ``presets`` (name to config; a dotted ``field`` reaches into a nested
    one), "2" if they agree, else "quick 12, paper 30" (the default preset,
    quick, first)."""

    def value(config: Any) -> Any:
        for name in field.split("."):
            config = getattr(config, name)
        return config

    names = sorted(presets, key=lambda name: (name != "quick", name))
    values = {name: value(presets[name]) for name in names}
    if len(set(values.values())) == 1:
        return str(next(iter(values.values())))
    return ", ".join(f"{name} {v}" for name, v in values.items())


def common_parser(prog: str, doc: str, presets: dict[str, Any], out_default: str):
    """The options every experiment has: --preset, --seed, --out, --workers,
    --filter-weights, --new-features, --no-record, --no-progress."""
    parser = argparse.ArgumentParser(
        prog=prog,
        description=doc.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=plain_text(doc.split("\n\n", 1)[1]) if "\n\n" in doc else None,
    )
    parser.add_argument(
        "--preset", choices=sorted(presets), default="quick",
        help="quick: minutes on two cores (default); paper: the paper's sizes",
    )  # fmt: skip
    parser.add_argument(
        "--seed", type=seed_argument, default=0, help="the one seed (default 0)"
    )
    parser.add_argument(
        "--out", type=path_argument, default=None, help=f"output folder ({out_default})"
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help=f"worker processes (default: {by_preset(presets, 'workers')}); "
        "results do not depend on it",
    )
    parser.add_argument(
        "--filter-weights",
        choices=hipmdp.FILTER_WEIGHTS,
        default=None,
        help="the weights of the filter's model-error factor: prior_mean "
        "(default) or training (as the factor was calibrated; hipmdp.FitConfig)",
    )
    parser.add_argument(
        "--new-features",
        choices=hipmdp.NEW_FEATURES,
        default=None,
        help="the sampler's new-feature step: paper (default; exact only as its "
        "N_w weight draws grow without bound) or multiple_try (exact at any N_w; "
        "hipmdp.FitConfig)",
    )
    parser.add_argument("--no-record", action="store_true", help="no .rrd recording")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


#: Top-level config fields of the experiments added after runs were made, with
#: the value an older run's missing field stands for (how it ran: before
#: ``--split``, every split was random; before ``--method``, no method was
#: added). ``tasks.seed_spread`` and ``tasks.compare_runs`` read old runs so.
ADDED_FIELDS = {"split": "random", "methods": []}

#: The same for the fields of the config's ``fit`` (``hipmdp.FitConfig``): before
#: ``periodic`` no kernel was periodic; before ``filter_weights`` the filter took
#: its model-error factor at the prior mean weights; before ``new_features`` the
#: sampler took the paper's new-feature step.
ADDED_FIT_FIELDS = {
    "periodic": False, "filter_weights": "prior_mean", "new_features": "paper",
}  # fmt: skip


def read_json_object(path: Path) -> dict[str, Any]:
    """The JSON object in the file ``path`` (a run's ``config.json`` or
    ``metrics.json``). Raises ValueError naming the file if it is not JSON (cut
    short, another kind of file) or holds something else than an object;
    FileNotFoundError if there is none."""
    try:
        value = json.loads(Path(path).read_text())
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError
        raise ValueError(f"{path}: not a JSON file ({err})") from None
    if not isinstance(value, dict):
        kind = {list: "an array", str: "a string", bool: "a boolean"}.get(
            type(value), "a number" if value is not None else "null"
        )
        raise ValueError(
            f"{path}: expected a JSON object ({{...}}) at the top level, got {kind}"
        )
    return value


def with_added_fields(config: dict[str, Any]) -> dict[str, Any]:
    """An experiment's config (as in its config.json) with the ADDED_FIELDS and
    ADDED_FIT_FIELDS an older run lacks, at the values it ran with."""
    out = {**ADDED_FIELDS, **config}
    if isinstance(config.get("fit"), dict):
        out["fit"] = {**ADDED_FIT_FIELDS, **config["fit"]}
    return out


#: The command-line flag of each config field the flags set, for error messages.
FLAGS = {
    "out": "--out",
    "seed": "--seed",
    "workers": "--workers",
    "n_trials": "--trials",
    "n_episodes": "--episodes",
    "n_runs": "--runs",
    "methods": "--method",
}


def apply_common(
    parser,
    args,
    preset: Any,
    *,
    artefacts: Sequence[str] = (),
    policies: bool = False,
    **changes: Any,
) -> Any:
    """The preset with the common options (and ``changes``) applied, and
    ``--out`` checked as the run will use it (:func:`check_out`, with the
    experiment's ``artefacts``), and each ``--method`` built and checked as the
    run will (``tasks.methods.load_all``; ``policies``: whether the experiment
    takes policies); a bad value is reported through ``parser.error`` (exit
    status 2), naming the flag."""
    changes = {k: v for k, v in changes.items() if v is not None}
    changes["seed"] = args.seed
    if args.workers is not None:
        changes["workers"] = args.workers
    for field in ("filter_weights", "new_features"):
        if getattr(args, field) is not None:
            changes["fit"] = dataclasses.replace(
                changes.get("fit", preset.fit), **{field: getattr(args, field)}
            )
    if args.no_record:
        changes["record"] = False
    if args.no_progress:
        changes["progress"] = False
    try:
        config = dataclasses.replace(preset, **changes)
        if getattr(config, "methods", ()):
            from tasks.methods import load_all  # tasks.methods imports this module

            # build each, before any work: main builds them again
            load_all(config.methods, policies=policies)
        if getattr(config, "record", False):
            from tasks.recording import recording_enabled

            recording_enabled()  # a RERUN that is neither on nor off
        check_out(args.out, config.name, artefacts)
    except ValueError as err:
        parser.error(flag_error(err))
    return config


def flag_error(err: ValueError) -> str:
    """A config's error message ("field: expected ..."), led by the field's flag
    where a flag sets it ("--trials (n_trials): expected ...")."""
    field, sep, rest = str(err).partition(":")
    if sep and field in FLAGS:
        return f"{FLAGS[field]} ({field}):{rest}"
    return str(err)


def weights_figure(
    file: str | os.PathLike,
    train_params: Array,
    train_w: Array,
    test_params: Array,
    test_w: Array,
    labels: Sequence[str],
    title: str,
) -> Path:
    """Each latent weight against each physical parameter, one panel per pair.

    train_params (B, p) and train_w (K', B): training instances' posterior means;
    test_params (T, p) and test_w (T, K'): test instances' filtered belief means.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k, p = train_w.shape[0], len(labels)
    rows = max(k, 1)
    fig, axes = plt.subplots(rows, p, figsize=(3.5 * p, 2.4 * rows), squeeze=False)
    for j in range(k):
        for col, label in enumerate(labels):
            ax = axes[j, col]
            ax.scatter(
                train_params[:, col], train_w[j], label="training (posterior mean)"
            )
            ax.scatter(
                test_params[:, col], test_w[:, j], marker="x",
                label="test (filtered belief mean)",
            )  # fmt: skip
            ax.set_xlabel(label)
            ax.set_ylabel(f"w{j + 1}")
    if k == 0:
        axes[0, 0].text(0.1, 0.5, "no latent features were inferred")
    else:  # an empty panel's legend is only matplotlib's warning that it is empty
        axes[0, 0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.45 / fig.get_figheight()))  # room for it
    return save_figure(fig, file)
