"""`python -m tasks.generate`: in-process smoke runs, reproducible files, the grid,
every policy, and bad options that stop before anything is written."""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import json
import os
import shlex
import signal
import threading
import time

import numpy as np
import pytest

from hipmdp import Transitions, shards
from hipmdp.data import ParameterTable
from tasks import collect, generate
from tasks.acrobot import AcrobotParams

TINY = ["--instances", "3", "--episodes-per-instance", "2", "--max-steps", "10"]
QUIET = ["--no-progress", "--shard-size", "2"]


def test_main_writes_loadable_shards_and_a_manifest(tmp_path, capsys):
    out = tmp_path / "data"
    result = generate.main(
        ["--domain", "acrobot", "--seed", "3", "--out", str(out), *TINY, *QUIET]
    )
    assert sorted(p.name for p in out.iterdir()) == [
        "manifest.json",
        "shard-00000.npz",
        "shard-00001.npz",
    ]
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest == result.content and manifest["complete"]
    assert manifest["config"]["seed"] == 3
    assert [e["instances"] for e in manifest["shards"]] == [[0, 1], [2]]
    first = Transitions.load(out / "shard-00000.npz")
    table = ParameterTable.load(out / "shard-00000.npz")
    assert manifest["shards"][0]["counts"] == {
        "episodes": 4,
        "transitions": len(first),
        "diverged_episodes": 0,
    }
    assert len(first) == 4 * 10 and first.angle_dims == (0, 1)
    np.testing.assert_array_equal(table.instances, [0, 1])
    np.testing.assert_array_equal(table.values, manifest["shards"][0]["parameters"])
    dataset = shards.load_dataset(out)
    everything = dataset.parameters
    masses = everything.values[:, :2]
    assert np.all((masses >= 0.7) & (masses <= 1.3)) and len(np.unique(masses)) == 6
    np.testing.assert_array_equal(everything.values[:, 2:], 1.0)  # nominal lengths
    assert len(dataset.load()) == 3 * 2 * 10
    assert capsys.readouterr().out == (
        f"wrote 2 shards and {out / 'manifest.json'}: 60 transitions, 3 instances, "
        "0 diverged episodes (2 shards generated now)\n"
    )
    # run again on the finished folder: nothing written, and it says so
    generate.main(
        ["--domain", "acrobot", "--seed", "3", "--out", str(out), *TINY, *QUIET]
    )
    assert "nothing to do: already finished, 2 shards" in capsys.readouterr().out
    # every shard done but the manifest killed before it said so: finished now
    manifest["complete"] = False
    (out / "manifest.json").write_text(json.dumps(manifest))
    generate.main(
        ["--domain", "acrobot", "--seed", "3", "--out", str(out), *TINY, *QUIET]
    )
    assert "wrote 2 shards" in capsys.readouterr().out
    assert json.loads((out / "manifest.json").read_text())["complete"]


def random_policy_shard(entry: dict, *, seed: int, split: int = 0) -> Transitions:
    """What `collect` gathers on a TINY acrobot run's shard `entry` (split
    `SPLITS[split]`, default `all`), instance `g` with the stream
    `SeedSequence(seed, spawn_key=(2, split, g))`."""
    streams = [
        np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2, split, g)))
        for g in entry["instances"]
    ]
    return collect.collect(
        "acrobot",
        [AcrobotParams(*row) for row in entry["parameters"]],
        episodes_per_instance=2,
        max_steps=10,
        rng=streams,
        instance_ids=entry["instances"],
    ).transitions


@pytest.mark.parametrize("book", [[], ["--book-inertia"]])
def test_plan_is_the_manifest_as_json_reads_it_back(tmp_path, book):
    """`prepare` compares the plan with a manifest read from disk: the plan must
    hold only what JSON gives back (lists, not tuples; exact floats)."""
    config = generate.parse_config(
        ["--domain", "acrobot", "--instances", "7", "--shard-size", "3",
         "--out", str(tmp_path), *book]
    )  # fmt: skip
    manifest = generate.plan(config)
    assert manifest == json.loads(json.dumps(manifest))
    assert [e["instances"] for e in manifest["shards"]] == [[0, 1, 2], [3, 4, 5], [6]]
    params = [
        AcrobotParams(*row) for e in manifest["shards"] for row in e["parameters"]
    ]
    assert len(set(params)) == 7


def test_shard_is_the_random_policy_on_its_instances_with_their_streams(tmp_path):
    """A shard holds exactly what `collect` gathers on its instances, instance
    `g` with the stream `SeedSequence(seed, spawn_key=(2, split, g))`."""
    out = tmp_path / "data"
    generate.main(
        ["--domain", "acrobot", "--seed", "5", "--out", str(out), *TINY, *QUIET]
    )
    entry = json.loads((out / "manifest.json").read_text())["shards"][1]
    expected = random_policy_shard(entry, seed=5)
    got = Transitions.load(out / "shard-00001.npz")
    for name in ("states", "actions", "next_states", "instances", "rewards", "dones"):
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))


def test_book_inertia_keeps_the_drawn_masses_at_the_books_inertia(tmp_path):
    """`--book-inertia` draws the same masses as without it, derives each link's
    shape so that I = 1 kg m^2, and the shards are simulated on those instances."""
    argv = ["--domain", "acrobot", "--seed", "5", *TINY, *QUIET]
    generate.main([*argv, "--out", str(tmp_path / "shape")])
    generate.main([*argv, "--out", str(tmp_path / "book"), "--book-inertia"])
    shape = shards.load_dataset(tmp_path / "shape")
    book = shards.load_dataset(tmp_path / "book")
    assert book.manifest["config"]["book_inertia"] is True
    assert shape.manifest["config"]["book_inertia"] is False
    np.testing.assert_array_equal(
        book.parameters.values[:, :4], shape.parameters.values[:, :4]
    )
    np.testing.assert_array_equal(shape.parameters.values[:, 4:], 1.0)
    masses, lengths = book.parameters.values[:, :2], book.parameters.values[:, 2:4]
    np.testing.assert_allclose(book.parameters.values[:, 4:] * masses * lengths**2, 1.0)
    for row in book.parameters.values:
        np.testing.assert_allclose(AcrobotParams(*row).inertias, 1.0)
    expected = random_policy_shard(book.manifest["shards"][1], seed=5)
    got = Transitions.load(tmp_path / "book" / "shard-00001.npz")
    np.testing.assert_array_equal(got.next_states, expected.next_states)
    other = Transitions.load(tmp_path / "shape" / "shard-00001.npz")
    np.testing.assert_array_equal(got.states[0], other.states[0])  # same start
    assert not np.array_equal(got.next_states, other.next_states)  # other dynamics


def test_book_inertia_is_part_of_the_run(tmp_path, capsys):
    out = tmp_path / "data"
    argv = ["--domain", "acrobot", "--out", str(out), *TINY, *QUIET]
    generate.main([*argv, "--book-inertia"])
    with pytest.raises(SystemExit):
        generate.main([*argv, "--resume"])
    assert "book_inertia" in capsys.readouterr().err


