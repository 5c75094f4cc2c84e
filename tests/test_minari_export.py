"""Minari export: read back the way Minari's ArrowStorage reads (pyarrow.dataset over
each episode folder), the episodes are the run's transitions, the ends are labelled
by the task, and each episode carries its instance's parameters."""

from __future__ import annotations

import dataclasses
import errno
import json
import re
import shutil
import sys

import numpy as np
import pytest

from hipmdp import shards
from tasks import acrobot, agents, cartpole, generate, minari_export

pa = pytest.importorskip("pyarrow")
pa_dataset = pytest.importorskip("pyarrow.dataset")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    argv = ["--domain", "cartpole", "--policy", "open-loop", "--instances", "3"]
    argv += ["--episodes-per-instance", "2", "--max-steps", "30", "--shard-size", "2"]
    generate.main([*argv, "--no-progress", "--out", str(out)])
    return out


def episode_table(data, episode):
    """One episode's Arrow table, read as Minari's ``ArrowStorage`` reads it."""
    return pa_dataset.dataset(
        f"{data}/{episode}", format="arrow", ignore_prefixes=["_", ".", "metadata.json"]
    ).to_table()


def read_episode(data, episode):
    """What `minari.dataset._storages.arrow_storage.ArrowStorage.get_episodes`
    does for one episode (without gymnasium's space decoding)."""
    table = episode_table(data, episode)
    return {
        "observations": np.stack(table["observations"].to_numpy(zero_copy_only=False)),
        "actions": np.asarray(table["actions"])[:-1],
        "rewards": np.asarray(table["rewards"])[:-1],
        "terminations": np.asarray(table["terminations"])[:-1],
        "truncations": np.asarray(table["truncations"])[:-1],
    }


def test_episodes_match_the_run_and_carry_their_parameters(run, tmp_path, capsys):
    data = minari_export.main([str(run), "--out", str(tmp_path)])
    assert data == tmp_path / "cartpole-open-loop-v0" / "data"
    assert capsys.readouterr().out == f"wrote {data}\n"
    meta = json.loads((data / "metadata.json").read_text())
    transitions = shards.load_dataset(run).load()
    assert meta["data_format"] == "arrow" and meta["total_episodes"] == 6
    assert meta["total_steps"] == len(transitions)
    assert json.loads(meta["action_space"]) == {
        "type": "Discrete", "dtype": "int64", "start": 0, "n": 2,
    }  # fmt: skip
    assert json.loads(meta["observation_space"])["shape"] == [4]
    ends = np.flatnonzero(transitions.dones) + 1
    table = shards.load_dataset(run).parameters
    failures = cartpole.failed(transitions.next_states[ends - 1])
    assert failures.any() and not failures.all()  # both kinds of ends occur
    for e, (start, stop) in enumerate(zip(np.r_[0, ends[:-1]], ends, strict=True)):
        episode = read_episode(data, e)
        np.testing.assert_array_equal(
            episode["observations"],
            np.r_[
                transitions.states[start:stop], transitions.next_states[stop - 1 :][:1]
            ],
        )
        np.testing.assert_array_equal(
            episode["actions"], transitions.actions[start:stop]
        )
        np.testing.assert_array_equal(
            episode["rewards"], transitions.rewards[start:stop]
        )
        # The end is a failure (terminal) or the 30-step limit (truncation).
        failed = bool(cartpole.failed(transitions.next_states[stop - 1]))
        assert episode["terminations"][-1] == failed
        assert episode["truncations"][-1] == (not failed)
        if not failed:
            assert stop - start == 30
        assert not episode["terminations"][:-1].any()
        assert not episode["truncations"][:-1].any()
        info = json.loads((data / str(e) / "metadata.json").read_text())
        b = int(transitions.instances[start])
        assert info == {
            "id": e,
            "total_steps": int(stop - start),
            "instance": b,
            "parameters": table.row(b),
        }


