"""Generate a sharded transition dataset: draw instances of a domain, run a policy on
each, write one shard per block of instances and a manifest.

    python -m tasks.generate --domain acrobot --instances 1000 \\
        --episodes-per-instance 4 --policy open-loop --workers 2 --out runs/acrobot_1000

Instances (`tasks.distributions`): the parameters named by `--vary NAME=LOW:HIGH`
(default: the two link masses in [0.7, 1.3] for the acrobot, as in the paper; the
pole mass in [0.05, 0.5] kg and half-length in [0.25, 1.0] m for the cart-pole)
follow `--distribution uniform` (default), `relative-normal` (`--sigma`) or `grid`
(`--grid K` points per parameter, `K^p` instances); the others stay nominal.
`--split train|interpolation|extrapolation` restricts them to the inner box (the
central `--inner-fraction` of every range), to held-out points inside it, or to
outside it; `all` (default) is the whole box. For the acrobot, `--book-inertia`
sets each drawn instance's link shapes so that its links keep the book's
1 kg·m² moment of inertia (`tasks.acrobot.book_inertia`) instead of scaling it
with mass × length²; the shapes are then derived, not varied.

Policies: `random` (uniform actions on the dm_control environment), `sarsa` (a
Sarsa(λ) agent on a Fourier basis learning per instance, as the paper gathers:
greedy, ε = 0, with optimistic initial values and ties broken at random; its
settings per domain in `tasks.agents`) and `open-loop` (uniform random action
sequences, the law of `random`, many instances at once with `mujoco.rollout`).

Output (`hipmdp.shards`): `OUT/shard-XXXXX.npz`, one per `--shard-size` instances,
each written to a temporary name and renamed, and `OUT/manifest.json` (config, seed,
each shard's instances, parameters, counts and SHA-256), written atomically when the
run starts and when it completes; in between, each finished shard is one line of
`OUT/progress.jsonl` (see `hipmdp.shards`). Streams: the instance parameters come from
`SeedSequence(seed, spawn_key=(0, split))`, instance `g`'s episodes (initial
states, and the random or open-loop actions or the Sarsa agent's exploration)
from `SeedSequence(seed, spawn_key=(2, split, g))`, so the files are the same
whatever `--workers` or `--scheduler`, and an instance's data the same whatever
`--shard-size` (until 2026-12-04, shard `k`'s episodes came from one stream
`(1, split, k)`, so they depended on the shard size and, for the random policy,
on the other instances in the shard). `--resume` keeps the shards whose file matches its
checksum and redoes the others (an unfinished run in `OUT` needs it, and so does a
finished one with a shard missing or not matching its checksum; a finished one
whose shards all match is left as it is), unless the run was started by other
software (the manifest's `software`: package versions and a digest of the
source; `--mixed-software` continues it all the same, listing in the manifest's
`earlier_software` which shards each earlier software made); an `OUT` holding
another run's manifest, or shards or a progress log without a manifest, or anything
else but no manifest, is an error and nothing is overwritten. Ctrl-C exits with
status 130 and SIGTERM (a batch system's stop) with 143, printing how many shards
are kept and the command that resumes the run; a shard being written then is
finished first. Any other error once the run has begun exits with status 1 and
the same line (with the traceback, unless it is a failure of the machines: a
killed pool process or Dask worker, a full disk, a worker running other code).

Execution (`concurrent.futures`): in-process (`--workers 1`), a local process pool
(`--workers N`), or a Dask cluster (`--scheduler ADDRESS`, needs
`pip install -e ".[dask]"`; a scheduler that does not answer within Dask's
connect timeout, `distributed.comm.timeouts.connect`, 30 s by default, stops the
run before anything is written, even one that accepts the connection and stays
silent, and after 2 s without an answer a line says what the run waits for; two
shards per thread of the cluster, as workers join, at least 64, are
kept in flight; a cluster with no worker for 30 s is warned of, once). Every
shard carries the client's `software` record, and a worker running other
software (another package version, an edited source) refuses it, naming its
host and what differs; on a cluster, the workers connected at the start are
asked first. The run then stops, keeping the finished shards. Read the result with
`hipmdp.Transitions.load(OUT, instances=...)` or `hipmdp.shards.Dataset(OUT)`.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import contextlib
import dataclasses
import functools
import hashlib
import importlib.resources
import importlib.util
import json
import math
import multiprocessing
import os
import shlex
import signal
import socket
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from tqdm import tqdm

from hipmdp import shards
from hipmdp.data import atomic_temporaries, folder_locked, lock_folder
from tasks._common import parameter_matrix, parameter_names
from tasks.acrobot import AcrobotParams, book_inertia_range, with_book_inertia
from tasks.agents import DOMAINS as agent_domains
from tasks.collect import DOMAINS, collect, collect_sarsa, get_domain
from tasks.distributions import KINDS, MAX_GRID_POINTS, SPLITS, Distribution, draw
from tasks.experiment import (
    Terminated,
    check_folder_out,
    check_integer,
    count,
    end_workers,
    exit_with,
    one_blas_thread,
    package_versions,
    path_argument,
    plain_text,
    printable_output,
    seed_argument,
    stops_ignored,
)
from tasks.rollout import MODULES, collect_open_loop

#: Parameters varied when no `--vary` is given: name -> (low, high).
DEFAULT_VARY = {
    "acrobot": {"link_mass_1": (0.7, 1.3), "link_mass_2": (0.7, 1.3)},
    "cartpole": {"pole_mass": (0.05, 0.5), "pole_half_length": (0.25, 1.0)},
}
POLICIES = {"random": collect, "sarsa": collect_sarsa, "open-loop": collect_open_loop}


@dataclasses.dataclass(frozen=True)
class Config:
    """A validated generation request (see the module docstring for the options).

    `manifest_config()` is what determines the data; `out`, `workers`,
    `scheduler`, `resume`, `mixed_software` and `progress` only say where and how
    it runs.

    Raises:
        ValueError: naming the field (and its command-line option) for a value of
            the wrong kind or range, before any file is written; for
            `book_inertia` on another domain than the acrobot, with varied link
            shapes, or on a box some of whose instances cannot keep the book's
            inertias (`_check_book_inertia`).
    """

    domain: str
    instances: int | None
    episodes_per_instance: int
    seed: int
    distribution: Distribution
    policy: str = "random"
    max_steps: int | None = None
    shard_size: int = 16
    out: Path = Path("runs/data")
    workers: int = 1
    scheduler: str | None = None
    resume: bool = False
    mixed_software: bool = False
    progress: bool = True
    book_inertia: bool = False

    def __post_init__(self) -> None:
        get_domain(self.domain)
        if not isinstance(self.distribution, Distribution):
            raise ValueError(
                "distribution: expected a tasks.distributions.Distribution, got "
                f"{type(self.distribution).__name__}"
            )
        if self.distribution.kind == "grid":
            if self.instances is not None:
                raise ValueError("instances (--instances): expected None for a grid")
        else:
            check_integer("instances (--instances)", self.instances, 1)
            if self.instances > MAX_GRID_POINTS:  # the plan's arrays alone: GBs
                raise ValueError(
                    f"instances (--instances): expected at most "
                    f"{MAX_GRID_POINTS:,} (as a grid), got {self.instances:,}"
                )
        check_integer("episodes_per_instance (--episodes-per-instance)",
                      self.episodes_per_instance, 1)  # fmt: skip
        check_integer("seed (--seed)", self.seed, 0)
        if self.policy not in POLICIES:
            raise ValueError(
                f"policy (--policy): expected one of {sorted(POLICIES)}, "
                f"got {self.policy!r}"
            )
        if self.max_steps is not None:
            check_integer("max_steps (--max-steps)", self.max_steps, 1)
        check_integer("shard_size (--shard-size)", self.shard_size, 1)
        check_integer("workers (--workers)", self.workers, 1)
        if self.scheduler is not None:
            if not isinstance(self.scheduler, str):
                raise ValueError(
                    f"scheduler (--scheduler): expected an address string, got "
                    f"{self.scheduler!r}"
                )
            if self.workers != 1:
                raise ValueError(
                    "--workers and --scheduler are exclusive (Dask decides)"
                )
        for name in ("resume", "mixed_software", "progress", "book_inertia"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(
                    f"{name}: expected True or False, got {getattr(self, name)!r}"
                )
        if self.mixed_software and not self.resume:
            raise ValueError("mixed_software (--mixed-software): needs --resume")
        for name in ("instances", "episodes_per_instance", "seed", "max_steps",
                     "shard_size", "workers"):  # fmt: skip
            value = getattr(self, name)
            if value is not None:  # a numpy integer as a Python one: JSON-ready
                object.__setattr__(self, name, int(value))
        if self.book_inertia:
            _check_book_inertia(self.domain, self.distribution)

    def manifest_config(self) -> dict[str, Any]:
        return {
            "domain": self.domain,
            "book_inertia": self.book_inertia,
            "instances": self.instances,
            "episodes_per_instance": self.episodes_per_instance,
            "seed": self.seed,
            "distribution": self.distribution.as_json(),
            "policy": self.policy,
            "max_steps": self.max_steps,
            "shard_size": self.shard_size,
        }


class ShardJob(NamedTuple):
    """Everything a worker needs for one shard (plain data, picklable)."""

    domain: str
    policy: str
    index: int
    instances: tuple[int, ...]
    values: tuple[tuple[float, ...], ...]
    episodes_per_instance: int
    max_steps: int | None
    entropy: int
    spawn_key: tuple[int, ...]  # instance g's stream: spawn_key + (g,)
    # the client's `software()`: a worker running other code refuses the shard
    # (`check_software`); None: unchecked
    software: dict[str, Any] | None = None


class ShardOutput(NamedTuple):
    """A finished shard: its archive bytes, counts and diverged episodes."""

    index: int
    data: bytes
    counts: dict[str, int]
    diverged: list[dict[str, Any]]


class BusyError(ValueError):
    """Another run is writing to `--out` (it holds the folder's lock)."""


def _busy(out: Path) -> BusyError:
    return BusyError(
        f"--out: another tasks.generate run is writing to {out}; wait for it to "
        "end, or choose another --out (two runs at once mix their shards)"
    )


class OtherSoftwareError(RuntimeError):
    """A worker runs other software than the client (`check_software`): its
    shards would differ from the client's, with a manifest that does not say so."""


class Generated(NamedTuple):
    """What a run left: the manifest path, the manifest, and the shards redone."""

    manifest: Path
    content: dict[str, Any]
    redone: tuple[int, ...]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m tasks.generate",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add = parser.add_argument
    add("--domain", required=True, choices=sorted(DOMAINS))
    add("--instances", type=int, default=None, help="instances drawn (default 4)")
    add("--episodes-per-instance", type=int, default=2, help="episodes (default 2)")
    add(
        "--seed",
        type=seed_argument,
        default=0,
        help="the one seed of every stream (default 0)",
    )
    add(
        "--out",
        type=path_argument,
        default=Path("runs/data"),
        help="run directory (default runs/data)",
    )
    add(
        "--vary",
        action="append",
        metavar="NAME=LOW:HIGH",
        help="repeatable; NAME one of "
        + "; ".join(
            f"{name}: {', '.join(parameter_names(domain.params_type))}"
            for name, domain in sorted(DOMAINS.items())
        )
        + " (units, nominal values and bounds: the docstrings of "
        "tasks.acrobot.AcrobotParams and tasks.cartpole.CartpoleParams)",
    )
    add("--distribution", choices=KINDS, default=None, help="default: uniform")
    add("--grid", type=int, metavar="K", help="K points per parameter (grid)")
    add(
        "--sigma",
        type=float,
        default=None,
        help="relative-normal only: std / nominal (default 0.1)",
    )
    add(
        "--split",
        choices=SPLITS,
        default="all",
        help="train: inner box; interpolation: held-out points inside it; "
        "extrapolation: outside it; all (default): the whole box",
    )
    add(
        "--inner-fraction",
        type=float,
        default=None,
        help="train, interpolation, extrapolation: inner box share per range "
        "(default 0.5)",
    )
    add(
        "--book-inertia",
        action="store_true",
        help="acrobot: each link keeps the book's 1 kg m^2 moment of inertia as its "
        "mass and length change (default: inertia scales as mass x length^2)",
    )
    add("--policy", choices=sorted(POLICIES), default="random", help="default: random")
    add(
        "--max-steps",
        type=int,
        default=None,
        help="step limit per episode (default: the task's, "
        + ", ".join(
            f"{domain.max_steps} for {name}"
            for name, domain in sorted(agent_domains.items())
        )
        + ")",
    )
    add("--shard-size", type=int, default=16, help="instances per shard (default 16)")
    add(
        "--workers",
        type=int,
        default=1,
        help="local worker processes (default 1: in this process)",
    )
    add("--scheduler", metavar="ADDRESS", help="Dask scheduler (tcp://host:port)")
    add("--resume", action="store_true", help="continue the run in --out")
    add(
        "--mixed-software",
        action="store_true",
        help="with --resume: continue a run started by other software (another "
        "version of a package or an edited source); the manifest records which "
        "shards each made",
    )
    add("--no-progress", action="store_true", help="no progress bar")
    return parser


def parse_config(argv: Sequence[str] | None = None) -> Config:
    """Parse and validate the command line; exits with status 2 on a bad option."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return _validate(args)
    except ValueError as error:
        parser.error(str(error))
        raise  # unreachable: parser.error exits


def _validate(args: argparse.Namespace) -> Config:
    spec = get_domain(args.domain)
    kind = args.distribution or ("grid" if args.grid is not None else "uniform")
    if args.grid is not None and kind != "grid":
        raise ValueError(f"--grid K goes with --distribution grid, not {kind}")
    if kind == "grid" and args.grid is None:
        raise ValueError("--distribution grid needs --grid K (points per parameter)")
    if kind == "grid" and args.instances is not None:
        raise ValueError("--instances and --grid are exclusive (grid gives K^p)")
    # options that would be accepted and do nothing
    if args.sigma is not None and kind != "relative-normal":
        raise ValueError(
            f"--sigma goes with --distribution relative-normal, not {kind}"
        )
    if args.inner_fraction is not None and args.split == "all":
        raise ValueError(
            "--inner-fraction goes with --split train, interpolation or "
            "extrapolation, not all"
        )
    if args.grid is not None and args.grid < 1:
        raise ValueError(f"--grid must be >= 1, got {args.grid}")
    if args.scheduler is not None and args.workers == 1:
        if importlib.util.find_spec("distributed") is None:
            raise ValueError('--scheduler needs Dask: pip install -e ".[dask]"')
        _check_scheduler_address(args.scheduler)
    names = [f.name for f in dataclasses.fields(spec.params_type)]
    vary = dict(DEFAULT_VARY[args.domain])
    if args.vary:
        vary = {}
        for item in args.vary:
            name, low, high = _parse_range(item)
            if name not in names:
                raise ValueError(f"--vary {item}: {args.domain} parameters are {names}")
            if name in vary:
                raise ValueError(f"--vary {item}: {name} is given twice")
            vary[name] = (low, high)
    defaults = {f.name: f.default for f in dataclasses.fields(Distribution)}
    distribution = Distribution(
        spec.params_type,
        vary,
        kind=kind,
        split=args.split,
        grid=args.grid,
        sigma=defaults["sigma"] if args.sigma is None else args.sigma,
        inner_fraction=(
            defaults["inner_fraction"]
            if args.inner_fraction is None
            else args.inner_fraction
        ),
    )
    return Config(
        domain=args.domain,
        instances=(
            None if kind == "grid" else 4 if args.instances is None else args.instances
        ),
        episodes_per_instance=args.episodes_per_instance,
        seed=args.seed,
        distribution=distribution,
        policy=args.policy,
        max_steps=args.max_steps,
        shard_size=args.shard_size,
        out=args.out,
        workers=args.workers,
        scheduler=args.scheduler,
        resume=args.resume,
        mixed_software=args.mixed_software,
        progress=not args.no_progress,
        book_inertia=args.book_inertia,
    )


def _check_scheduler_address(address: str) -> None:
    """Raise ValueError for a `--scheduler` that is no scheduler address (a port
    alone, the dashboard's http:// URL): Dask's own errors were tracebacks."""
    from distributed.comm import get_address_host_port, parse_address
    from distributed.comm.registry import get_backend

    try:
        scheme, _ = parse_address(address)
        get_backend(scheme)  # an unknown scheme (http) raises
        if scheme not in ("tcp", "tls", "ws", "wss"):  # inproc: a test's cluster
            return
        _, port = get_address_host_port(address)
    except ValueError as error:
        reason = str(error)
    else:
        if 0 < port < 65536:
            return
        reason = f"port {port} is out of range"
    raise ValueError(
        f"--scheduler {address!r}: {reason}; expected the scheduler's address, "
        "tcp://HOST:PORT (port 8786 by default; not the dashboard's http:// one)"
    )


def _check_book_inertia(domain: str, distribution: Distribution) -> None:
    """Raise ValueError unless every instance of `distribution` can keep the
    book's inertias: the acrobot, link shapes not varied, and `m l²` of each link
    within the range the shape's bounds allow at both corners of the box."""
    if domain != "acrobot":
        raise ValueError(f"--book-inertia is for the acrobot, not {domain}")
    shapes = [n for n in distribution.names if n.startswith("link_shape_")]
    if shapes:
        raise ValueError(
            f"--book-inertia derives {', '.join(shapes)}; do not --vary them"
        )
    low, high = book_inertia_range()
    nominal = AcrobotParams()
    bounds = zip(distribution.lows, distribution.highs, strict=True)
    ranges = dict(zip(distribution.names, bounds, strict=True))
    for link in (1, 2):
        mass, length = f"link_mass_{link}", f"link_length_{link}"
        m_lo, m_hi = ranges.get(mass, (getattr(nominal, mass),) * 2)
        l_lo, l_hi = ranges.get(length, (getattr(nominal, length),) * 2)
        reach = (float(m_lo * l_lo**2), float(m_hi * l_hi**2))
        if reach[0] < low or reach[1] > high:
            raise ValueError(
                f"--book-inertia: link {link}'s mass x length^2 spans "
                f"[{reach[0]:.3g}, {reach[1]:.3g}] kg m^2 over --vary ({mass} "
                f"[{m_lo:g}, {m_hi:g}], {length} [{l_lo:g}, {l_hi:g}]); keeping "
                f"I = 1 kg m^2 needs it within [{low:.3g}, {high:.3g}] (link_shape_"
                f"{link} = 1 / (m l^2) within its bounds)"
            )


def _parse_range(item: str) -> tuple[str, float, float]:
    try:
        name, bounds = item.split("=")
        low, high = (float(x) for x in bounds.split(":"))
    except ValueError:
        raise ValueError(f"--vary expects NAME=LOW:HIGH, got {item!r}") from None
    if not (math.isfinite(low) and math.isfinite(high)):
        raise ValueError(f"--vary {item}: LOW and HIGH must be finite numbers")
    if not low <= high:
        raise ValueError(f"--vary {item}: LOW must be <= HIGH")
    return name, low, high


def plan(config: Config) -> dict[str, Any]:
    """Draw the instances and lay out the run's manifest (no shard finished)."""
    split = SPLITS.index(config.distribution.split)
    stream = np.random.SeedSequence(config.seed, spawn_key=(0, split))
    bar = tqdm(  # shown at once: a million instances take half a minute
        total=config.instances,  # a grid's count once drawn
        desc=f"planning {config.domain} instances",
        leave=False,
        disable=not config.progress,
    )
    with bar:
        return _plan(config, split, stream, bar)


def _plan(
    config: Config, split: int, stream: np.random.SeedSequence, bar: tqdm
) -> dict[str, Any]:
    """`plan`'s work, counting the instances laid out on `bar`."""
    drawn = draw(
        config.distribution, config.instances, rng=np.random.default_rng(stream)
    )
    bar.total = len(drawn.params)
    spec = get_domain(config.domain)
    if config.book_inertia:
        booked = [with_book_inertia(p) for p in drawn.params]
        values = parameter_matrix(booked)
        drawn = drawn._replace(params=booked, values=values)
    module = MODULES[config.domain]
    entries = []
    for index, start in enumerate(range(0, len(drawn.params), config.shard_size)):
        stop = min(start + config.shard_size, len(drawn.params))
        entries.append(
            {
                "index": index,
                "file": shards.shard_name(index),
                "instances": list(range(start, stop)),
                "parameters": drawn.values[start:stop].tolist(),
                # MuJoCo steps per action of each instance (a fast acrobot's
                # step is finer, tasks.acrobot.sub_steps)
                "sub_steps": [module.sub_steps(p) for p in drawn.params[start:stop]],
                "sha256": None,
                "counts": None,
                "diverged": [],
            }
        )
        bar.update(stop - start)
    manifest = {
        "format": shards.FORMAT,
        # as read back: lists, exact floats (the entries are built so)
        "config": json.loads(json.dumps(config.manifest_config())),
        "parameter_names": [f.name for f in dataclasses.fields(spec.params_type)],
        "angle_dims": list(spec.angle_dims),
        "shards": entries,
        "complete": False,
        "software": software(),
    }
    return manifest


#: The first spawn key of each instance's episode stream (module docstring).
INSTANCE_STREAMS = 2

#: The packages whose versions a run's data depend on (recorded in the manifest).
DATA_PACKAGES = ("hipmdp", "numpy", "scipy", "mujoco", "dm-control")


def software() -> dict[str, Any]:
    """What the data depend on besides the config: the packages' versions and a
    SHA-256 over the source of `hipmdp`, `tasks` and the MJCF models (any edit
    changes it; a resumed run must not mix shards made by other code)."""
    import hipmdp
    import tasks

    digest = hashlib.sha256()
    sources = [
        (name, source_files(Path(package.__file__).parent))
        for name, package in (("hipmdp", hipmdp), ("tasks", tasks))
    ]
    models = importlib.resources.files("tasks.mjcf")  # as the models are read
    xml = sorted((f.name, f) for f in models.iterdir() if f.name.endswith(".xml"))
    sources.append(("mjcf", xml))
    for name, files in sources:
        for path, file in files:
            digest.update(f"{name}/{path}".encode() + b"\0")
            digest.update(file.read_bytes() + b"\0")
    return {
        "packages": package_versions(DATA_PACKAGES),
        "source_sha256": digest.hexdigest(),
    }


def source_files(root: Path) -> list[tuple[str, Path]]:
    """Every ``.py`` file under ``root``, subpackages' too, as ``(path relative to
    root, file)`` in the order of those paths (the same on every machine)."""
    return sorted((f.relative_to(root).as_posix(), f) for f in root.rglob("*.py"))


@functools.cache
def local_software() -> dict[str, Any]:
    """This process's `software()`, computed once (it reads every source file,
    ~12 ms): what a worker compares each shard's `ShardJob.software` with."""
    return software()


def check_software(expected: dict[str, Any] | None) -> None:
    """Raise OtherSoftwareError, naming this worker's host and what differs,
    unless this process runs the software `expected` (the client's); None
    checks nothing."""
    if expected is None:
        return
    own = local_software()
    if own != expected:
        raise OtherSoftwareError(
            f"{_this_worker()} runs other software than the client "
            f"({software_difference(expected, own)}); its shards would differ from "
            "the client's: run the workers from the client's code and packages"
        )


def _this_worker() -> str:
    """This process as a worker: a Dask worker's address, or its pid; and host."""
    host = socket.gethostname()
    if "distributed" in sys.modules:  # a pool worker need not import it
        from distributed import get_worker

        with contextlib.suppress(ValueError):  # not in a Dask worker
            return f"the Dask worker {get_worker().address} on host {host}"
    return f"the worker process {os.getpid()} on host {host}"


def software_difference(client: dict[str, Any], worker: dict[str, Any]) -> str:
    """What differs between the `software()` records of the client and a worker:
    `numpy 2.1.0 on the client, 2.0.2 on the worker; the source of ...`."""
    differences = [
        f"{name} {client['packages'].get(name)} on the client, "
        f"{worker['packages'].get(name)} on the worker"
        for name in sorted(set(client["packages"]) | set(worker["packages"]))
        if client["packages"].get(name) != worker["packages"].get(name)
    ]
    if client.get("source_sha256") != worker.get("source_sha256"):
        differences.append(
            "the source of hipmdp, tasks or the MJCF models (SHA-256 "
            f"{str(client.get('source_sha256'))[:12]}... on the client, "
            f"{str(worker.get('source_sha256'))[:12]}... on the worker)"
        )
    return "; ".join(differences) or "its software record"


def _worker_software(dask_worker: Any) -> dict[str, Any]:
    """`local_software()`, run on the Dask worker `dask_worker` by `client.run`."""
    return local_software()


def check_cluster_software(client: Any, expected: dict[str, Any]) -> None:
    """Raise OtherSoftwareError if a worker connected to the Dask `client` runs
    other software than `expected`, or cannot tell (it runs code older than
    `local_software`): an early, clear error before any shard is submitted.
    Workers that join later are checked by each shard (`run_shard`)."""
    answers = client.run(_worker_software, on_error="return")
    wrong = []
    for address, answer in sorted(answers.items()):
        if isinstance(answer, BaseException):
            wrong.append(
                f"the Dask worker {address} cannot tell its software "
                f"({type(answer).__name__}: {answer}; older code?)"
            )
        elif answer != expected:
            wrong.append(
                f"the Dask worker {address} runs other software than the client "
                f"({software_difference(expected, answer)})"
            )
    if wrong:
        more = f"; and {len(wrong) - 3} more" if len(wrong) > 3 else ""
        raise OtherSoftwareError(
            "; ".join(wrong[:3]) + more + "; its shards would differ from the "
            "client's: run the workers from the client's code and packages"
        )


def prepare(config: Config) -> tuple[dict[str, Any], list[int]]:
    """The manifest to continue from and the shards still to do; writes nothing.

    Raises:
        ValueError: if `config.out` holds a manifest of another run (listing the
            differences), or of this run unfinished without `config.resume`, or
            started by other software without `config.mixed_software`, or
            shard files or a progress log without a manifest. (This run
            finished: nothing to do.)
    """
    check_folder_out(config.out, "--out")
    if folder_locked(config.out):
        raise _busy(config.out)
    old = shards.read_manifest(config.out)
    if old is None:  # a run writes its manifest before anything else
        if any(config.out.glob("shard-*.npz")):
            raise ValueError(
                f"{config.out} holds shard files but no manifest; choose another --out"
            )
        if (config.out / shards.PROGRESS).exists():
            raise ValueError(
                f"{config.out} holds a {shards.PROGRESS} that no run of "
                "tasks.generate left (it has no manifest), which a run would "
                "replace; choose another --out"
            )
        _check_no_other_files(config.out)
    fresh = plan(config)
    if old is None:
        return fresh, [e["index"] for e in fresh["shards"]]
    differences = shards.config_differences(old["config"], fresh["config"])
    if differences:
        advice = "choose another --out"
        if config.resume:
            made = _options(old["config"], fresh["config"])
            advice = f"to resume it, pass the options it was made with ({made}), or "
            advice += "choose another --out"
        raise ValueError(
            f"{config.out} holds a different run ({'; '.join(differences)}); {advice}"
        )
    layout = [(e["instances"], e["parameters"]) for e in old["shards"]]
    if layout != [(e["instances"], e["parameters"]) for e in fresh["shards"]]:
        order = ""  # the draws follow the --vary order, which the manifest loses
        if len(config.distribution.vary) > 1:
            order = " or with the --vary in another order"
        raise ValueError(
            f"{config.out} holds this configuration but other instances (made by "
            f"another version of the code{order}?); choose another --out"
        )
    nominal = MODULES[config.domain].N_SUB_STEPS
    for entry, new in zip(old["shards"], fresh["shards"], strict=True):
        # a run from before 2026-12-04 names none: every instance took nominal steps
        steps = entry.get("sub_steps", [nominal] * len(entry["instances"]))
        if steps != new["sub_steps"]:
            raise ValueError(
                f"{config.out} holds this run, but its shard {entry['index']} was "
                "simulated with other steps per action than this version takes "
                "(fast acrobots integrate with finer steps, tasks.acrobot.sub_steps; "
                "a manifest that records no sub_steps is taken to have run the "
                "nominal count everywhere); choose another --out"
            )
        entry["sub_steps"] = steps
    todo, damaged = [], []  # damaged: recorded finished, but the file differs
    for entry in old["shards"]:
        if not shards.shard_is_valid(config.out, entry):
            if entry["sha256"] is not None:
                damaged.append(entry["file"])
            entry.update(sha256=None, counts=None, diverged=[])
            todo.append(entry["index"])
    recorded = old.get("software")  # None: a run from before 2026-12-04, made
    # by code that seeded shards, not instances; a finished run (nothing to do)
    # is left as it is, whatever made it
    kept = [e["index"] for e in old["shards"] if e["index"] not in todo]
    # no shard kept (killed before the first finished): nothing to mix
    if todo and kept and recorded != fresh["software"]:
        if not config.mixed_software:
            raise ValueError(
                f"{config.out} holds this run, made by other software "
                f"({_software_change(recorded, fresh['software'])}): its shards "
                "would mix with data this version makes; choose another --out, or "
                "pass --resume --mixed-software to continue it all the same (the "
                "manifest then records which shards each software made)"
            )
        earlier = old.setdefault("earlier_software", [])
        listed = {i for entry in earlier for i in entry["shards"]}
        earlier.append(
            {"software": recorded, "shards": [i for i in kept if i not in listed]}
        )
    if todo and "earlier_software" in old:  # a shard redone is made by this version
        old["earlier_software"] = [
            entry | {"shards": [i for i in entry["shards"] if i not in todo]}
            for entry in old["earlier_software"]
        ]
        old["earlier_software"] = [e for e in old["earlier_software"] if e["shards"]]
        if not old["earlier_software"]:
            del old["earlier_software"]
    if todo:  # what the shards still to do are made by
        old["software"] = fresh["software"]
    if todo and not config.resume:
        bad = ""
        if damaged:
            more = f" and {len(damaged) - 5} more" if len(damaged) > 5 else ""
            bad = "; damaged (missing, or not matching its checksum): "
            bad += ", ".join(damaged[:5]) + more
        raise ValueError(
            f"{config.out} holds this run, unfinished ({len(todo)} of "
            f"{len(old['shards'])} shards to do{bad}); pass --resume to continue it"
        )
    if todo:  # a finished run with a damaged shard is unfinished until it is redone
        old["complete"] = False
    return old, todo


def _options(old: dict[str, Any], new: dict[str, Any]) -> str:
    """The command-line options that give the manifest config `old` where it
    differs from `new`: `--instances 48 --shard-size 4`, `without --max-steps`;
    every `--vary` of `old` if one range differs."""
    old, new = shards.flat_config(old), shards.flat_config(new)
    given, without = [], []
    for key in sorted(set(old) | set(new)):
        name = key.removeprefix("distribution.")
        if old.get(key) == new.get(key) or name.startswith("vary."):
            continue
        flag = "--" + {"kind": "distribution"}.get(name, name).replace("_", "-")
        if old.get(key) is None or old.get(key) is False:  # not 0 (seed 0)
            without.append(flag)
        else:
            given.append(flag if old[key] is True else f"{flag} {old[key]}")
    if any(old.get(k) != new.get(k) for k in {*old, *new} if ".vary." in k):
        prefix = "distribution.vary."
        ranges = {k.removeprefix(prefix): v for k, v in old.items() if prefix in k}
        default = DEFAULT_VARY.get(old.get("domain"), {})
        if ranges == {name: list(bounds) for name, bounds in default.items()}:
            without.append("--vary")
        else:  # the manifest keeps no order: the parameters' own
            fields = dataclasses.fields(get_domain(old["domain"]).params_type)
            given += [
                f"--vary {f.name}={ranges[f.name][0]!r}:{ranges[f.name][1]!r}"
                for f in fields
                if f.name in ranges
            ]
            if len(ranges) > 1:  # but the draws follow the order given
                given.append("(in the order they were first given)")
    parts = [" ".join(given)] if given else []
    return "; ".join(parts + ([f"without {' '.join(without)}"] if without else []))


def _check_no_other_files(out: Path) -> None:
    """Raise ValueError if the folder `out`, which holds no manifest, holds
    anything but what a run killed while writing its first manifest leaves."""
    if not out.is_dir():
        return
    left = set(atomic_temporaries(out, shards.MANIFEST))
    found = sorted(p.name for p in out.iterdir() if p not in left)
    if found:
        more = f" and {len(found) - 3} more" if len(found) > 3 else ""
        listed = ", ".join(found[:3]) + more
        raise ValueError(
            f"{out} is not empty ({listed}) and holds no run of tasks.generate (no "
            f"{shards.MANIFEST}); choose an empty or new folder for --out"
        )


def _software_change(recorded: dict | None, fresh: dict) -> str:
    """What changed between the software that started a run and this one."""
    if recorded is None:
        return (
            "it records none: made before 2026-12-04, when each shard's episodes "
            "were drawn from one stream; each instance has its own now"
        )
    changed = [
        name
        for name in DATA_PACKAGES
        if recorded["packages"].get(name) != fresh["packages"][name]
    ]
    if recorded.get("source_sha256") != fresh["source_sha256"]:
        changed.append("the source of hipmdp, tasks or the MJCF models")
    return f"{', '.join(changed) or 'its record'} changed since it started"


@one_blas_thread
def run_shard(job: ShardJob) -> ShardOutput:
    """Gather one shard's transitions (runs in a worker, in-process, forkserver or
    Dask alike: at one BLAS thread, so a Sarsa policy's data do not depend on
    where it runs). A worker that runs other software than `job.software`, the
    client's, refuses the shard (OtherSoftwareError)."""
    check_software(job.software)
    spec = get_domain(job.domain)
    params = [spec.params_type(*row) for row in job.values]
    streams = [
        np.random.default_rng(
            np.random.SeedSequence(job.entropy, spawn_key=(*job.spawn_key, g))
        )
        for g in job.instances
    ]
    kwargs = {} if job.max_steps is None else {"max_steps": job.max_steps}
    collection = POLICIES[job.policy](
        job.domain,
        params,
        episodes_per_instance=job.episodes_per_instance,
        rng=streams,
        instance_ids=list(job.instances),
        **kwargs,
    )
    counts = {
        "episodes": collection.n_episodes,
        "transitions": len(collection.transitions),
        "diverged_episodes": len(collection.diverged),
    }
    data = shards.shard_bytes(collection.transitions, collection.parameters)
    return ShardOutput(
        job.index, data, counts, [d._asdict() for d in collection.diverged]
    )


class InlineExecutor(cf.Executor):
    """Runs each task in the calling thread when it is submitted."""

    def submit(self, fn, /, *args, **kwargs) -> cf.Future:
        future: cf.Future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as error:  # handed to the caller via the future
            future.set_exception(error)
        return future


@contextlib.contextmanager
def executor_for(
    workers: int, scheduler: str | None, software: dict[str, Any] | None = None
) -> Iterator[cf.Executor]:
    """In-process for one worker, a process pool for several, or a Dask cluster;
    on a cluster, the workers connected must run `software` (if given), or
    OtherSoftwareError is raised before any shard is submitted."""
    if scheduler is not None:
        try:
            import distributed
        except ImportError:
            raise ValueError(
                '--scheduler needs Dask: pip install -e ".[dask]"'
            ) from None
        _check_scheduler_answers(scheduler)
        with distributed.Client(scheduler) as client:
            if software is not None:
                check_cluster_software(client, software)
            executor = client.get_executor()
            # the cluster's threads, as workers join and leave (`_in_flight`)
            executor.threads = functools.partial(_cluster_threads, client)
            yield executor
    elif workers == 1:
        yield InlineExecutor()
    else:
        # A fresh server process imports the simulation code once and forks the
        # workers: no threads or MuJoCo state of the caller are copied, no import
        # per worker. Not this module itself: under `python -m tasks.generate` the
        # server also runs it as the main module, and runpy warns when it was
        # imported already.
        # Ctrl-C reaches the workers too: an idle one ends without a traceback
        # (SystemExit), a busy one's shard fails, and the caller reports it;
        # unless the caller ignores Ctrl-C (started in the background), then
        # they do too. SIGTERM keeps its default, ending a worker at once: the
        # pool terminates its workers so when one dies, and one blocked writing
        # a large result no one reads would never handle a signal in Python.
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(["tasks.collect", "tasks.rollout"])
        # And a worker ends when this process is gone (experiment.exit_with).
        ignored = signal.getsignal(signal.SIGINT) == signal.SIG_IGN
        action = signal.SIG_IGN if ignored else _exit_quietly
        with cf.ProcessPoolExecutor(
            workers,
            mp_context=context,
            initializer=_init_worker,
            initargs=(action, os.getpid()),
        ) as pool:
            yield pool


# seconds past Dask's connect timeout before a connection that Dask made, but
# whose handshake never came, is given up (`_check_scheduler_answers`)
_HANDSHAKE_GRACE = 1.0


def _check_scheduler_answers(address: str) -> None:
    """Raise OSError unless a Dask scheduler at `address` answers within Dask's
    connect timeout (`distributed.comm.timeouts.connect`, 30 s by default).

    Dask's connect reads the scheduler's handshake without a deadline: an
    address that accepts the connection and stays silent (another server, the
    dashboard's port) made `Client` wait for ever, `Client(timeout=...)` too.
    A connection of our own, the handshake included, gets the deadline; the
    error is Dask's own for a scheduler that cannot be reached. Without an
    answer after ``min(2 s, timeout / 2)`` (Dask retries a refused connection
    until the timeout: a scheduler may be starting), a line on stderr says what
    the run waits for. The deadline over Dask's retries and the handshake is a
    little later than Dask's own (`_HANDSHAKE_GRACE`), or it would fire first
    and call a refused connection an accepted one."""
    import asyncio

    import dask
    from dask.utils import parse_timedelta
    from distributed.comm import connect, parse_address
    from distributed.security import Security

    if parse_address(address)[0] == "inproc":  # in this process: it answers
        return
    timeout = parse_timedelta(
        dask.config.get("distributed.comm.timeouts.connect"), default="seconds"
    )
    arguments = Security().get_connection_args("client")

    async def handshake() -> None:
        answer = asyncio.ensure_future(
            asyncio.wait_for(
                connect(address, timeout=timeout, **arguments),
                timeout + _HANDSHAKE_GRACE,
            )
        )
        done, _ = await asyncio.wait({answer}, timeout=min(2.0, timeout / 2))
        if not done:
            print(
                f"--scheduler {address}: no answer yet; waiting up to {timeout:g} s "
                "(distributed.comm.timeouts.connect)",
                file=sys.stderr,
            )
        comm = await answer
        await comm.close()

    try:  # in a thread of its own: the caller may run an event loop
        with cf.ThreadPoolExecutor(1) as thread:
            thread.submit(asyncio.run, handshake()).result()
    except TimeoutError:  # (an OSError: before the next clause)
        raise OSError(
            f"Timed out trying to connect to {address} after {timeout:g} s (it "
            "accepted the connection but did not answer as a Dask scheduler)"
        ) from None
    except OSError:
        raise
    except Exception as error:  # something else answered
        raise OSError(
            f"{address} did not answer as a Dask scheduler "
            f"({type(error).__name__}: {error})"
        ) from None


def _init_worker(action: Any, owner: int) -> None:
    """A pool worker's start: Ctrl-C handled by ``action``; the worker ends when
    the process ``owner`` is gone (:func:`tasks.experiment.exit_with`); tqdm's
    lock is a thread lock (a worker shows no bar): its default, a
    multiprocessing lock, is a named semaphore in a forkserver's worker, which
    a worker ended by SIGTERM left behind, and the resource tracker warned of
    "leaked semaphore objects" after the run's stop line."""
    from tqdm import tqdm

    signal.signal(signal.SIGINT, action)
    tqdm.set_lock(threading.RLock())
    exit_with(owner)


def _exit_quietly(signum: int, frame: Any) -> None:
    """A pool worker's Ctrl-C: end without a traceback (as SystemExit does)."""
    raise SystemExit(128 + signum)


class _Deferral:
    """While `depth` > 0 a stop signal is held in `pending` (`_signals_deferred`)."""

    depth = 0
    pending: BaseException | None = None


def _raise_stop(signum: int, frame: Any) -> None:
    """`main`'s handler of Ctrl-C and SIGTERM: raise KeyboardInterrupt or
    Terminated, at once or, while a finished shard is written, once it is."""
    error = Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()
    if _Deferral.depth:
        _Deferral.pending = _Deferral.pending or error
        return
    raise error


@contextlib.contextmanager
def _stop_signals() -> Iterator[None]:
    """Within: SIGTERM raises Terminated and Ctrl-C KeyboardInterrupt, each held
    back while a finished shard is written (`_signals_deferred`). A signal that
    is ignored (a run started in the background, under nohup) or handled by the
    caller is left as it is; so is every signal outside the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    for signum, default in [
        (signal.SIGINT, signal.default_int_handler),
        (signal.SIGTERM, signal.SIG_DFL),
    ]:
        if signal.getsignal(signum) is default:
            previous[signum] = signal.signal(signum, _raise_stop)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        _Deferral.depth, _Deferral.pending = 0, None


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Within: a stop signal (`_stop_signals`) waits, and is raised on leaving,
    so that a finished shard is written whole and recorded, no temporary file
    left behind."""
    _Deferral.depth += 1
    try:
        yield
    finally:
        _Deferral.depth -= 1
    if not _Deferral.depth and _Deferral.pending is not None:
        error, _Deferral.pending = _Deferral.pending, None
        raise error


def generate(
    config: Config,
    *,
    executor: cf.Executor | None = None,
    prepared: tuple[dict[str, Any], list[int]] | None = None,
) -> Generated:
    """Run (or continue) the run `config` describes; see the module docstring.

    Args:
        config: the run.
        executor: where shards are computed; default from `config.workers` and
            `config.scheduler`.
        prepared: what `prepare(config)` returned just before, if the caller
            called it (drawing a large run's instances twice costs seconds).
    """
    manifest, todo = prepare(config) if prepared is None else prepared
    out = config.out
    if not todo and manifest["complete"]:  # finished already: touch nothing ...
        shards.remove_progress(out)  # ... but a log a kill left (the manifest has it)
        return Generated(out / shards.MANIFEST, manifest, ())
    entries = {e["index"]: e for e in manifest["shards"]}
    split = SPLITS.index(config.distribution.split)
    jobs = [
        ShardJob(
            config.domain,
            config.policy,
            k,
            tuple(entries[k]["instances"]),
            tuple(tuple(row) for row in entries[k]["parameters"]),
            config.episodes_per_instance,
            config.max_steps,
            config.seed,
            (INSTANCE_STREAMS, split),
            manifest.get("software"),  # what makes the shards to do: this client
        )
        for k in todo
    ]
    context = (
        contextlib.nullcontext(executor)
        if executor is not None
        else executor_for(config.workers, config.scheduler, manifest.get("software"))
    )
    bar = tqdm(
        total=len(entries),
        initial=len(entries) - len(todo),
        desc=f"{config.domain} shards",
        disable=not config.progress,
    )
    with context as pool, bar, contextlib.ExitStack() as stack:
        # the manifest once the workers (or the Dask scheduler) are there: a
        # scheduler that cannot be reached leaves no unfinished run behind
        out.mkdir(parents=True, exist_ok=True)
        # one run at a time in a folder (held until this block ends, or the
        # process dies): two runs at once both reported success over shards
        # that failed their checksums
        try:
            lock = lock_folder(out, wait=False)
        except BlockingIOError:
            raise _busy(out) from None
        stack.callback(lambda: lock is not None and os.close(lock))
        shards.remove_temporaries(out)
        path = shards.write_manifest(out, manifest)  # with what was done before
        shards.remove_progress(out)  # the manifest holds it now
        pending: set[cf.Future] = set()
        queue = list(reversed(jobs))

        def keep(future: cf.Future) -> None:
            """Write a finished shard and record it (raises a failed one's
            error); a stop signal waits until it is written and recorded."""
            result = future.result()
            with _signals_deferred():
                entry = entries[result.index]
                entry["sha256"] = shards.write_shard(out, result.index, result.data)
                entry["counts"] = result.counts
                entry["diverged"] = result.diverged
                shards.append_progress(out, entry)
                bar.update()

        try:
            threads = getattr(pool, "threads", None)  # a Dask cluster's
            warned = threads is None  # warned of no workers, or nothing to warn of
            while queue or pending:
                in_flight = _in_flight(pool, config)  # as workers join and leave
                while queue and len(pending) < in_flight:
                    pending.add(pool.submit(run_shard, queue.pop()))
                done, _ = cf.wait(
                    pending,
                    timeout=None if warned else NO_WORKERS_WARNING,
                    return_when=cf.FIRST_COMPLETED,
                )
                if not done and not warned and threads() == 0:
                    tqdm.write(
                        f"python -m tasks.generate: warning: no Dask worker has "
                        f"been connected to {config.scheduler} for "
                        f"{NO_WORKERS_WARNING:g} s; waiting for one (dask worker "
                        f"{config.scheduler})",
                        file=sys.stderr,
                    )
                    warned = True
                # the finished shards first: a failed or cancelled one's error
                # (Ctrl-C in the inline executor, a lost Dask scheduler) is
                # raised once they are kept (`exception()` of a cancelled future
                # raises, so `cancelled()` is asked first)
                for future in sorted(done, key=_failed):
                    pending.discard(future)
                    keep(future)
        except BaseException:  # stopped: the shards not started are not run ...
            _cancel_waiting(pool, pending, owned=executor is None)
            for future in pending:  # ... and those finished meanwhile are kept
                if future.done() and not _failed(future):
                    keep(future)
            raise
    manifest["complete"] = True
    shards.write_manifest(out, manifest)
    shards.remove_progress(out)
    return Generated(path, manifest, tuple(todo))


def _cancel_waiting(
    pool: cf.Executor, futures: set[cf.Future], owned: bool = True
) -> None:
    """Cancel the ``futures`` of ``pool`` that have not started.

    A process pool the run made (``owned``) is shut down instead, its workers
    ended and its queued shards never run (:func:`tasks.experiment.end_workers`); a
    caller's pool, ``generate(executor=...)``, is left usable, and the caller's
    own futures in it alone. Not cancelled one by one: a future cancelled
    here, as the pool's manager thread failed the futures of a worker killed by
    the same stop (SIGTERM to the process group), raised InvalidStateError in
    that thread, printed as its traceback, and the pool skipped its clean-up
    (CPython gh-107219, fixed in 3.12). Ended: the workers' running shards
    would be discarded, and this process's exit waited for them (a SIGTERM to
    it alone, not its group, printed the run's stop line and then exited only
    when they were done, minutes later)."""
    if owned and isinstance(pool, cf.ProcessPoolExecutor):
        end_workers(pool)
    else:
        for future in futures:
            future.cancel()


#: Seconds a Dask run waits with no worker before it warns (once; it waits on).
NO_WORKERS_WARNING = 30.0

#: Shards in flight on a Dask cluster at least (before its workers join).
MIN_IN_FLIGHT = 64


def _in_flight(pool: cf.Executor, config: Config) -> int:
    """How many shards to keep submitted: two per worker (one running, one
    waiting), on a Dask cluster per thread as the cluster now has (it was 64
    whatever the cluster, leaving a larger one idle), at least MIN_IN_FLIGHT."""
    threads = getattr(pool, "threads", None)  # a Dask cluster's (executor_for)
    if threads is not None:
        return max(2 * threads(), MIN_IN_FLIGHT)
    if config.scheduler is not None:  # a Dask executor passed in
        return MIN_IN_FLIGHT
    return 2 * config.workers


def _cluster_threads(client: Any) -> int:
    """The threads of the Dask workers connected to `client` now (one call to
    the scheduler; `Client.nthreads`, in every release the `dask` extra
    allows, where `scheduler_info(n_workers=...)` is 2025's)."""
    return int(sum(client.nthreads().values()))


def _failed(future: cf.Future) -> bool:
    """Whether a finished future holds no result: cancelled or failed."""
    return future.cancelled() or future.exception() is not None


def main(argv: Sequence[str] | None = None) -> Generated:
    """Command-line entry point; returns what was written.

    Ctrl-C stops it with status 130, SIGTERM with 143, each with one line on
    stderr: how many shards are finished (kept) and the command that resumes
    the run. So does any error once the run has begun, with status 1: one line
    for a worker or cluster that failed (`_cluster_failure`), the line and the
    traceback for anything else (a bug)."""
    printable_output()
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    config = parse_config(argv)
    started = False
    try:
        with _stop_signals():
            try:
                prepared = prepare(config)  # a bad --out stops here, before writing
            except ValueError as error:
                parser.error(str(error))
            for warning in config.distribution.far_from_nominal():
                print(f"{parser.prog}: warning: {warning}", file=sys.stderr)
            if config.resume and shards.read_manifest(config.out) is None:
                # a batch script may always pass --resume; a mistyped --out is told
                print(
                    f"{parser.prog}: --resume: {config.out} holds no run yet; "
                    "starting one",
                    file=sys.stderr,
                )
            finished = prepared[0]["complete"] and not prepared[1]
            started = True
            result = generate(config, prepared=prepared)
    except KeyboardInterrupt:
        with stops_ignored():  # a second stop would cut the line short
            stopped = _interrupted(config, argv, started=started)
            parser.exit(130, f"{parser.prog}: {stopped}\n")
    except Terminated:
        with stops_ignored():
            stopped = _interrupted(config, argv, started=started, what="terminated")
            parser.exit(143, f"{parser.prog}: {stopped}\n")
    except BusyError as error:  # another run took --out after `prepare` looked
        parser.error(str(error))
    except cf.CancelledError:  # Dask cancels every task when it loses the scheduler
        stopped = _interrupted(config, argv, started=True, what="stopped")
        parser.exit(
            1,
            f"{parser.prog}: error: shards were cancelled (on a Dask cluster: "
            f"the scheduler was lost); {stopped}\n",
        )
    except Exception as error:
        if not started:
            raise
        stopped = _interrupted(config, argv, started=True, what="stopped")
        if isinstance(error, OSError) and stopped.startswith("stopped before"):
            # a scheduler that cannot be reached: nothing written
            parser.exit(1, f"{parser.prog}: error: {error}\n")
        if _cluster_failure(error):  # a full disk, a killed worker, other code
            parser.exit(1, f"{parser.prog}: error: {_describe(error)}; {stopped}\n")
        print(
            f"{parser.prog}: error: the run stopped on the error below; {stopped}",
            file=sys.stderr,
        )
        raise
    counts = [e["counts"] for e in result.content["shards"]]
    done = "nothing to do: already finished," if finished else "wrote"
    n_instances = sum(len(e["instances"]) for e in result.content["shards"])
    print(
        f"{done} {count(len(counts), 'shard')} and {result.manifest}: "
        f"{count(sum(c['transitions'] for c in counts), 'transition')}, "
        f"{count(n_instances, 'instance')}, "
        f"{count(sum(c['diverged_episodes'] for c in counts), 'diverged episode')} "
        f"({count(len(result.redone), 'shard')} generated now)"
    )
    return result


def _cluster_failure(error: BaseException) -> bool:
    """Whether `error` is a failure of the machines, not of this code: said in
    one line, no traceback. An OSError (a scheduler lost, a full disk), a
    worker that runs other software, a pool's process that died (killed, out of
    memory), a task whose Dask workers died (KilledWorker)."""
    if isinstance(error, OSError | OtherSoftwareError | cf.BrokenExecutor):
        return True
    dask = sys.modules.get("distributed.scheduler")
    return dask is not None and isinstance(error, dask.KilledWorker)


def _describe(error: BaseException) -> str:
    """`error` as a line: its message, named by its kind where the message does
    not say what happened."""
    if isinstance(error, OSError | OtherSoftwareError):
        return str(error)
    return f"{type(error).__name__}: {str(error).rstrip('.')}"


def _interrupted(
    config: Config, argv: list[str], *, started: bool, what: str = "interrupted"
) -> str:
    """What a run stopped by Ctrl-C (or, `what`, otherwise) leaves, and the
    command that continues it."""
    command = ["python", "-m", "tasks.generate", *argv]
    manifest = shards.read_manifest(config.out) if started else None
    if manifest is None:  # stopped before the run wrote anything
        return f"{what} before the run began; run again: {shlex.join(command)}"
    entries = manifest["shards"]
    kept = sum(e["sha256"] is not None for e in entries)  # as a resume finds them
    plus = "" if config.resume else " plus --resume"
    resume = shlex.join(command + ([] if config.resume else ["--resume"]))
    return (
        f"{what}: {kept} of {len(entries)} shards finished are kept in "
        f"{config.out}; resume with the same command{plus}: {resume}"
    )


if __name__ == "__main__":
    # Run as `tasks.generate`, not as `__main__`: a Dask client pickles the
    # functions and classes of `__main__` by value, so a worker ran the client's
    # `run_shard` with its own other modules (and could not find
    # `local_software`, which is pickled by name); named by module, a worker runs
    # its own code, which `check_software` compares with the client's.
    importlib.import_module("tasks.generate").main()
