"""Shard files and the lazy dataset: shards hold what `Transitions.save` writes, with
reproducible bytes; a run loads by instance reading only the shards it needs."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from hipmdp import Transitions, shards
from hipmdp.data import ParameterTable
from tasks import generate


def small_batch():
    rng = np.random.default_rng(0)
    transitions = Transitions(
        states=rng.normal(size=(5, 4)),
        actions=np.array([0, 1, 1, 0, 1]),
        next_states=rng.normal(size=(5, 4)),
        instances=np.array([3, 3, 3, 8, 8]),
        rewards=rng.normal(size=5),
        dones=np.array([0, 0, 1, 0, 1], dtype=bool),
        angle_dims=(1,),
    )
    table = ParameterTable(np.array([3, 8]), ("a", "b"), rng.uniform(size=(2, 2)))
    return transitions, table


def test_shard_bytes_hold_what_save_writes_and_are_reproducible(tmp_path):
    transitions, table = small_batch()
    data = shards.shard_bytes(transitions, table)
    assert data == shards.shard_bytes(*small_batch())
    (tmp_path / "shard.npz").write_bytes(data)
    transitions.save(tmp_path / "saved.npz", table)
    with (
        np.load(tmp_path / "shard.npz", allow_pickle=False) as ours,
        np.load(tmp_path / "saved.npz", allow_pickle=False) as saved,
    ):
        assert sorted(ours.files) == sorted(saved.files)
        for key in saved.files:
            np.testing.assert_array_equal(ours[key], saved[key])
            assert ours[key].dtype == saved[key].dtype
    loaded = shards.load_dataset(tmp_path / "shard.npz")
    np.testing.assert_array_equal(loaded.next_states, transitions.next_states)
    assert loaded.angle_dims == (1,)
    np.testing.assert_array_equal(
        ParameterTable.load(tmp_path / "shard.npz").values, table.values
    )
    assert shards.write_shard(tmp_path, 4, data) == shards.sha256(data)
    assert (tmp_path / "shard-00004.npz").read_bytes() == data


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    argv = ["--domain", "cartpole", "--policy", "open-loop", "--instances", "5"]
    argv += ["--shard-size", "2", "--no-progress", "--out", str(out)]
    generate.main(argv)
    return out


def test_dataset_loads_by_instance_reading_only_the_needed_shards(run, tmp_path):
    dataset = shards.load_dataset(run / "manifest.json")
    assert isinstance(dataset, shards.Dataset) and dataset.complete
    np.testing.assert_array_equal(dataset.instances, [0, 1, 2, 3, 4])
    everything = dataset.load()
    assert len(everything) == dataset.n_transitions
    np.testing.assert_array_equal(everything.instance_ids, [0, 1, 2, 3, 4])
    part = dataset.load(instances=[1, 4])
    expected = everything.select(instances=[1, 4])
    for name in ("states", "actions", "next_states", "instances", "rewards", "dones"):
        np.testing.assert_array_equal(getattr(part, name), getattr(expected, name))
    # Without shard 1 (instances 2, 3), the others still load and it is named.
    lazy = shards.Dataset(run)
    lazy.directory = tmp_path
    for name in ("manifest.json", "shard-00000.npz", "shard-00002.npz"):
        (tmp_path / name).write_bytes((run / name).read_bytes())
    assert len(lazy.load(instances=[0, 4])) == len(everything.select(instances=[0, 4]))
    with pytest.raises(ValueError, match="shard-00001.npz is missing .* finished"):
        lazy.load(instances=3)
    with pytest.raises(
        ValueError,
        match=r"instances \[9\] are not in the run \(its instances: 0 to 4\)",
    ):
        dataset.load(instances=[0, 9])
    lazy.manifest = {**lazy.manifest, "shards": [
        {**e, "instances": [b * 10 for b in e["instances"]]}
        for e in lazy.manifest["shards"]
    ]}  # fmt: skip
    with pytest.raises(ValueError, match=r"\(its instances: \[0, 10, 20, 30, 40\]\)"):
        lazy.load(instances=[5])
    for bad, match in [([], "one or more ids"), ([True], "an integer array")]:
        with pytest.raises(ValueError, match=f"instances: expected {match}"):
            dataset.load(instances=bad)


def test_parameters_in_the_manifest_match_the_shards(run):
    table = shards.Dataset(run).parameters
    for index, ids in enumerate([[0, 1], [2, 3], [4]]):
        stored = ParameterTable.load(run / shards.shard_name(index))
        np.testing.assert_array_equal(stored.instances, ids)
        np.testing.assert_array_equal(stored.values, table.values[ids])
        assert stored.names == table.names


def test_parameter_table_loads_a_run_as_transitions_do(run):
    """ParameterTable.load takes a run's folder or its manifest.json, as
    Transitions.load does (it was an IsADirectoryError, and "not an .npz
    archive"): a row per instance, the shards' own rows."""
    data = Transitions.load(run)
    for path in (run, run / "manifest.json", str(run)):
        table = ParameterTable.load(path)
        np.testing.assert_array_equal(table.instances, data.instance_ids)
        for index, ids in enumerate([[0, 1], [2, 3], [4]]):
            stored = ParameterTable.load(run / shards.shard_name(index))
            np.testing.assert_array_equal(table.values[ids], stored.values)
            assert table.names == stored.names


def test_temporaries_are_removed_and_foreign_manifests_refused(tmp_path):
    for name in (".shard-00001.npz.x1.tmp", ".manifest.json.y2.tmp", ".other.tmp"):
        (tmp_path / name).write_bytes(b"partial")
    removed = shards.remove_temporaries(tmp_path)
    assert sorted(p.name for p in removed) == [
        ".manifest.json.y2.tmp",
        ".shard-00001.npz.x1.tmp",
    ]
    assert [p.name for p in tmp_path.iterdir()] == [".other.tmp"]
    with pytest.raises(ValueError, match=f"no manifest.json in {tmp_path}$"):
        shards.load_dataset(tmp_path)
    (tmp_path / "batch.npz").write_bytes(b"")  # an experiment's run folder
    with pytest.raises(
        ValueError,
        match="read one of its .npz files with hipmdp.Transitions.load, e.g. .*batch",
    ):
        shards.load_dataset(tmp_path)
    (tmp_path / "batch.npz").unlink()
    (tmp_path / "manifest.json").write_text('{"format": "something else"}')
    with pytest.raises(ValueError, match="not a hipmdp-shards/1 manifest"):
        shards.Dataset(tmp_path)
    # shards missing or not listed by index (a line of the log would finish the
    # wrong shard)
    for listed in ("", ', "shards": [{"index": 1}, {"index": 0}]'):
        (tmp_path / "manifest.json").write_text(
            '{"format": "hipmdp-shards/1"' + listed + "}"
        )
        with pytest.raises(ValueError, match="expected shards listed by index 0, 1"):
            shards.Dataset(tmp_path)
    (tmp_path / "notes.txt").write_text("")
    with pytest.raises(ValueError, match="expected a run folder or its manifest.json"):
        shards.Dataset(tmp_path / "notes.txt")


def unfinished_copy(run, to):
    """Copy the finished run ``run`` to ``to`` with the manifest its start wrote
    (nothing finished, nothing logged); returns the finished run's manifest."""
    whole = shards.read_manifest(run)
    shutil.copytree(run, to)
    blank = json.loads(json.dumps(whole))
    blank["complete"] = False
    for e in blank["shards"]:
        e.update(sha256=None, counts=None, diverged=[])
    shards.write_manifest(to, blank)
    return whole


def test_progress_lines_finish_shards_of_an_unfinished_run(run, tmp_path):
    """An unfinished run's manifest holds no checksums; its progress log does. A
    reader sees the logged shards as finished (and loads them, checked), the
    others as not; a line cut short by a kill, or not a record, is skipped."""
    part = tmp_path / "part"
    whole = unfinished_copy(run, part)
    assert shards.read_progress(part) == {}
    shards.append_progress(part, whole["shards"][2])
    shards.append_progress(part, whole["shards"][0])
    with open(part / shards.PROGRESS, "a") as fh:
        fh.write('["not", "a record"]\n{"index": 1, "sha256": "ab')  # killed
    assert sorted(shards.read_progress(part)) == [0, 2]
    # a line appended after the cut one is whole; the last line for an index
    # wins; an index beyond the run's shards is skipped
    shards.append_progress(part, {**whole["shards"][2], "counts": None})
    assert shards.read_progress(part)[2]["counts"] is None
    shards.append_progress(part, whole["shards"][2])
    for beyond in (99, len(whole["shards"]), -1):  # -1: refused, not the last
        shards.append_progress(part, {**whole["shards"][2], "index": beyond})
    assert -1 not in shards.read_progress(part)  # not applied to the last shard
    assert len(shards.read_manifest(part)["shards"]) == len(whole["shards"])
    dataset = shards.Dataset(part)
    assert not dataset.complete
    assert dataset.n_transitions == sum(
        whole["shards"][i]["counts"]["transitions"] for i in (0, 2)
    )
    expected = shards.Dataset(run).load(instances=[0, 4])
    got = dataset.load(instances=[0, 4])  # shards 0 and 2
    np.testing.assert_array_equal(got.states, expected.states)
    with pytest.raises(ValueError, match="is not finished"):
        dataset.load(instances=[2])  # shard 1: its line was cut short
    shards.remove_progress(part)
    assert shards.read_progress(part) == {}
    shards.remove_progress(part)  # nothing to remove: no error


def test_a_reader_racing_the_final_manifest_reads_it_again(run, tmp_path, monkeypatch):
    """The run completes (final manifest written, log deleted) between a reader's
    reading the start's manifest and its log: the reader reads the manifest
    again, not an unfinished one with nothing logged."""
    part = tmp_path / "part"
    whole = unfinished_copy(run, part)
    for e in whole["shards"]:
        shards.append_progress(part, e)
    read, calls = shards.read_progress, []

    def the_run_completes_meanwhile(directory):
        calls.append(directory)
        if len(calls) == 1:
            shards.write_manifest(part, whole)
            shards.remove_progress(part)
        return read(directory)

    monkeypatch.setattr(shards, "read_progress", the_run_completes_meanwhile)
    assert shards.read_manifest(part) == whole and len(calls) == 2


@pytest.mark.parametrize("how", ["replaced, same mtime", "rewritten in place"])
def test_a_manifest_changed_under_a_reader_is_read_again(
    run, tmp_path, monkeypatch, how
):
    """The reader notices a replaced manifest by its inode even where the clock
    is coarse (same mtime), and one rewritten in place (same inode) by its
    mtime."""
    part = tmp_path / "part"
    whole = unfinished_copy(run, part)
    path = part / shards.MANIFEST
    read, calls = shards.read_progress, []

    def the_manifest_changes_meanwhile(directory):
        calls.append(directory)
        if len(calls) == 1:
            st = path.stat()
            if how == "rewritten in place":
                path.write_text(json.dumps(whole))
                os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
            else:
                shards.write_manifest(part, whole)
                os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
        return read(directory)

    monkeypatch.setattr(shards, "read_progress", the_manifest_changes_meanwhile)
    assert shards.read_manifest(part) == whole and len(calls) == 2


def test_progress_lines_hold_every_field_and_malformed_ones_are_skipped(tmp_path):
    """A line is one record with all of PROGRESS_FIELDS (diverged episodes too),
    one per line; records without every field or with an index that is not a
    non-negative integer are skipped, not fatal."""
    entry = {"index": 0, "file": "shard-00000.npz", "sha256": "ab",
             "counts": {"episodes": 2, "transitions": 9, "diverged_episodes": 1},
             "diverged": [[3, 1]]}  # fmt: skip
    shards.append_progress(tmp_path, entry)
    shards.append_progress(tmp_path, {**entry, "index": 1})
    lines = (tmp_path / shards.PROGRESS).read_bytes().split(b"\n")
    assert lines[2:] == [b""] and all(json.loads(line) for line in lines[:2])
    progress = shards.read_progress(tmp_path)
    assert progress[0] == {k: entry[k] for k in shards.PROGRESS_FIELDS}
    with open(tmp_path / shards.PROGRESS, "a") as fh:
        for record in ({"index": 2, "sha256": "cd"}, {**progress[0], "index": 3.0},
                       {**progress[0], "index": "4"},
                       {**progress[0], "index": True, "sha256": "ef"}):  # fmt: skip
            fh.write(json.dumps(record) + "\n")
    again = shards.read_progress(tmp_path)
    assert sorted(again) == [0, 1] and again[1]["sha256"] == "ab"  # true is no 1


def test_config_differences_name_keys_on_either_side():
    old, new = {"seed": 0, "gone": 1}, {"seed": 1, "added": 2}
    assert shards.config_differences(old, new) == [
        "added: None -> 2",
        "gone: 1 -> None",
        "seed: 0 -> 1",
    ]
    assert shards.config_differences(old, dict(old)) == []
    # a nested mapping (the distribution): its differing keys alone, sorted
    old = {"distribution": {"sigma": 0.1, "kind": "uniform", "grid": None}}
    new = {"distribution": {"kind": "uniform", "grid": 3, "sigma": 0.2}}
    assert shards.config_differences(old, new) == [
        "distribution.grid: None -> 3",
        "distribution.sigma: 0.1 -> 0.2",
    ]


def test_a_shard_is_valid_only_with_its_checksum_and_bytes(run, tmp_path):
    """What a resume keeps: a shard whose file matches the manifest's SHA-256;
    not one without a checksum, without its file, or with a byte changed."""
    entry = shards.read_manifest(run)["shards"][1]
    data = (run / entry["file"]).read_bytes()
    assert entry["sha256"] == shards.sha256(data)
    assert shards.shard_is_valid(run, entry)
    assert not shards.shard_is_valid(run, {**entry, "sha256": None})
    assert not shards.shard_is_valid(tmp_path, entry)  # no file there
    damaged = bytearray(data)
    damaged[len(data) // 2] ^= 1
    (tmp_path / entry["file"]).write_bytes(bytes(damaged))
    assert not shards.shard_is_valid(tmp_path, entry)


def test_verify_checks_every_shard(run, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    shards.Dataset(copy).verify()
    last = copy / shards.shard_name(2)
    last.write_bytes(last.read_bytes()[:-1])
    with pytest.raises(ValueError) as damaged:
        shards.Dataset(copy).verify()
    assert str(damaged.value) == (  # the folder too: which run's shard to redo
        f"{copy}: shard {last.name} does not match its checksum (corrupt or "
        f"truncated); redo it with --resume (the command that made the run, --out "
        f"{copy})"
    )


def _edited(run, tmp_path, edit):
    """A copy of ``run`` whose manifest ``edit(manifest)`` changed."""
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    manifest = json.loads((copy / shards.MANIFEST).read_text())
    edit(manifest)
    (copy / shards.MANIFEST).write_text(json.dumps(manifest))
    return copy


def test_a_manifest_that_disagrees_with_its_shards_is_refused(run, tmp_path):
    """The manifest has no checksum: with two shards' instance lists swapped,
    load(instances=[0]) gave no transitions and no error; with a parameter
    changed, verify() passed. A shard read now checks the manifest's instances
    and parameters (their names too, which label the columns of
    `Dataset.parameters`) against its own table."""

    def swap(m):
        a, b = m["shards"][0], m["shards"][1]
        a["instances"], b["instances"] = b["instances"], a["instances"]

    def nudge(m):
        m["shards"][1]["parameters"][0][1] += 0.1

    def rename(m):
        m["parameter_names"][0] += "_renamed"

    for edit in (swap, nudge, rename):
        copy = _edited(run, tmp_path / edit.__name__, edit)
        with pytest.raises(ValueError, match=r"manifest.json does not match shard"):
            shards.Dataset(copy).verify()
        with pytest.raises(ValueError, match=r"manifest.json does not match shard"):
            shards.Dataset(copy).load(instances=[0, 2])


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda m: m.update(complete="no"), "complete"),
        (lambda m: m.pop("parameter_names"), "parameter_names"),
        (lambda m: m.update(config=[]), "config"),
        (lambda m: m["shards"][1].pop("file"), r"shards\[1\].file"),
        (lambda m: m["shards"][0].update(instances="0, 1"), r"shards\[0\].instances"),
        (
            lambda m: m["shards"][0].update(instances=[0, True]),
            r"shards\[0\].instances",
        ),
        (lambda m: m["shards"][2]["parameters"].pop(), r"shards\[2\].parameters"),
        (
            lambda m: m["shards"][0]["parameters"][0].append(1.0),
            r"shards\[0\].parameters",
        ),
        (lambda m: m["shards"][0].update(sha256=7), r"shards\[0\].sha256"),
        (lambda m: m["shards"][0].update(counts={"n": 3}), r"shards\[0\].counts"),
    ],
)
def test_a_manifest_missing_a_field_names_it(run, tmp_path, edit, field):
    """Each was a KeyError or TypeError in a reader, or ("complete": "no") read
    as complete."""
    copy = _edited(run, tmp_path, edit)
    for read in (shards.Dataset, ParameterTable.load, Transitions.load):
        with pytest.raises(ValueError, match=rf"manifest.json: {field}: expected"):
            read(copy)


def test_transitions_load_reads_a_run_directory_or_its_manifest(run):
    everything = shards.Dataset(run).load()
    np.testing.assert_array_equal(Transitions.load(run).states, everything.states)
    some = Transitions.load(run / shards.MANIFEST, instances=[0, 4])
    expected = everything.select(instances=[0, 4])
    np.testing.assert_array_equal(some.states, expected.states)
    np.testing.assert_array_equal(some.instances, expected.instances)