def test_columns_and_spaces_are_typed_as_minari_writes_them(run, tmp_path):
    """As Minari 0.5's ArrowStorage writes them (``_encode_space``,
    ``update_episodes``): a Box observation as a fixed-size list of its dtype, a
    Discrete action as int32, float rewards, bool end flags, the step columns
    padded with one zero row; the spaces serialised as Minari does (Box: dtype,
    shape, low, high). The Arrow layout needs Minari 0.5 (0.4 had HDF5 only),
    and Minari looks ``minari_version`` up in its set of supported releases
    (``minari_version not in supported_dataset_versions``), so it must be one
    release, 0.5 or later: a range such as ">=0.5.0" is refused by every Minari.
    The run's generating config rides along, so the dataset says how it was
    made."""
    from packaging.version import Version

    data = minari_export.export(run, tmp_path)
    meta = json.loads((data / "metadata.json").read_text())
    assert json.loads(meta["observation_space"]) == {
        "type": "Box", "dtype": "float64", "shape": [4],
        "low": [-np.inf] * 4, "high": [np.inf] * 4,
    }  # fmt: skip
    version = meta["minari_version"]
    assert re.fullmatch(r"\d+\.\d+\.\d+", version), version
    assert Version(version) >= Version("0.5.0")
    assert meta["hipmdp_manifest"] == shards.Dataset(run).manifest["config"]
    # and what a step is: dt as the data's, the action table, the step limit
    dataset = shards.Dataset(run)
    domain = dataset.manifest["config"]["domain"]
    task = meta["hipmdp_task"]
    assert task["dt"] == dataset.load().dt
    module = {"acrobot": acrobot, "cartpole": cartpole}[domain]
    assert task["action_values"] == module.ACTIONS.tolist()
    assert task["angle_dims"] == list(module.ANGLE_DIMS)
    assert task["state"] == list(module.STATE_NAMES)
    assert len(task["state_units"]) == module.STATE_DIM
    limit = dataset.manifest["config"]["max_steps"]
    assert task["max_steps"] == (limit or agents.DOMAINS[domain].max_steps)
    for e in range(meta["total_episodes"]):
        table = episode_table(data, e)
        assert table.schema.field("observations").type == pa.list_(pa.float64(), 4)
        for name, kind in [("actions", pa.int32()), ("rewards", pa.float64()),
                           ("terminations", pa.bool_()),
                           ("truncations", pa.bool_())]:  # fmt: skip
            assert table.schema.field(name).type == kind, name
            assert not table[name][-1].as_py(), name  # the padding row: zero


def test_an_existing_export_is_not_overwritten(run, tmp_path):
    minari_export.export(run, tmp_path, dataset_id="cartpole-mine-v1")
    before = (tmp_path / "cartpole-mine-v1" / "data" / "metadata.json").read_bytes()
    with pytest.raises(ValueError, match="exists"):
        minari_export.export(run, tmp_path, dataset_id="cartpole-mine-v1")
    after = (tmp_path / "cartpole-mine-v1" / "data" / "metadata.json").read_bytes()
    assert after == before


def test_a_damaged_last_shard_is_found_before_anything_is_written(
    run, tmp_path, monkeypatch
):
    """It was found after the shards before it were exported, and the partial
    folder stayed."""
    damaged = tmp_path / "run"
    shutil.copytree(run, damaged)
    last = sorted(damaged.glob("shard-*.npz"))[-1]
    last.write_bytes(last.read_bytes()[:-10])
    out = tmp_path / "out"
    started = []  # the export of the first shards began (in a folder then removed)
    write = minari_export._export
    monkeypatch.setattr(
        minari_export, "_export", lambda *a: started.append(1) or write(*a)
    )
    with pytest.raises(ValueError, match=f"shard {last.name} does not match"):
        minari_export.export(damaged, out)
    assert not out.exists() or list(out.iterdir()) == []
    assert started == []


def test_an_unfinished_run_is_refused(run, tmp_path):
    """A run killed after its last shard, before its manifest said it was
    complete: every shard is there and sound, but the run is not finished."""
    killed = tmp_path / "run"
    shutil.copytree(run, killed)
    manifest = json.loads((killed / shards.MANIFEST).read_text())
    (killed / shards.MANIFEST).write_text(json.dumps({**manifest, "complete": False}))
    killed_run = shards.Dataset(killed)
    killed_run.verify()  # all shards pass their checksums
    assert not killed_run.complete
    out = tmp_path / "out"
    with pytest.raises(ValueError, match="is not a finished run; --resume it first"):
        minari_export.export(killed, out)
    assert not out.exists()


def test_a_missing_pyarrow_is_a_usage_error_and_a_full_disk_is_not(
    run, tmp_path, capsys, monkeypatch
):
    """pyarrow comes with an extra (``.[minari]``): without it the command says
    so as a usage error (status 2) and leaves nothing; an OSError is a failure of
    the work (status 1), not of the command line."""
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "pyarrow", None)  # import pyarrow: ImportError
        with pytest.raises(SystemExit) as stopped:
            minari_export.main([str(run), "--out", str(tmp_path)])
    assert stopped.value.code == 2
    assert "pyarrow" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []

    def full(*args, **kw):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(minari_export, "export", full)
    with pytest.raises(SystemExit) as stopped:
        minari_export.main([str(run), "--out", str(tmp_path)])
    assert stopped.value.code == 1
    assert "error: [Errno 28] No space left on device" in capsys.readouterr().err


