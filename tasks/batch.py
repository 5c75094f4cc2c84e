"""Batch data as the paper gathers it (its "Sarsa" on a Fourier basis; λ and ε
are ours): Sarsa(λ) agents learning on each training instance, every transition
they see kept (``tasks.collect.collect_sarsa``).

Each (instance, repetition) is one job with its own seed spawned from one
``SeedSequence``, so the data do not depend on how many worker processes ran them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from hipmdp.data import ParameterTable, Transitions
from tasks._common import parameter_matrix, parameter_names
from tasks.collect import collect_sarsa
from tasks.experiment import pool_map, seed_value


def _job(args) -> Transitions:
    domain, instance, params, seed, n_episodes, max_steps = args
    entropy, spawn_key = seed
    rng = np.random.default_rng(np.random.SeedSequence(entropy, spawn_key=spawn_key))
    out = collect_sarsa(
        domain, [params], episodes_per_instance=n_episodes, rng=rng,
        instance_ids=[instance], max_steps=max_steps,
    )  # fmt: skip
    if out.diverged:
        raise RuntimeError(f"{domain} instance {instance} diverged: {out.diverged}")
    return out.transitions


def gather_batch(
    domain: str,
    instances: Sequence[Any],
    *,
    repetitions: int,
    episodes: int,
    max_steps: int,
    seed: np.random.SeedSequence,
    workers: int = 1,
    progress: bool = False,
) -> Transitions:
    """Sarsa transitions on every instance; instance ids ``0..B-1`` in order.

    Args:
        domain: ``"acrobot"`` or ``"cartpole"``.
        instances: the parameter dataclasses of the training instances.
        repetitions: independent agents per instance (the paper's cart-pole: 5;
            not stated for the acrobot).
        episodes: episodes per agent (the paper's cart-pole: 30); max_steps:
            their step limit.
        seed: all streams are spawned from it; workers: processes.
    """
    seeds = seed.spawn(len(instances) * repetitions)
    jobs = [
        (
            domain,
            b,
            params,
            seed_value(s),
            episodes,
            max_steps,
        )  # fmt: skip
        for b, params in enumerate(instances)
        for s in seeds[b * repetitions : (b + 1) * repetitions]
    ]
    parts = pool_map(_job, jobs, workers=workers, desc="batch data (Sarsa)",
                     progress=progress)  # fmt: skip
    return Transitions.concatenate(parts)


def parameter_table(instances: Sequence[Any]) -> ParameterTable:
    """The parameters of ``instances`` (one domain's dataclasses), ids ``0..B-1``."""
    names = parameter_names(type(instances[0]))
    values = parameter_matrix(instances)
    return ParameterTable(
        instances=np.arange(len(instances)), names=names, values=values
    )


def gather_and_save(
    domain: str, instances: Sequence[Any], path, *, config, seed, progress: bool
) -> Transitions:
    """:func:`gather_batch` with an experiment config's sizes (``batch_repetitions``,
    ``batch_episodes``, ``batch_max_steps``, ``workers``), saved with its parameter
    table to ``path``."""
    batch = gather_batch(
        domain, instances, repetitions=config.batch_repetitions,
        episodes=config.batch_episodes, max_steps=config.batch_max_steps,
        seed=seed, workers=config.workers, progress=progress,
    )  # fmt: skip
    batch.save(path, table=parameter_table(instances))
    return batch
