"""Minari export: read back the way Minari's ArrowStorage reads (pyarrow.dataset over
each episode folder), the episodes are the run's transitions, the ends are labelled
by the task, and each episode carries its instance's parameters."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from hipmdp import shards
from tasks import cartpole, generate, minari_export

pa_dataset = pytest.importorskip("pyarrow.dataset")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    argv = ["--domain", "cartpole", "--policy", "open-loop", "--instances", "3"]
    argv += ["--episodes-per-instance", "2", "--max-steps", "30", "--shard-size", "2"]
    generate.main([*argv, "--no-progress", "--out", str(out)])
    return out


def read_episode(data, episode):
    """What `minari.dataset._storages.arrow_storage.ArrowStorage.get_episodes`
    does for one episode (without gymnasium's space decoding)."""
    table = pa_dataset.dataset(
        f"{data}/{episode}", format="arrow", ignore_prefixes=["_", ".", "metadata.json"]
    ).to_table()
    return {
        "observations": np.stack(table["observations"].to_numpy(zero_copy_only=False)),
        "actions": np.asarray(table["actions"])[:-1],
        "rewards": np.asarray(table["rewards"])[:-1],
        "terminations": np.asarray(table["terminations"])[:-1],
        "truncations": np.asarray(table["truncations"])[:-1],
    }


def test_episodes_match_the_run_and_carry_their_parameters(run, tmp_path):
    data = minari_export.main([str(run), "--out", str(tmp_path)])
    assert data == tmp_path / "cartpole-open-loop-v0" / "data"
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


def test_an_existing_export_is_not_overwritten(run, tmp_path):
    minari_export.export(run, tmp_path, dataset_id="cartpole-mine-v1")
    before = (tmp_path / "cartpole-mine-v1" / "data" / "metadata.json").read_bytes()
    with pytest.raises(ValueError, match="exists"):
        minari_export.export(run, tmp_path, dataset_id="cartpole-mine-v1")
    after = (tmp_path / "cartpole-mine-v1" / "data" / "metadata.json").read_bytes()
    assert after == before


def test_a_damaged_last_shard_is_found_before_anything_is_written(run, tmp_path):
    """It was found after the shards before it were exported, and the partial
    folder stayed."""
    damaged = tmp_path / "run"
    shutil.copytree(run, damaged)
    last = sorted(damaged.glob("shard-*.npz"))[-1]
    last.write_bytes(last.read_bytes()[:-10])
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=f"shard {last.name} does not match"):
        minari_export.export(damaged, out)
    assert not out.exists() or list(out.iterdir()) == []


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
    # Minari refuses the last three too: a dot, no version, a 1-letter namespace
    ["", "../out-v0", "ab//cd/x-v0", "a b-v0", "ns/..", "a.b-v0", "ab-cd", "x/y-v0"],
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