def test_same_arguments_write_identical_files(tmp_path):
    for name in ("a", "b"):
        generate.main(
            ["--domain", "cartpole", "--out", str(tmp_path / name), *TINY, *QUIET]
        )
    for file in ("manifest.json", "shard-00000.npz", "shard-00001.npz"):
        assert (tmp_path / "a" / file).read_bytes() == (
            tmp_path / "b" / file
        ).read_bytes()
    generate.main(
        ["--domain", "cartpole", "--seed", "1", "--out", str(tmp_path / "c"), *TINY]
        + QUIET
    )
    first = (tmp_path / "a" / "shard-00000.npz").read_bytes()
    assert first != (tmp_path / "c" / "shard-00000.npz").read_bytes()


def test_grid_takes_every_combination(tmp_path):
    argv = ["--domain", "cartpole", "--grid", "2", "--out", str(tmp_path)]
    argv += ["--vary", "pole_mass=0.1:0.3", "--vary", "pole_half_length=0.4:0.6"]
    argv += ["--episodes-per-instance", "1", "--max-steps", "5", "--no-progress"]
    generate.main(argv)
    table = shards.load_dataset(tmp_path).parameters
    assert table.names == ("cart_mass", "pole_mass", "pole_half_length")
    np.testing.assert_allclose(
        table.values,
        [[1, 0.1, 0.4], [1, 0.1, 0.6], [1, 0.3, 0.4], [1, 0.3, 0.6]],
    )


