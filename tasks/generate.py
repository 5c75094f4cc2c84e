"""Generate a transition dataset: draw instances of a domain, run a policy on each,
write one `.npz` (transitions + parameter table) and a JSON summary.

    python -m tasks.generate --domain acrobot --instances 4 \\
        --episodes-per-instance 2 --seed 0 --out runs/data

Instances vary the parameters named by `--vary NAME=LOW:HIGH` (default: the two
link masses in [0.7, 1.3] for the acrobot, as in the paper; the pole mass in
[0.05, 0.5] kg and half-length in [0.25, 1.0] m for the cart-pole); the others stay
nominal. `--distribution uniform` (default) draws `--instances` of them
independently and uniformly; `--grid K` takes the `K^p` points of a regular grid
over the `p` varied parameters instead.

Writes `OUT/<domain>_seed<S>.npz` (`hipmdp.Transitions.load` and
`hipmdp.data.ParameterTable.load` read it) and `OUT/<domain>_seed<S>.json` (config,
seed, counts, diverged episodes, dataset file name), each atomically. The same
arguments give the same files. Bad options stop with a message before anything is
written.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from hipmdp.data import atomic_write
from tasks.collect import DOMAINS, Collection, collect, get_domain

#: Parameters varied when no `--vary` is given: name -> (low, high).
DEFAULT_VARY = {
    "acrobot": {"link_mass_1": (0.7, 1.3), "link_mass_2": (0.7, 1.3)},
    "cartpole": {"pole_mass": (0.05, 0.5), "pole_half_length": (0.25, 1.0)},
}


@dataclasses.dataclass(frozen=True)
class Config:
    """A validated generation request (see the module docstring for the options)."""

    domain: str
    instances: int
    episodes_per_instance: int
    seed: int
    out: Path
    vary: dict[str, tuple[float, float]]
    grid: int | None
    distribution: str
    policy: str
    max_steps: int | None
    progress: bool

    @property
    def stem(self) -> str:
        return f"{self.domain}_seed{self.seed}"


class Generated(NamedTuple):
    """Paths written and what was gathered."""

    dataset: Path
    summary: Path
    collection: Collection


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m tasks.generate",
        description="Gather transitions from instances of a domain into one .npz.",
    )
    parser.add_argument("--domain", required=True, choices=sorted(DOMAINS))
    parser.add_argument(
        "--instances", type=int, default=None, help="instances drawn (default 4)"
    )
    parser.add_argument("--episodes-per-instance", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/data"))
    parser.add_argument(
        "--vary",
        action="append",
        metavar="NAME=LOW:HIGH",
        help="a varied parameter and its range (repeatable)",
    )
    sampling = parser.add_mutually_exclusive_group()
    sampling.add_argument("--grid", type=int, metavar="K", help="K points per param")
    sampling.add_argument("--distribution", choices=["uniform"], default=None)
    parser.add_argument("--policy", choices=["random"], default="random")
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--no-progress", action="store_true")
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
    if args.grid is not None and args.instances is not None:
        raise ValueError("--instances and --grid are exclusive (grid gives K^p)")
    for name in ("instances", "episodes_per_instance", "grid", "max_steps"):
        value = getattr(args, name)
        if value is not None and value < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    names = [f.name for f in dataclasses.fields(spec.params_type)]
    vary = dict(DEFAULT_VARY[args.domain])
    if args.vary:
        vary = {}
        for item in args.vary:
            name, low, high = _parse_range(item)
            if name not in names:
                raise ValueError(f"--vary {item}: {args.domain} parameters are {names}")
            vary[name] = (low, high)
    for name, (low, high) in vary.items():
        for value in (low, high):  # the dataclass checks the documented bounds
            spec.params_type(**{name: value})
    return Config(
        domain=args.domain,
        instances=4 if args.instances is None else args.instances,
        episodes_per_instance=args.episodes_per_instance,
        seed=args.seed,
        out=args.out,
        vary=vary,
        grid=args.grid,
        distribution=args.distribution or "uniform",
        policy=args.policy,
        max_steps=args.max_steps,
        progress=not args.no_progress,
    )


def _parse_range(item: str) -> tuple[str, float, float]:
    try:
        name, bounds = item.split("=")
        low, high = (float(x) for x in bounds.split(":"))
    except ValueError:
        raise ValueError(f"--vary expects NAME=LOW:HIGH, got {item!r}") from None
    if not low <= high:
        raise ValueError(f"--vary {item}: LOW must be <= HIGH")
    return name, low, high


def draw_instances(config: Config, *, rng: np.random.Generator) -> list[Any]:
    """The instances' parameters: a grid or independent uniform draws.

    Uniform: each varied parameter `~ U[low, high]` independently, `config.instances`
    times. Grid: `np.linspace(low, high, K)` per varied parameter, all `K^p`
    combinations (the first parameter varies slowest).
    """
    params_type = get_domain(config.domain).params_type
    names = list(config.vary)
    lows = np.array([config.vary[n][0] for n in names])
    highs = np.array([config.vary[n][1] for n in names])
    if config.grid is not None:
        axes = [
            np.linspace(lo, hi, config.grid) for lo, hi in zip(lows, highs, strict=True)
        ]
        points = np.array(list(itertools.product(*axes)))
    else:
        points = rng.uniform(lows, highs, size=(config.instances, len(names)))
    return [params_type(**dict(zip(names, row, strict=True))) for row in points]


def generate(config: Config) -> Generated:
    """Draw instances, gather transitions, write the dataset and its summary."""
    params_stream, collect_stream = np.random.SeedSequence(config.seed).spawn(2)
    instances = draw_instances(config, rng=np.random.default_rng(params_stream))
    collection = collect(
        config.domain,
        instances,
        episodes_per_instance=config.episodes_per_instance,
        rng=np.random.default_rng(collect_stream),
        max_steps=config.max_steps,
        progress=config.progress,
    )
    config.out.mkdir(parents=True, exist_ok=True)
    dataset = config.out / f"{config.stem}.npz"
    collection.transitions.save(dataset, collection.parameters)
    summary = {
        "config": {
            k: str(v) if isinstance(v, Path) else v
            for k, v in dataclasses.asdict(config).items()
        },
        "seed": config.seed,
        "dataset": dataset.name,
        "parameter_names": list(collection.parameters.names),
        "counts": {
            "instances": len(instances),
            "episodes": collection.n_episodes,
            "transitions": len(collection.transitions),
            "diverged_episodes": len(collection.diverged),
        },
        "diverged": [d._asdict() for d in collection.diverged],
    }
    path = config.out / f"{config.stem}.json"
    text = json.dumps(summary, indent=2) + "\n"
    atomic_write(path, lambda fh: fh.write(text.encode()))
    return Generated(dataset, path, collection)


def main(argv: Sequence[str] | None = None) -> Generated:
    """Command-line entry point; returns what was written."""
    result = generate(parse_config(argv))
    counts = json.loads(result.summary.read_text())["counts"]
    print(
        f"wrote {result.dataset} ({counts['transitions']} transitions, "
        f"{counts['instances']} instances, {counts['diverged_episodes']} diverged "
        f"episodes) and {result.summary}"
    )
    return result


if __name__ == "__main__":
    main()