def test_an_error_mid_export_leaves_nothing(run, tmp_path, monkeypatch):
    calls = []

    def fail_on_the_third(*args):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("boom")
        return columns(*args)

    columns = minari_export._episode_columns
    monkeypatch.setattr(minari_export, "_episode_columns", fail_on_the_third)
    with pytest.raises(RuntimeError, match="boom"):
        minari_export.export(run, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_a_missing_run_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as stopped:
        minari_export.main([str(tmp_path / "nope"), "--out", str(tmp_path / "x")])
    assert stopped.value.code == 2
    assert "nope" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stopped:
        minari_export.main([str(tmp_path), "--out", ""])
    assert stopped.value.code == 2
    assert "argument --out: expected a path" in capsys.readouterr().err


@pytest.mark.parametrize("dataset_id", ["hipmdp/cartpole-v2", "D4RL/door/human-v2"])
def test_a_namespaced_id_is_stored_as_minari_stores_it(run, tmp_path, dataset_id):
    data = minari_export.export(run, tmp_path, dataset_id=dataset_id)
    assert data == tmp_path.joinpath(*dataset_id.split("/"), "data")
    meta = json.loads((data / "metadata.json").read_text())
    assert meta["dataset_id"] == dataset_id
    assert [p.name for p in data.parent.parent.iterdir()] == [data.parent.name]


@pytest.mark.parametrize(
    "dataset_id",
    # Minari refuses "a.b-v0", "ab-cd" and "x/y-v0" too: a dot, no version, a
    # 1-letter namespace; "ab-v" has no version number, "ab-v0/../.." leaves --out
    [
        "",
        "../out-v0",
        "ab//cd/x-v0",
        "a b-v0",
        "ns/..",
        "a.b-v0",
        "ab-cd",
        "x/y-v0",
        "ab-v",
        "ab-v0/../..",
    ],  # fmt: skip
)
def test_a_bad_dataset_id_is_refused_before_any_file_is_written(
    run, tmp_path, capsys, dataset_id
):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as stopped:
        minari_export.main([str(run), "--out", str(out), "--dataset-id", dataset_id])
    assert stopped.value.code == 2
    assert "--dataset-id: expected Minari's [namespace/]name-vN" in (
        capsys.readouterr().err
    )
    assert list(tmp_path.iterdir()) == []  # not out, nor anything beside it


def test_an_out_that_is_a_file_is_a_usage_error(run, tmp_path, capsys):
    file = tmp_path / "file"
    file.write_text("mine")
    with pytest.raises(SystemExit) as stopped:
        minari_export.main([str(run), "--out", str(file)])
    assert stopped.value.code == 2
    assert "--out: " in capsys.readouterr().err and file.read_text() == "mine"


def test_episode_ends_are_labelled_by_their_own_instances_task():
    """The acrobot's goal is the tip above l₁, so it depends on the instance's
    link lengths: a pose with the tip at l₂ = 1 m reaches it for l₁ = 0.8 m and
    not for l₁ = 1.2 m (nor for the nominal 1 m, which a label from the nominal
    parameters would use)."""
    from hipmdp.data import ParameterTable, Transitions
    from tasks.acrobot import AcrobotParams, goal_reached

    pose = np.array([np.pi / 2, np.pi / 2, 0.0, 0.0])  # link 1 level, link 2 up
    short, long = AcrobotParams(link_length_1=0.8), AcrobotParams(link_length_1=1.2)
    assert not goal_reached(pose[None], AcrobotParams())[0]
    states = np.zeros((4, 4))
    next_states = np.array([np.zeros(4), pose, np.zeros(4), pose])
    transitions = Transitions(
        states, np.zeros(4, int), next_states, np.array([0, 0, 1, 1]),
        angle_dims=(0, 1), dones=np.array([False, True, False, True]),
    )  # fmt: skip
    names = [f.name for f in dataclasses.fields(AcrobotParams)]
    table = ParameterTable(
        [0, 1], names,
        [[getattr(p, n) for n in names] for p in (short, long)],
    )  # fmt: skip
    ends = minari_export.episode_ends(transitions, table, "acrobot", 500)
    assert ends == [(0, 2, True), (2, 4, False)]


def test_episode_ends_take_the_manifests_step_limit_as_it_is(tmp_path):
    """A run made without `--max-steps` records `max_steps: null`; passing it (or
    nothing) to `episode_ends` means the task's limit, as `generate` does."""
    from hipmdp.shards import Dataset
    from tasks import generate

    out = tmp_path / "run"
    generate.main(["--domain", "acrobot", "--out", str(out), "--no-progress"])
    dataset = Dataset(out)
    data, table = dataset.load(), dataset.parameters
    recorded = dataset.manifest["config"]["max_steps"]
    assert recorded is None
    expected = minari_export.episode_ends(data, table, "acrobot", 500)
    assert len(expected) == 8
    assert minari_export.episode_ends(data, table, "acrobot", recorded) == expected
    assert minari_export.episode_ends(data, table, "acrobot") == expected