@pytest.mark.parametrize("policy", ["sarsa", "open-loop"])
def test_other_policies_write_chained_episodes(tmp_path, policy):
    argv = ["--domain", "cartpole", "--policy", policy, "--out", str(tmp_path)]
    generate.main(argv + ["--instances", "2", "--episodes-per-instance", "3"] + QUIET)
    data = shards.load_dataset(tmp_path).load()
    # Three episodes per instance, each ending in a done; balance rewards are 0/1.
    assert np.count_nonzero(data.dones) == 6 and data.dones[-1]
    within = ~data.dones[:-1]
    np.testing.assert_array_equal(
        data.states[1:][within], data.next_states[:-1][within]
    )
    assert set(np.unique(data.rewards)) <= {0.0, 1.0}
    np.testing.assert_array_equal(data.instance_ids, [0, 1])


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--domain", "no_such_domain"], "invalid choice"),
        (["--domain", "acrobot", "--instances", "0"], "(--instances): expected >= 1"),
        (
            ["--domain", "acrobot", "--episodes-per-instance", "0"],
            "(--episodes-per-instance): expected >= 1",
        ),
        (["--domain", "acrobot", "--grid", "0"], "--grid must be >= 1"),
        (["--domain", "acrobot", "--max-steps", "0"], "(--max-steps): expected >= 1"),
        (["--domain", "acrobot", "--grid", "2", "--instances", "3"], "exclusive"),
        (
            ["--domain", "acrobot", "--grid", "2", "--distribution", "uniform"],
            "--grid K goes with --distribution grid",
        ),
        (["--domain", "acrobot", "--distribution", "grid"], "needs --grid K"),
        (["--domain", "acrobot", "--vary", "pole_mass=0.1:0.2"], "acrobot parameters"),
        (["--domain", "acrobot", "--vary", "link_mass_1=0.1:1"], "lower bound 0.2"),
        (["--domain", "acrobot", "--vary", "link_mass_1=1"], "NAME=LOW:HIGH"),
        (["--domain", "acrobot", "--vary", "link_mass_1=1.2:0.9"], "LOW must be"),
        (["--domain", "acrobot", "--vary", "link_mass_1=nan:2"], "must be finite"),
        (["--domain", "acrobot", "--vary", "link_mass_1=1:inf"], "must be finite"),
        (
            [
                "--domain",
                "acrobot",
                "--sigma",
                "0",
                "--distribution",
                "relative-normal",
            ],
            "sigma must be a positive",
        ),
        (
            ["--domain", "acrobot", "--split", "train", "--inner-fraction", "1"],
            "inner_fraction must be in (0, 1)",
        ),
        (["--domain", "acrobot", "--policy", "greedy"], "invalid choice"),
        (["--domain", "cartpole", "--book-inertia"], "is for the acrobot"),
        (
            ["--domain", "acrobot", "--book-inertia", "--vary", "link_shape_2=1:1.2"],
            "derives link_shape_2; do not --vary",
        ),
        (
            ["--domain", "acrobot", "--book-inertia", "--vary", "link_length_2=0.5:1"],
            "link 2's mass x length^2 spans [0.25, 1]",
        ),
        (
            ["--domain", "acrobot", "--book-inertia", "--vary", "link_mass_1=0.7:1.5"],
            "spans [0.7, 1.5] kg m^2 over --vary (link_mass_1 [0.7, 1.5], "
            "link_length_1 [1, 1]); keeping I = 1 kg m^2 needs it within [0.667, 1.43]",
        ),
        (["--domain", "acrobot", "--workers", "0"], "(--workers): expected >= 1"),
        (["--domain", "acrobot", "--shard-size", "0"], "(--shard-size): expected >= 1"),
        # options that would do nothing
        (["--domain", "acrobot", "--sigma", "0.3"], "--sigma goes with --distribution"),
        (
            ["--domain", "acrobot", "--inner-fraction", "0.9"],
            "--inner-fraction goes with --split train",
        ),
        (
            [
                "--domain",
                "acrobot",
                "--vary",
                "link_mass_1=1:2",
                "--vary",
                "link_mass_1=0.5:0.6",
            ],
            "link_mass_1 is given twice",
        ),  # fmt: skip
        (
            ["--domain", "acrobot", "--workers", "2", "--scheduler", "tcp://x:1"],
            "--workers and --scheduler are exclusive",
        ),
        (["--domain", "acrobot", "--seed", "-1"], "--seed: expected an integer >= 0"),
        # a memory error (a traceback) while planning, or minutes before any output
        (
            ["--domain", "acrobot", "--instances", "1000000000"],
            "(--instances): expected at most 10,000,000 (as a grid), got 1,000,000,000",
        ),
    ],
)
def test_bad_options_stop_with_a_message_and_write_nothing(
    tmp_path, capsys, argv, message
):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as stopped:
        generate.main([*argv, "--out", str(out)])
    assert stopped.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        # 0 episodes wrote the manifest, then failed; shard_size 0 failed in range()
        ("episodes_per_instance", 0, r"episodes_per_instance \(--episodes-per-ins"),
        ("shard_size", 0, r"shard_size \(--shard-size\): expected >= 1"),
        ("shard_size", 2.0, r"shard_size \(--shard-size\): expected an integer"),
        ("instances", None, r"instances \(--instances\): expected an integer"),
        ("seed", -1, r"seed \(--seed\): expected >= 0"),
        ("policy", "greedy", r"policy \(--policy\): expected one of"),
        ("max_steps", 0, r"max_steps \(--max-steps\): expected >= 1"),
        ("scheduler", 5, r"scheduler \(--scheduler\): expected an address"),
        ("resume", "yes", "resume: expected True or False"),
        # a truthy string is not True: the manifest would record "yes"
        ("book_inertia", "yes", "book_inertia: expected True or False"),
        ("mixed_software", "no", "mixed_software: expected True or False"),
        ("progress", 1, "progress: expected True or False"),
        ("domain", "no_such_domain", "domain must be one of"),
        ("distribution", {"link_mass_1": (1, 2)}, "distribution: expected a tasks"),
    ],
)
def test_config_built_in_python_is_checked_when_built(tmp_path, field, value, match):
    """Building the Config raises (dataclasses.replace runs its checks), so
    generate, which writes the manifest first, is never reached."""
    config = generate.parse_config(["--domain", "acrobot", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(config, **{field: value})


def test_numpy_numbers_in_a_config_built_in_python_plan_as_json(tmp_path):
    """np.int64 counts and a np.float32 σ passed the checks, then the manifest
    failed to serialise (a TypeError naming no field)."""
    config = generate.parse_config(["--domain", "acrobot", "--out", str(tmp_path)])
    distribution = dataclasses.replace(
        config.distribution, kind="relative-normal", sigma=np.float32(0.25),
        inner_fraction=np.float64(0.5),
    )  # fmt: skip
    numpy_config = dataclasses.replace(
        config, instances=np.int64(5), seed=np.uint8(3), shard_size=np.int32(2),
        episodes_per_instance=np.int64(1), max_steps=np.int16(4),
        distribution=distribution,
    )  # fmt: skip
    python_config = dataclasses.replace(
        config, instances=5, seed=3, shard_size=2, episodes_per_instance=1,
        max_steps=4, distribution=dataclasses.replace(
            distribution, sigma=float(np.float32(0.25)), inner_fraction=0.5),
    )  # fmt: skip
    manifest = generate.plan(numpy_config)
    assert json.loads(json.dumps(manifest)) == generate.plan(python_config)


def test_an_out_that_is_a_file_is_refused(tmp_path, capsys):
    out = tmp_path / "file"
    out.write_text("mine")
    for argv, match in (
        (["--out", str(out)], "exists and is not a folder"),
        (["--out", str(out / "sub")], f"--out: {out} is not a folder, so"),
        (["--out", ""], "argument --out: expected a path, got ''"),
    ):
        with pytest.raises(SystemExit) as stopped:
            generate.main(["--domain", "acrobot", *argv])
        assert stopped.value.code == 2
        assert match in capsys.readouterr().err
    assert out.read_text() == "mine" and sorted(tmp_path.iterdir()) == [out]


def test_a_non_empty_out_that_holds_no_run_is_refused_untouched(
    tmp_path, capsys, monkeypatch
):
    """`--out hipmdp` wrote a manifest and shards among the package's source:
    a folder holding anything but a run is refused before any work (the
    instances are not even planned), naming what it holds; an empty folder, or
    one a run killed while writing its first manifest left (a temporary file
    only), is used."""
    argv = ["--domain", "acrobot", *TINY, *QUIET]
    out = tmp_path / "source"
    out.mkdir()
    for name in ("b.py", "a.py", "c.txt", "d.md"):
        (out / name).write_text("mine")

    def plan(config):
        raise AssertionError("planned before --out was checked")

    with monkeypatch.context() as patched, pytest.raises(SystemExit) as stopped:
        patched.setattr(generate, "plan", plan)
        generate.main([*argv, "--out", str(out)])
    assert stopped.value.code == 2
    assert (
        f"{out} is not empty (a.py, b.py, c.txt and 1 more) and holds no run of "
        "tasks.generate (no manifest.json); choose an empty or new folder for --out"
    ) in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["a.py", "b.py", "c.txt", "d.md"]
    empty, killed = tmp_path / "empty", tmp_path / "killed"
    empty.mkdir()
    killed.mkdir()
    (killed / ".manifest.json.k1ll3d.tmp").write_text("{")
    for folder in (empty, killed):
        assert generate.main([*argv, "--out", str(folder)]).content["complete"]
    assert sorted(p.name for p in killed.iterdir()) == sorted(
        p.name for p in empty.iterdir()
    )


def test_help_describes_the_options(capsys):
    with pytest.raises(SystemExit) as stopped:
        generate.main(["--help"])
    assert stopped.value.code == 0
    text = capsys.readouterr().out
    for option in (
        "--domain", "--instances", "--episodes-per-instance", "--grid", "--vary",
        "--seed", "--out", "--workers", "--resume", "--scheduler", "--policy",
        "--distribution", "--split",
    ):  # fmt: skip
        assert option in text
    assert "`" not in text  # the docstring's Markdown code spans as plain text
    assert "Instances (tasks.distributions): the parameters named by --vary" in text


def test_help_states_the_defaults_and_the_parameter_names(capsys):
    """`--help` gives every default that `test_defaults_are_the_documented_ones`
    checks (seed 0, shards of 16, 1 worker), each task's step limit, the
    names `--vary` takes and where the Sarsa agent's settings are (its ε is 0),
    so a run can be described from it alone."""
    with pytest.raises(SystemExit):
        generate.main(["--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    for phrase in (
        "the one seed of every stream (default 0)",
        "instances per shard (default 16)",
        "local worker processes (default 1: in this process)",
        "(default: the task's, 500 for acrobot, 300 for cartpole)",
        "acrobot: link_mass_1, link_mass_2, link_length_1, link_length_2, "
        "link_shape_1, link_shape_2",
        "cartpole: cart_mass, pole_mass, pole_half_length",
        "greedy, ε = 0, with optimistic initial values",  # tasks.agents.DOMAINS
        "its settings per domain in tasks.agents",
    ):
        assert phrase in text, phrase
    from tasks.agents import DOMAINS as AGENTS

    assert {domain.sarsa.epsilon for domain in AGENTS.values()} == {0.0}


@pytest.mark.parametrize("split", ["all", "train", "extrapolation"])
def test_instances_and_episodes_come_from_the_splits_own_streams(tmp_path, split):
    """The instances from `SeedSequence(seed, spawn_key=(0, split))`, instance
    `g`'s episodes from `(2, split, g)`, `split` its index in SPLITS: two
    splits' runs with one seed share no stream."""
    from tasks.distributions import SPLITS, draw

    out = tmp_path / split
    argv = ["--domain", "acrobot", "--seed", "5", "--split", split, "--out", str(out)]
    generate.main([*argv, *TINY, *QUIET])
    k = SPLITS.index(split)
    stream = np.random.default_rng(np.random.SeedSequence(5, spawn_key=(0, k)))
    config = generate.parse_config([*argv, *TINY, *QUIET])
    drawn = draw(config.distribution, 3, rng=stream)
    manifest = json.loads((out / "manifest.json").read_text())
    rows = [row for entry in manifest["shards"] for row in entry["parameters"]]
    assert rows == drawn.values.tolist()
    expected = random_policy_shard(manifest["shards"][1], seed=5, split=k)
    got = Transitions.load(out / "shard-00001.npz")
    for name in ("states", "actions", "next_states", "instances", "rewards", "dones"):
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))


def test_a_range_of_one_value_holds_a_parameter_fixed():
    """`--vary NAME=LOW:HIGH` takes LOW == HIGH (LOW must be <= HIGH)."""
    config = generate.parse_config(
        ["--domain", "acrobot", "--vary", "link_mass_1=1.2:1.2", "--out", "x"]
    )
    assert config.distribution.vary == {"link_mass_1": (1.2, 1.2)}


def test_the_software_digest_covers_hipmdp_tasks_and_the_models(monkeypatch):
    """An edit to a source file of hipmdp or tasks, or to an MJCF model, changes
    `source_sha256`: a resumed run cannot mix shards made by other code."""
    from pathlib import Path

    before = generate.software()["source_sha256"]
    real = Path.read_bytes
    for folder, name in [("hipmdp", "data.py"), ("tasks", "collect.py"),
                         ("mjcf", "acrobot.xml")]:  # fmt: skip

        def edited(self, folder=folder, name=name):
            ours = (self.parent.name, self.name) == (folder, name)
            return real(self) + b"#" if ours else real(self)

        monkeypatch.setattr(Path, "read_bytes", edited)
        assert generate.software()["source_sha256"] != before, folder


def test_defaults_are_the_documented_ones():
    """The defaults the module docstring and `--help` state: 4 instances, 2
    episodes each, seed 0, shards of 16, the random policy, and the paper's
    varied parameters (acrobot link masses in [0.7, 1.3]; cart-pole pole mass
    in [0.05, 0.5] kg and half-length in [0.25, 1.0] m), drawn uniformly."""
    acrobot = generate.parse_config(["--domain", "acrobot"])
    assert acrobot.instances == 4 and acrobot.episodes_per_instance == 2
    assert acrobot.seed == 0 and acrobot.shard_size == 16
    assert acrobot.policy == "random" and acrobot.workers == 1
    assert acrobot.distribution.kind == "uniform"
    assert acrobot.distribution.vary == {
        "link_mass_1": (0.7, 1.3),
        "link_mass_2": (0.7, 1.3),
    }
    cartpole = generate.parse_config(["--domain", "cartpole"])
    assert cartpole.distribution.vary == {
        "pole_mass": (0.05, 0.5),
        "pole_half_length": (0.25, 1.0),
    }


def test_sigma_and_inner_fraction_reach_the_distribution():
    """`--sigma` and `--inner-fraction` are used, not replaced by the defaults
    (0.1 and 0.5; the values here differ from both)."""
    normal = generate.parse_config(
        ["--domain", "acrobot", "--distribution", "relative-normal", "--sigma", "0.3"]
    )
    assert normal.distribution.sigma == 0.3
    train = generate.parse_config(
        ["--domain", "acrobot", "--split", "train", "--inner-fraction", "0.25"]
    )
    assert train.distribution.inner_fraction == 0.25


def test_instances_are_accepted_up_to_the_limit(tmp_path):
    """`instances` may be exactly MAX_GRID_POINTS (the message says "at most");
    one more is refused. Building the Config draws nothing, so this is fast."""
    from tasks.distributions import MAX_GRID_POINTS

    config = generate.parse_config(["--domain", "acrobot", "--out", str(tmp_path)])
    assert dataclasses.replace(config, instances=MAX_GRID_POINTS).instances == (
        MAX_GRID_POINTS
    )
    with pytest.raises(ValueError, match="expected at most"):
        dataclasses.replace(config, instances=MAX_GRID_POINTS + 1)


@pytest.mark.parametrize(
    "address, reason",
    [
        ("8786", "missing port number"),
        ("", "missing port number"),
        ("http://127.0.0.1:8787", "unknown address scheme 'http'"),
        ("tcp://127.0.0.1:99999", "port 99999 is out of range"),
        ("tcp://host:port", "invalid literal"),
    ],
)
def test_a_scheduler_address_that_is_none_is_a_usage_error(
    tmp_path, capsys, address, reason
):
    """A port alone or the dashboard's URL ended in a traceback of Dask's (a
    port out of range, in the connect timeout): a usage error now, before
    anything is written."""
    pytest.importorskip("distributed")
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as stopped:
        generate.main(
            ["--domain", "acrobot", "--scheduler", address, "--out", str(out)]
        )
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert f"--scheduler {address!r}: " in err and reason in err
    assert "expected the scheduler's address, tcp://HOST:PORT" in err
    assert not out.exists()


def test_a_scheduler_without_dask_installed_stops_before_anything(
    tmp_path, capsys, monkeypatch
):
    """Without `distributed`, `--scheduler` is refused while parsing (exit 2), not
    after the manifest is written."""
    real = generate.importlib.util.find_spec
    monkeypatch.setattr(
        generate.importlib.util,
        "find_spec",
        lambda name, *a: None if name == "distributed" else real(name, *a),
    )
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as stopped:
        generate.main(
            ["--domain", "acrobot", "--scheduler", "tcp://x:1", "--out", str(out)]
        )
    assert stopped.value.code == 2
    assert "--scheduler needs Dask" in capsys.readouterr().err
    assert not out.exists()


def test_progress_bar_shows_unless_no_progress(tmp_path, capsys):
    """The bars (on stderr) name the domain's instances planned and its shards;
    `--no-progress` hides them."""
    argv = ["--domain", "acrobot", *TINY, "--shard-size", "2"]
    generate.main([*argv, "--out", str(tmp_path / "quiet"), "--no-progress"])
    assert capsys.readouterr().err == ""
    generate.main([*argv, "--out", str(tmp_path / "shown")])
    err = capsys.readouterr().err
    assert "acrobot shards" in err
    # planning shows too (3,000,000 instances showed nothing for minutes)
    assert "planning acrobot instances:   0%|          | 0/3 " in err


def test_a_relative_normal_far_from_its_box_is_warned_about(tmp_path, capsys):
    """A nominal mass of 1 with σ = 0.05 · 1 lies 20σ below the range [2, 3]
    (far beyond `far_from_nominal`'s 2σ): the run goes on, with a warning."""
    argv = ["--domain", "acrobot", "--distribution", "relative-normal"]
    argv += ["--sigma", "0.05", "--vary", "link_mass_1=2:3", "--out", str(tmp_path)]
    generate.main([*argv, *TINY, *QUIET])
    err = capsys.readouterr().err
    assert "warning: link_mass_1: the nominal 1 lies 20.0σ outside" in err
    assert shards.Dataset(tmp_path).complete


def test_diverged_episodes_are_counted_and_named_in_the_manifest(tmp_path, monkeypatch):
    """An episode that diverges (instance 1's second episode, started at a
    velocity of 1e150) is dropped from its shard and recorded in the manifest:
    the count and the instance, episode and step."""
    from tasks import rollout

    real = rollout.rollout_episodes

    def blown_up(domain, instances, episode_instance, initial_states, actions, **kw):
        initial_states = initial_states.copy()
        if len(instances) == 2:  # the shard of instances 0, 1
            initial_states[3, 2] = 1e150  # episodes are instance-major: 1's second
        return real(domain, instances, episode_instance, initial_states, actions, **kw)

    monkeypatch.setattr(rollout, "rollout_episodes", blown_up)
    generate.main(
        ["--domain", "acrobot", "--policy", "open-loop", "--out", str(tmp_path)]
        + TINY
        + QUIET
    )
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    first, second = manifest["shards"]
    assert first["counts"] == {
        "episodes": 4,
        "transitions": 3 * 10,
        "diverged_episodes": 1,
    }
    assert [d["instance"] for d in first["diverged"]] == [1]
    assert [(d["episode"], d["step"]) for d in first["diverged"]] == [(1, 0)]
    assert second["counts"]["diverged_episodes"] == 0 and not second["diverged"]
    assert len(Transitions.load(tmp_path / "shard-00000.npz")) == 3 * 10


def _resumes_as_an_uninterrupted_run(resume, argv, out, tmp_path, redone):
    """``resume`` (the command a stopped run printed) redoes the shards
    ``redone``, and the run then has the bytes of an uninterrupted run of
    ``argv`` (two shards)."""
    assert generate.main(resume[3:]).redone == redone
    generate.main([*argv, "--out", str(tmp_path / "whole")])
    for name in ("manifest.json", "shard-00000.npz", "shard-00001.npz"):
        assert (out / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()


def test_workers_choose_in_process_or_a_process_pool():
    """`--workers 1` runs in the calling process; more, in a process pool (the
    bytes are the same, tests/test_generate_scale.py: only where they run)."""
    import concurrent.futures as cf

    with generate.executor_for(1, None) as inline:
        assert isinstance(inline, generate.InlineExecutor)
    with generate.executor_for(2, None) as pool:
        assert isinstance(pool, cf.ProcessPoolExecutor)


@pytest.mark.parametrize("stopped_at", [0, 1])
def test_ctrl_c_keeps_the_finished_shards_and_says_how_to_resume(
    tmp_path, capsys, monkeypatch, stopped_at
):
    """Ctrl-C in one of the two shards (a worker's KeyboardInterrupt reaches the
    caller through its future): status 130 and one line on stderr, no traceback,
    naming the other shard as kept and the command that resumes; that command
    finishes the run as an uninterrupted one would have. Both shards are done
    by the time the caller waits, and ``cf.wait`` gives them as a set, in no set
    order: stopping in either one, the finished one is kept whichever comes
    first."""
    argv = ["--domain", "acrobot", "--seed", "3", *TINY, *QUIET]
    run_shard = generate.run_shard

    def interrupted(job):
        if job.index == stopped_at:
            raise KeyboardInterrupt
        return run_shard(job)

    out = tmp_path / "stopped"
    monkeypatch.setattr(generate, "run_shard", interrupted)
    with pytest.raises((SystemExit, KeyboardInterrupt)) as stopped:  # not pytest's
        generate.main([*argv, "--out", str(out)])
    assert stopped.type is SystemExit and stopped.value.code == 130
    resume = ["python", "-m", "tasks.generate", *argv, "--out", str(out), "--resume"]
    assert capsys.readouterr().err == (
        f"python -m tasks.generate: interrupted: 1 of 2 shards finished are kept "
        f"in {out}; resume with the same command plus --resume: {shlex.join(resume)}\n"
    )
    monkeypatch.setattr(generate, "run_shard", run_shard)
    _resumes_as_an_uninterrupted_run(resume, argv, out, tmp_path, (stopped_at,))


@pytest.mark.parametrize("cancelled", [0, 1])
def test_cancelled_shards_keep_the_finished_ones_and_say_how_to_resume(
    tmp_path, capsys, monkeypatch, cancelled
):
    """A Dask client that loses its scheduler cancels every task: the run ended
    with a traceback of `CancelledError` raised while sorting the finished
    futures (`exception()` of a cancelled one raises), before the finished
    shards among them were kept. Now they are kept, and one line says how to
    resume; the resumed run has the bytes of an uninterrupted one."""
    import concurrent.futures as cf
    import contextlib

    argv = ["--domain", "acrobot", "--seed", "3", *TINY, *QUIET]

    class Cancels(generate.InlineExecutor):
        def submit(self, fn, /, *args, **kwargs):
            if args[0].index != cancelled:
                return super().submit(fn, *args, **kwargs)
            future: cf.Future = cf.Future()
            future.cancel()
            future.set_running_or_notify_cancel()  # as a cancelled task's is
            return future

    out = tmp_path / "stopped"
    monkeypatch.setattr(
        generate, "executor_for", lambda *a: contextlib.nullcontext(Cancels())
    )
    with pytest.raises(SystemExit) as stopped:
        generate.main([*argv, "--out", str(out)])
    assert stopped.value.code == 1
    resume = ["python", "-m", "tasks.generate", *argv, "--out", str(out), "--resume"]
    assert capsys.readouterr().err == (
        "python -m tasks.generate: error: shards were cancelled (on a Dask "
        "cluster: the scheduler was lost); stopped: 1 of 2 shards finished are "
        f"kept in {out}; resume with the same command plus --resume: "
        f"{shlex.join(resume)}\n"
    )
    monkeypatch.undo()
    _resumes_as_an_uninterrupted_run(resume, argv, out, tmp_path, (cancelled,))


def test_a_shard_the_pool_finished_as_ctrl_c_came_is_kept(
    tmp_path, capsys, monkeypatch
):
    """Ctrl-C while the caller waits on a pool, which finishes shard 0 in the
    meantime (a future the wait did not return): that shard is written and
    kept, the other cancelled, and the resumed run has the bytes of an
    uninterrupted one."""
    import concurrent.futures as cf
    import contextlib

    argv = ["--domain", "acrobot", "--seed", "3", *TINY, *QUIET]

    class Held(cf.Executor):
        """A pool whose shards run only when the test says."""

        def __init__(self):
            self.jobs = []

        def submit(self, fn, /, *args, **kwargs):
            self.jobs.append((cf.Future(), fn, args))
            return self.jobs[-1][0]

    pool = Held()

    def ctrl_c_while_waiting(futures, timeout=None, return_when=None):
        future, fn, args = pool.jobs[0]
        future.set_result(fn(*args))  # the pool's thread, meanwhile
        raise KeyboardInterrupt

    out = tmp_path / "stopped"
    monkeypatch.setattr(
        generate, "executor_for", lambda *a: contextlib.nullcontext(pool)
    )
    monkeypatch.setattr(generate.cf, "wait", ctrl_c_while_waiting)
    with pytest.raises((SystemExit, KeyboardInterrupt)) as stopped:  # not pytest's
        generate.main([*argv, "--out", str(out)])
    assert stopped.type is SystemExit and stopped.value.code == 130
    assert [job[2][0].index for job in pool.jobs] == [0, 1]
    assert pool.jobs[1][0].cancelled()
    resume = ["python", "-m", "tasks.generate", *argv, "--out", str(out), "--resume"]
    assert capsys.readouterr().err == (
        f"python -m tasks.generate: interrupted: 1 of 2 shards finished are kept "
        f"in {out}; resume with the same command plus --resume: {shlex.join(resume)}\n"
    )
    monkeypatch.undo()
    _resumes_as_an_uninterrupted_run(resume, argv, out, tmp_path, (1,))


def test_a_resumed_run_stopped_again_says_to_run_its_own_command_again(
    tmp_path, capsys, monkeypatch
):
    """A run started with --resume and stopped by Ctrl-C: the command that
    resumes it is its own, with --resume once (not "plus --resume")."""
    out = tmp_path / "stopped"
    argv = ["--domain", "acrobot", "--seed", "3", *TINY, *QUIET, "--out", str(out)]
    argv.append("--resume")  # (an empty folder: --resume starts the run)
    run_shard = generate.run_shard

    def interrupted(job):
        if job.index == 1:
            raise KeyboardInterrupt
        return run_shard(job)

    monkeypatch.setattr(generate, "run_shard", interrupted)
    with pytest.raises((SystemExit, KeyboardInterrupt)) as stopped:  # not pytest's
        generate.main(argv)
    assert stopped.type is SystemExit and stopped.value.code == 130
    assert capsys.readouterr().err == (
        f"python -m tasks.generate: --resume: {out} holds no run yet; starting one\n"
        f"python -m tasks.generate: interrupted: 1 of 2 shards finished are kept "
        f"in {out}; resume with the same command: "
        f"{shlex.join(['python', '-m', 'tasks.generate', *argv])}\n"
    )


def test_resume_says_when_there_is_no_run_to_resume(tmp_path, capsys):
    """--resume into a folder without a run starts one and says so (a mistyped
    --out would otherwise pass unnoticed); resuming a run says nothing of it."""
    out = tmp_path / "typo"
    argv = ["--domain", "cartpole", *TINY, *QUIET, "--out", str(out), "--resume"]
    generate.main(argv)
    err = capsys.readouterr().err
    assert err == f"python -m tasks.generate: --resume: {out} holds no run yet; " + (
        "starting one\n"
    )
    generate.main(argv)
    assert "holds no run" not in capsys.readouterr().err


def test_a_second_stop_while_the_line_is_composed_is_ignored(
    tmp_path, capsys, monkeypatch
):
    """Ctrl-C pressed again, or SIGTERM sent, while the stopped run reads its
    manifest to say what it kept: still status 130 and the whole line, not a
    traceback; the handlers are put back."""
    out = tmp_path / "stopped"
    argv = ["--domain", "acrobot", "--seed", "3", *TINY, *QUIET, "--out", str(out)]
    run_shard, interrupted = generate.run_shard, generate._interrupted

    def ctrl_c_at_shard_1(job):
        if job.index == 1:
            raise KeyboardInterrupt
        return run_shard(job)

    def under_a_second_stop(*args, **kwargs):
        if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:  # would end pytest
            raise AssertionError("SIGTERM at its default while composing")
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handlers, if any, run before this ends
        return interrupted(*args, **kwargs)

    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    monkeypatch.setattr(generate, "run_shard", ctrl_c_at_shard_1)
    monkeypatch.setattr(generate, "_interrupted", under_a_second_stop)
    with pytest.raises((SystemExit, KeyboardInterrupt)) as stopped:  # not pytest's
        generate.main(argv)
    assert stopped.type is SystemExit and stopped.value.code == 130
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
    assert capsys.readouterr().err.startswith(
        f"python -m tasks.generate: interrupted: 1 of 2 shards finished are kept "
        f"in {out}; resume with the same command plus --resume: "
    )


@pytest.mark.parametrize(
    "first, second",
    [(signal.SIGINT, signal.SIGTERM), (signal.SIGTERM, signal.SIGINT)],
    ids=["ctrl-c first", "sigterm first"],
)
def test_two_stop_signals_while_a_shard_is_written_raise_the_first(first, second):
    """Ctrl-C and SIGTERM both come while a finished shard is written: it is
    written whole, then the first one's stop is raised (status 130 for Ctrl-C,
    143 for SIGTERM), not the later one's."""
    expected = {signal.SIGINT: KeyboardInterrupt, signal.SIGTERM: generate.Terminated}
    written = []
    with pytest.raises((KeyboardInterrupt, generate.Terminated)) as stopped:
        with generate._signals_deferred():
            generate._raise_stop(first, None)  # the handler, as a signal calls it
            generate._raise_stop(second, None)
            written.append("shard")
    assert written == ["shard"]
    assert stopped.type is expected[first]


def test_a_stop_as_the_pools_worker_dies_leaves_no_traceback():
    """SIGTERM to a run's process group (a batch system's stop) ends the pool's
    workers and stops the run at once: the run cancelled the shards not started
    as the pool's thread failed them for the dead worker, which raised
    InvalidStateError in that thread (CPython gh-107219, fixed in 3.12): a
    traceback after the stop line, 3 of 4 times by hand. Here in the order that
    raised it: the shards cancelled, then the worker killed. The pool cancels
    its own now."""
    errors = []
    previous, threading.excepthook = threading.excepthook, errors.append
    try:
        with generate.executor_for(2, None) as pool:
            # "running": in a worker or in the pool's call queue (workers + 1
            # places, filled as the pool's thread wakes); the last one waits
            futures = [pool.submit(time.sleep, 60) for _ in range(6)]
            for _ in range(600):  # a guard of a minute, not a timing check
                if sum(f.running() for f in futures) >= 3:
                    break
                time.sleep(0.1)
            assert sum(f.running() for f in futures) >= 3
            assert not futures[-1].running()
            workers = list(pool._processes.values())  # (no public way)
            generate._cancel_waiting(pool, set(futures))
            for process in workers:
                process.kill()
    finally:
        threading.excepthook = previous
    assert errors == []
    assert all(f.cancelled() or f.exception() for f in futures)


def _semaphores_of_a_bar() -> list[str]:
    """In a pool worker: the named semaphores a (hidden) progress bar registers
    with multiprocessing's resource tracker."""
    from multiprocessing import resource_tracker

    from tqdm.auto import tqdm

    registered, real = [], resource_tracker.register  # as synchronize finds it
    resource_tracker.register = lambda name, kind: (
        registered.append(kind),
        real(name, kind),
    )
    try:
        for _ in tqdm(range(2), disable=True):
            pass
    finally:
        resource_tracker.register = real
    return registered


def test_pool_workers_make_no_named_semaphore_for_their_bars():
    """A worker's progress bar (hidden) made tqdm's multiprocessing lock, a
    named semaphore in a forkserver's worker: a worker ended by SIGTERM (to
    the run's process group) left it, and the resource tracker printed "There
    appear to be 1 leaked semaphore objects" after the stop line, 2 times in 4
    by hand."""
    with generate.executor_for(2, None) as pool:
        assert pool.submit(_semaphores_of_a_bar).result() == []


def _shard_fails(job):
    raise ValueError(f"shard {job.index} failed")


class _FailsShard1(cf.ProcessPoolExecutor):
    """A caller's process pool in which shard 1 fails."""

    def submit(self, fn, /, *args, **kwargs):
        if fn is generate.run_shard and args[0].index == 1:
            fn = _shard_fails
        return super().submit(fn, *args, **kwargs)


def test_a_failed_shard_leaves_a_callers_pool_usable(tmp_path):
    """Only a pool the run made is shut down when it stops (the pool cancels
    its own waiting shards): a pool the caller passed, ``executor=``, was left
    shut down by a failed shard, refusing the caller's next job."""
    argv = ["--domain", "acrobot", *TINY, "--shard-size", "1", "--no-progress"]
    config = generate.parse_config([*argv, "--out", str(tmp_path / "run")])
    with _FailsShard1(1) as pool:
        with pytest.raises(ValueError, match="shard 1 failed"):
            generate.generate(config, executor=pool)
        assert pool.submit(int, "7").result() == 7


def test_pool_workers_end_quietly_on_ctrl_c():
    """Ctrl-C reaches every process in the terminal's group: an idle pool worker
    printed a KeyboardInterrupt traceback; its handler now raises SystemExit,
    which a process ends with silently (the caller reports the interruption).
    A caller that ignores Ctrl-C gets workers that ignore it too."""
    with generate.executor_for(2, None) as pool:
        handler = pool.submit(signal.getsignal, signal.SIGINT).result()
    with pytest.raises((SystemExit, KeyboardInterrupt)) as ended:  # not pytest's
        handler(signal.SIGINT, None)
    assert ended.type is SystemExit and ended.value.code == 130
    # started in the background (Ctrl-C ignored): the workers ignore it too
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with generate.executor_for(2, None) as pool:
            handler = pool.submit(signal.getsignal, signal.SIGINT).result()
    finally:
        signal.signal(signal.SIGINT, previous)
    assert handler == signal.SIG_IGN


def test_the_software_digest_does_not_depend_on_the_listing_order(monkeypatch):
    """Two machines list a folder's files in different orders: the digest must
    not change with it, or a run resumed elsewhere is refused as made by other
    software."""
    from pathlib import Path

    before = generate.software()["source_sha256"]
    real_rglob, real_iterdir = Path.rglob, Path.iterdir
    monkeypatch.setattr(
        Path, "rglob", lambda self, p: reversed(list(real_rglob(self, p)))
    )
    monkeypatch.setattr(
        Path, "iterdir", lambda self: reversed(list(real_iterdir(self)))
    )
    assert generate.software()["source_sha256"] == before


def test_the_software_digest_reads_subpackages_too(tmp_path):
    """The digest read the packages' top-level files only: an edit in a
    subpackage (``hipmdp/sub/x.py``) would have left it unchanged, and a resumed
    run would mix shards of two codes. Files are named by their path under the
    package, so a file moved into a subpackage changes it too."""
    for name in ("b.py", "a/z.py", "a/b/c.py", "a/notes.txt", "a/__pycache__/z.pyc"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(name)
    files = generate.source_files(tmp_path)
    assert [path for path, _ in files] == ["a/b/c.py", "a/z.py", "b.py"]
    assert all(file == tmp_path / path for path, file in files)


def test_book_inertia_takes_a_box_that_reaches_the_shape_bounds_exactly(tmp_path):
    """The corners of the box may sit on the range `book_inertia_range` allows
    (inclusive, as the link-shape bounds are): masses 1/1.5 and 1/0.7 kg at
    l = 1 m keep I = 1 kg m^2 with link_shape_1 at its bounds 1.5 and 0.7."""
    from tasks.acrobot import book_inertia_range

    low, high = book_inertia_range()
    config = generate.parse_config(
        ["--domain", "acrobot", "--book-inertia", "--grid", "2",
         "--vary", f"link_mass_1={low!r}:{high!r}", "--out", str(tmp_path)]
    )  # fmt: skip
    rows = [row for e in generate.plan(config)["shards"] for row in e["parameters"]]
    shapes = sorted(AcrobotParams(*row).link_shape_1 for row in rows)
    np.testing.assert_allclose(shapes, [0.7, 1.5], rtol=1e-12)


def other_software(real: dict) -> dict:
    """`real` (a `software()` record) as a worker with an edited source and
    another numpy would report it."""
    packages = real["packages"] | {"numpy": "0.0.1"}
    return {"packages": packages, "source_sha256": "0" * 64}


def test_a_worker_running_other_software_refuses_its_shard(
    tmp_path, capsys, monkeypatch
):
    """Workers compared nothing: one started from a checkout with an edited line
    made other data than the client, under a manifest recording the client's
    software. Each shard now carries the client's `software()`, and a worker
    whose own differs refuses it, naming its host and what differs; the run
    stops with one line, keeping the shard a matching worker made, and the
    resumed run has the bytes of an uninterrupted one. (Here the second shard
    runs on other software.)"""
    import socket

    argv = ["--domain", "acrobot", "--seed", "3", *TINY, *QUIET]
    real = generate.software()
    calls = []

    def changing():  # the first shard matches, the second does not
        calls.append(None)
        return real if len(calls) == 1 else other_software(real)

    monkeypatch.setattr(generate, "local_software", changing)
    out = tmp_path / "stopped"
    with pytest.raises(SystemExit) as stopped:
        generate.main([*argv, "--out", str(out)])
    assert stopped.value.code == 1
    err = capsys.readouterr().err
    resume = ["python", "-m", "tasks.generate", *argv, "--out", str(out), "--resume"]
    numpy = real["packages"]["numpy"]
    assert err == (
        f"python -m tasks.generate: error: the worker process {generate.os.getpid()} "
        f"on host {socket.gethostname()} runs other software than the client "
        f"(numpy {numpy} on the client, 0.0.1 on the worker; the source of hipmdp, "
        f"tasks or the MJCF models (SHA-256 {real['source_sha256'][:12]}... on the "
        f"client, 000000000000... on the worker)); its shards would differ from the "
        "client's: run the workers from the client's code and packages; stopped: 1 "
        f"of 2 shards finished are kept in {out}; resume with the same command plus "
        f"--resume: {shlex.join(resume)}\n"
    )
    monkeypatch.undo()
    _resumes_as_an_uninterrupted_run(resume, argv, out, tmp_path, (1,))


def test_a_dask_worker_running_other_software_stops_the_run_before_any_file(
    tmp_path, capsys, monkeypatch
):
    """The workers connected when the run starts are asked for their software
    (`client.run`): one that runs other software stops the run before anything
    is written, naming its address and what differs."""
    distributed = pytest.importorskip("distributed")
    real = generate.software()
    out = tmp_path / "run"
    with distributed.Client(
        processes=False, n_workers=2, threads_per_worker=1, dashboard_address=None
    ) as client:
        odd = sorted(client.scheduler_info()["workers"])[1]

        def per_worker(dask_worker):  # in-process: one process, two workers
            return other_software(real) if dask_worker.address == odd else real

        monkeypatch.setattr(generate, "_worker_software", per_worker)
        with pytest.raises(SystemExit) as stopped:
            generate.main(
                ["--domain", "acrobot", *TINY, *QUIET, "--out", str(out),
                 "--scheduler", client.scheduler.address]
            )  # fmt: skip
    assert stopped.value.code == 1
    err = capsys.readouterr().err
    assert err.startswith(
        f"python -m tasks.generate: error: the Dask worker {odd} runs other "
        f"software than the client (numpy {real['packages']['numpy']} on the "
        "client, 0.0.1 on the worker; the source of hipmdp"
    )
    assert "stopped before the run began; run again: " in err
    assert err.count("\n") == 1 and not out.exists()


def killed_worker() -> BaseException:
    """What Dask raises for a task whose workers died while running it."""
    from types import SimpleNamespace

    distributed = pytest.importorskip("distributed")
    worker = SimpleNamespace(address="tcp://10.0.0.7:4000")
    return distributed.scheduler.KilledWorker(
        "run_shard-1", worker, 3
    )  # 3 allowed: 4 died


def broken_pool() -> BaseException:
    from concurrent.futures.process import BrokenProcessPool

    return BrokenProcessPool("A process died")


@pytest.mark.parametrize(
    "error, said",
    [
        # a pool's process killed (the out-of-memory killer)
        (broken_pool, "BrokenProcessPool: A process died"),
        (
            killed_worker,
            "KilledWorker: Attempted to run task 'run_shard-1' on 4 different",
        ),
        (lambda: OSError(28, "No space left on device"), "[Errno 28] No space left"),
    ],
)
def test_a_failed_worker_keeps_the_finished_shards_and_says_how_to_resume(
    tmp_path, capsys, monkeypatch, error, said
):
    """A pool process killed, a task whose Dask workers died, a full disk: once
    the run had begun, each ended in a traceback with no word of the shards
    kept or of how to resume. One line says both now (status 1)."""
    argv = ["--domain", "acrobot", "--seed", "3", *TINY, *QUIET]
    failure = error()

    class Fails(generate.InlineExecutor):
        def submit(self, fn, /, *args, **kwargs):
            if args[0].index == 0:
                return super().submit(fn, *args, **kwargs)
            future: generate.cf.Future = generate.cf.Future()
            future.set_exception(failure)
            return future

    out = tmp_path / "stopped"
    monkeypatch.setattr(generate, "executor_for", lambda *a: _context(Fails()))
    with pytest.raises(SystemExit) as stopped:
        generate.main([*argv, "--out", str(out)])
    assert stopped.value.code == 1
    resume = ["python", "-m", "tasks.generate", *argv, "--out", str(out), "--resume"]
    err = capsys.readouterr().err
    assert err.startswith(f"python -m tasks.generate: error: {said}")
    assert err.endswith(
        "; stopped: 1 of 2 shards finished are kept in "
        f"{out}; resume with the same command plus --resume: {shlex.join(resume)}\n"
    )
    assert err.count("\n") == 1


def test_a_bug_once_the_run_began_says_how_to_resume_above_its_traceback(
    tmp_path, capsys, monkeypatch
):
    """Any other error (a bug's) is raised with its traceback, after the line
    naming the shards kept and the command that resumes."""
    argv = ["--domain", "acrobot", "--seed", "3", *TINY, *QUIET]
    run_shard = generate.run_shard

    def buggy(job):
        if job.index == 1:
            raise ZeroDivisionError("a bug")
        return run_shard(job)

    out = tmp_path / "stopped"
    monkeypatch.setattr(generate, "run_shard", buggy)
    with pytest.raises(ZeroDivisionError, match="a bug"):
        generate.main([*argv, "--out", str(out)])
    resume = ["python", "-m", "tasks.generate", *argv, "--out", str(out), "--resume"]
    assert capsys.readouterr().err == (
        "python -m tasks.generate: error: the run stopped on the error below; "
        f"stopped: 1 of 2 shards finished are kept in {out}; resume with the same "
        f"command plus --resume: {shlex.join(resume)}\n"
    )


def _context(executor):
    import contextlib

    return contextlib.nullcontext(executor)


def test_a_dask_cluster_gets_two_shards_in_flight_per_thread(tmp_path, monkeypatch):
    """A Dask run kept 64 shards in flight whatever the cluster's size, so a
    cluster of more than 64 threads idled. It keeps two per thread now (here 2
    workers of 40 threads: 160), counted when the first shard is kept, after
    the first round of submissions."""
    distributed = pytest.importorskip("distributed")
    from distributed.cfexecutor import ClientExecutor

    submitted, at_first_write = [], []
    submit, write = ClientExecutor.submit, shards.write_shard

    def counted_submit(self, fn, *args, **kwargs):
        submitted.append(args[0].index)
        return submit(self, fn, *args, **kwargs)

    def counted_write(*args, **kwargs):
        at_first_write.append(at_first_write[0] if at_first_write else len(submitted))
        return write(*args, **kwargs)

    monkeypatch.setattr(ClientExecutor, "submit", counted_submit)
    monkeypatch.setattr(shards, "write_shard", counted_write)
    with distributed.Client(
        processes=False, n_workers=2, threads_per_worker=40, dashboard_address=None
    ) as client:
        generate.main(
            ["--domain", "cartpole", "--instances", "200", "--shard-size", "1",
             "--episodes-per-instance", "1", "--max-steps", "2", "--no-progress",
             "--out", str(tmp_path), "--scheduler", client.scheduler.address]
        )  # fmt: skip
    assert sorted(submitted) == list(range(200))
    assert at_first_write[0] == 160


def test_a_dask_run_without_workers_warns_once_and_waits(tmp_path, monkeypatch):
    """A cluster with no worker left the run waiting with no word. After
    NO_WORKERS_WARNING seconds without one (here none) it says so on stderr,
    once, and waits on: the worker started on seeing the warning finishes the
    run."""
    import sys
    import threading

    distributed = pytest.importorskip("distributed")
    # (raising=False: code without the warning waits for the guard, then fails)
    monkeypatch.setattr(generate, "NO_WORKERS_WARNING", 0, raising=False)
    written = []
    with distributed.Client(
        processes=False, n_workers=0, dashboard_address=None
    ) as client:
        address = client.scheduler.address

        class Stderr:
            def write(self, text):
                written.append(text)
                if "warning: no Dask worker" in text:
                    client.cluster.scale(1)

            def flush(self):
                pass

        guard = threading.Timer(60, client.cluster.scale, (1,))  # not a timing
        guard.start()  # check: without the warning, the run would never end
        try:
            monkeypatch.setattr(sys, "stderr", Stderr())
            generate.main(
                ["--domain", "acrobot", *TINY, *QUIET, "--out", str(tmp_path),
                 "--scheduler", address]
            )  # fmt: skip
            monkeypatch.undo()
        finally:
            guard.cancel()
    assert "".join(written) == (
        f"python -m tasks.generate: warning: no Dask worker has been connected to "
        f"{address} for 0 s; waiting for one (dask worker {address})\n"
    )
    assert shards.Dataset(tmp_path).complete
