"""Transitions and ParameterTable: validation, deltas, selection, files."""

from __future__ import annotations

import dataclasses
import gc
import io
import os
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import stats

from hipmdp import Transitions
from hipmdp.data import (
    ParameterTable,
    check_queries,
    gaussian_loglik,
    is_real_number,
    load_npz,
    wanted_instances,
    wrap_angle,
)
from hipmdp.filter import prior_belief
from hipmdp.gibbs_model import GibbsPriors, check_priors
from hipmdp.sarsa import SarsaConfig, init_state, sarsa_update


def make(n=12, d=4, seed=0, **kw) -> Transitions:
    rng = np.random.default_rng(seed)
    args = dict(
        states=rng.normal(size=(n, d)),
        actions=rng.integers(0, 3, size=n),
        next_states=rng.normal(size=(n, d)),
        instances=rng.integers(0, 4, size=n),
        rewards=-np.ones(n),
        dones=rng.random(n) < 0.2,
        angle_dims=(0, 1),
    )
    args.update(kw)
    return Transitions(**args)


def table_for(t: Transitions) -> ParameterTable:
    ids = t.instance_ids
    return ParameterTable(
        instances=ids, names=("mass", "length"), values=np.c_[ids + 1.0, ids * 0.5 + 1]
    )


@given(st.floats(-1e3, 1e3, allow_nan=False))
@example(np.pi)
@example(-np.pi)
@example(3 * np.pi)
@example(-1e3)
@example(1e3)
def test_wrap_angle_range_and_equivalence(x):
    y = float(wrap_angle(x))
    assert -np.pi < y <= np.pi
    # same angle: differs from x by a whole number of turns
    turns = (x - y) / (2 * np.pi)
    assert abs(turns - round(turns)) < 1e-9


def test_wrap_angle_boundary_maps_to_plus_pi():
    assert wrap_angle(-np.pi) == np.pi
    assert wrap_angle(np.pi) == np.pi


def test_deltas_wrap_only_angle_dims():
    s = np.array([[3.0, 0.0, 3.0]])
    s2 = np.array([[-3.0, 0.0, -3.0]])
    t = Transitions(s, [0], s2, [0], angle_dims=(0,))
    d = t.deltas
    np.testing.assert_allclose(d[0, 0], 2 * np.pi - 6.0)  # wrapped across ±π
    np.testing.assert_allclose(d[0, 2], -6.0)  # not an angle: plain difference


def test_shape_facts():
    t = make()
    assert len(t) == t.n_transitions == 12
    assert t.state_dim == 4
    assert t.n_actions == int(t.actions.max()) + 1
    np.testing.assert_array_equal(t.instance_ids, np.unique(t.instances))


def test_repr_summarises_instead_of_printing_the_arrays():
    """A batch of thousands of transitions printed a screenful of arrays."""
    n = 3000
    rng = np.random.default_rng(0)
    s = rng.normal(size=(n, 2))
    data = Transitions(s, np.arange(n) % 3, s + 0.1, np.arange(n) // 375,
                       rewards=np.zeros(n), angle_dims=(0,), dt=0.05)  # fmt: skip
    assert repr(data) == (
        "Transitions(N=3000, D=2, actions=3, instances=8, rewards, angle_dims=(0,), "
        "dt=0.05)"
    )
    plain = Transitions(s[:4], [0, 1, 1, 0], s[:4], [5, 5, 6, 6])
    assert repr(plain) == "Transitions(N=4, D=2, actions=2, instances=2)"


def test_select_by_instance_and_action():
    t = make(n=200)
    sub = t.select(instances=[1, 2], actions=0)
    assert set(sub.instances) <= {1, 2} and set(sub.actions) == {0}
    expected = np.isin(t.instances, [1, 2]) & (t.actions == 0)
    assert len(sub) == expected.sum()
    np.testing.assert_array_equal(sub.states, t.states[expected])
    np.testing.assert_array_equal(sub.dones, t.dones[expected])


def test_select_takes_sets_and_names_what_is_wrong():
    """A set was a 0-d object array to ``np.isin`` and selected nothing, and so
    did an id not in the data."""
    t = make(n=200)
    for ids, actions in [({1, 2}, {0}), (frozenset({2, 1}), (0,))]:
        expected = t.select(instances=[1, 2], actions=0)
        got = t.select(instances=ids, actions=actions)
        assert len(got) == len(expected) > 0
        np.testing.assert_array_equal(got.states, expected.states)
    with pytest.raises(ValueError, match=r"instances: ids \[7\] are not in the data"):
        t.select(instances=[1, 7])
    with pytest.raises(ValueError, match="actions: expected integers"):
        t.select(actions=[0.5])
    with pytest.raises(ValueError, match="instances: expected an integer array"):
        t.select(instances=["1"])
    assert len(t.select(actions=[5])) == 0  # an action without transitions
    assert len(t.select(instances=[])) == 0


def test_concatenate_keeps_order_and_drops_missing_optional_fields():
    a, b = make(seed=1), make(seed=2, rewards=None)
    c = Transitions.concatenate([a, b])
    np.testing.assert_array_equal(c.states, np.vstack([a.states, b.states]))
    assert c.rewards is None and c.dones is not None
    # the angles and the step travel with the data: the parts' Δs, stacked
    first, second = make(seed=1, dt=0.2), make(seed=2, dt=0.2)
    both = Transitions.concatenate([first, second])
    assert (both.angle_dims, both.dt) == ((0, 1), 0.2)
    np.testing.assert_array_equal(both.deltas, np.vstack([first.deltas, second.deltas]))
    with pytest.raises(ValueError, match="angle_dims"):
        Transitions.concatenate([a, make(angle_dims=(0,))])
    with pytest.raises(ValueError, match="at least one"):
        Transitions.concatenate([])


def test_save_load_round_trip(tmp_path):
    t = make(n=50)
    table = table_for(t)
    path = t.save(tmp_path / "d.npz", table=table)
    u = Transitions.load(path)
    for name in ["states", "actions", "next_states", "instances", "rewards", "dones"]:
        np.testing.assert_array_equal(getattr(u, name), getattr(t, name))
    assert u.angle_dims == t.angle_dims
    v = ParameterTable.load(path)
    np.testing.assert_array_equal(v.values, table.values)
    assert v.names == table.names
    assert (
        v.row(int(t.instance_ids[0]))["mass"]
        == table.row(int(t.instance_ids[0]))["mass"]
    )
    # a file with no table
    t.save(tmp_path / "e.npz")
    assert ParameterTable.load(tmp_path / "e.npz") is None


def test_sha256_is_of_the_data_however_they_were_read_or_typed(tmp_path):
    """The digest a fitted model records of its data: the same for the data read
    back from a file with a parameter table and for integers of another width
    (numpy's default int is 32 bits on Windows with numpy 1.x), another for any
    change of a value, a shape, a field's presence, the angles or the step."""
    t = make(n=50)
    digest = t.sha256()
    u = Transitions.load(t.save(tmp_path / "d.npz", table=table_for(t)))
    assert u.sha256() == digest
    narrow = dataclasses.replace(
        t, actions=t.actions.astype(np.int32), instances=t.instances.astype(np.int32)
    )
    assert narrow.sha256() == digest
    states = t.states.copy()
    states[3, 1] += 1e-12
    changed = [
        dataclasses.replace(t, states=states),
        t.take(np.arange(49)),
        dataclasses.replace(t, rewards=None),
        dataclasses.replace(t, dones=~t.dones),
        dataclasses.replace(t, angle_dims=()),
        dataclasses.replace(t, dt=None if t.dt is not None else 0.1),
    ]
    digests = {c.sha256() for c in changed}
    assert digest not in digests and len(digests) == len(changed)


def test_sha256_is_each_arrays_name_shape_and_little_endian_values():
    """The documented digest, its bytes written out by hand for one transition
    with every optional field: each array of the file (but format_version), in
    its order, as "name:shape;" then its values as little-endian float64, int64
    or one byte per bool (the scalar dt with shape (1,), as np.ascontiguousarray
    gives it and as every recorded digest has it). Empty data of two state
    dimensions differ by the shapes alone."""
    import hashlib
    import struct

    t = Transitions([[0.5, -2.0]], [1], [[0.25, 3.0]], [7], rewards=[-1.0],
                    dones=[True], angle_dims=(0,), dt=0.2)  # fmt: skip
    stream = [
        b"states:(1, 2);", struct.pack("<2d", 0.5, -2.0),
        b"actions:(1,);", struct.pack("<q", 1),
        b"next_states:(1, 2);", struct.pack("<2d", 0.25, 3.0),
        b"instances:(1,);", struct.pack("<q", 7),
        b"angle_dims:(1,);", struct.pack("<q", 0),
        b"rewards:(1,);", struct.pack("<d", -1.0),
        b"dones:(1,);", b"\x01",
        b"dt:(1,);", struct.pack("<d", 0.2),  # 0-d, hashed 1-d as digests were
    ]  # fmt: skip
    assert t.sha256() == hashlib.sha256(b"".join(stream)).hexdigest()
    empty = [Transitions(np.zeros((0, d)), [], np.zeros((0, d)), []) for d in (2, 4)]
    assert empty[0].sha256() != empty[1].sha256()


def test_file_is_plain_npz_without_pickle(tmp_path):
    path = make().save(tmp_path / "d.npz", table=table_for(make()))
    with np.load(path, allow_pickle=False) as f:
        assert all(f[k].dtype != object for k in f.files)


UNPICKLED = []


class _RecordsItsUnpickling:
    """An object whose unpickling appends to UNPICKLED (as a hostile pickle
    would run code of its choosing)."""

    def __reduce__(self):
        return UNPICKLED.append, ("unpickled",)


def test_an_array_that_needs_pickle_is_refused_unread(tmp_path):
    """A member stored as a pickled object array (np.savez pickles by default)
    is refused naming the file and the array, and is never unpickled."""
    path = make().save(tmp_path / "d.npz")
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    hostile = np.empty(1, dtype=object)
    hostile[0] = _RecordsItsUnpickling()
    np.savez(path, **(arrays | {"states": hostile}))
    with pytest.raises(ValueError, match=f"{path}: array 'states' cannot be read"):
        Transitions.load(path)
    assert UNPICKLED == []


@pytest.mark.parametrize(
    "override, match",
    [
        (dict(states=np.zeros((12,))), "states: expected shape"),
        (dict(next_states=np.zeros((11, 4))), "next_states: expected shape"),
        (dict(next_states=np.zeros((12, 3))), "next_states: expected shape"),
        (dict(actions=np.zeros(11, int)), "actions: expected shape"),
        (dict(actions=np.full(12, -1)), "actions: expected indices >= 0"),
        (dict(actions=np.full(12, 0.5)), "actions: expected integers"),
        (dict(instances=np.zeros(13, int)), "instances: expected shape"),
        (dict(states=np.full((12, 4), np.nan)), "states: non-finite"),
        (dict(next_states=np.full((12, 4), np.inf)), "next_states: non-finite"),
        (dict(rewards=np.full(12, np.nan)), "rewards: non-finite"),
        (dict(rewards=np.zeros(3)), "rewards: expected shape"),
        (dict(dones=np.full(12, 2)), "dones: expected booleans"),
        (dict(dones=np.zeros(3, bool)), "dones: expected shape"),
        (dict(angle_dims=(7,)), "angle_dims"),
        (dict(angle_dims=(0, 0)), "angle_dims"),
        (dict(states=np.full((12, 4), "x")), "states: expected a numeric array"),
    ],
)
def test_bad_input_names_the_field(override, match):
    with pytest.raises(ValueError, match=match):
        make(**override)


def test_bad_save_writes_nothing(tmp_path):
    t = make()
    with pytest.raises(ValueError, match="path: expected a .npz"):
        t.save(tmp_path / "d.txt")
    partial = ParameterTable(instances=[0], names=("mass",), values=[[1.0]])
    with pytest.raises(ValueError, match="table: no parameters for instances"):
        t.save(tmp_path / "d.npz", table=partial)
    assert list(tmp_path.iterdir()) == []


def test_failed_write_leaves_old_file_intact(tmp_path):
    from hipmdp.data import atomic_write

    path = make().save(tmp_path / "d.npz")
    before = path.read_bytes()

    def dies_halfway(fh):
        fh.write(b"half a file")
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError, match="killed"):
        atomic_write(path, dies_halfway)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["d.npz"]  # no temp file left


def test_a_write_is_on_disk_before_its_rename_and_the_rename_after(
    tmp_path, monkeypatch
):
    """Whole after a power loss too, not only after a kill: the temporary
    file's data are fsynced before the rename gives them the name (else the
    name could come back on an empty file), and the folder after it (else the
    rename could be lost)."""
    from hipmdp.data import atomic_write

    events = []
    fsync, replace = os.fsync, os.replace

    def recording_fsync(fd):
        events.append(("fsync", os.fstat(fd).st_ino))
        fsync(fd)

    def recording_replace(src, dst):
        events.append(("replace", os.stat(src).st_ino))
        replace(src, dst)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    monkeypatch.setattr(os, "replace", recording_replace)
    path = atomic_write(tmp_path / "f.bin", lambda fh: fh.write(b"data"))
    file, folder = path.stat().st_ino, tmp_path.stat().st_ino
    assert events == [("fsync", file), ("replace", file), ("fsync", folder)]


def test_a_save_removes_what_killed_saves_of_the_same_file_left(tmp_path):
    """A save killed mid-write leaves a full-size hidden temporary file; the next
    save of the same file removes it, but not one a live writer holds (its
    flock), nor another file's, nor a name mkstemp does not make."""
    from hipmdp.data import lock_folder

    stale = [".d.npz.k2x_9abc.tmp", ".d.npz.00000000.tmp"]
    kept = [".d.npz.backup.tmp", ".d.npz.ABCDEFGH.tmp", ".e.npz.abcdefgh.tmp",
            ".d.npz.x.abcdefgh.tmp", "d.npz.abcdefgh.tmp"]  # fmt: skip
    live = tmp_path / ".d.npz.livewrit.tmp"
    for name in stale + kept + [live.name]:
        (tmp_path / name).write_bytes(b"half")
    lock = lock_folder(live)  # another writer, still writing
    try:
        make().save(tmp_path / "d.npz")
    finally:
        os.close(lock)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        kept + [live.name, "d.npz"]
    )
    make().save(tmp_path / "d.npz")  # the writer has gone
    assert not live.exists()


def test_a_writer_holds_a_lock_on_its_temporary_file(tmp_path):
    """What spares a live writer's temporary file from another's cleaning."""
    from hipmdp.data import atomic_temporaries, atomic_write, folder_locked

    seen = []

    def write(fh):
        (tmp,) = atomic_temporaries(tmp_path, "f.bin")
        seen.append(folder_locked(tmp))
        fh.write(b"x")

    atomic_write(tmp_path / "f.bin", write, clean=True)
    assert seen == [True]


def test_atomic_folder_appears_whole_or_not_at_all(tmp_path):
    from hipmdp.data import atomic_folder

    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="killed"):
        with atomic_folder(out) as tmp:
            (tmp / "a.txt").write_text("first file")
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []  # neither out nor the temporary folder

    # a kill (no clean-up) leaves a hidden temporary folder: the next write clears it
    killed = tmp_path / ".run.x1y2_z3w.tmp"
    killed.mkdir()
    (killed / "a.txt").write_text("half a run")
    # a neighbour's temporary folder, perhaps still being written: left alone
    neighbour = tmp_path / ".run.old.ab12cd34.tmp"
    neighbour.mkdir()
    out.mkdir()  # an empty folder is accepted, as absent
    with atomic_folder(out) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".run.")
        assert not out.exists() or list(out.iterdir()) == []
        (tmp / "a.txt").write_text("whole")
    assert sorted(p.name for p in tmp_path.iterdir()) == [neighbour.name, "run"]
    assert [p.name for p in out.iterdir()] == ["a.txt"]
    assert (out / "a.txt").read_text() == "whole"
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o777 & ~umask  # as mkdir would make it


def test_atomic_folder_that_fails_leaves_no_parent_folders_it_made(tmp_path):
    """out = runs/new/deeper/run with runs/ there already: an error removes
    new/ and deeper/ (an empty deeper/ would be the run's only trace), and a
    parent another writer has put a file into meanwhile stays, with its file."""
    from hipmdp.data import atomic_folder

    (tmp_path / "runs").mkdir()
    out = tmp_path / "runs" / "new" / "deeper" / "run"
    with pytest.raises(RuntimeError, match="failed"):
        with atomic_folder(out) as tmp:
            assert tmp.parent == out.parent.resolve()
            raise RuntimeError("failed")
    assert list((tmp_path / "runs").iterdir()) == []

    with pytest.raises(RuntimeError, match="failed"):
        with atomic_folder(out):
            (tmp_path / "runs" / "new" / "other.txt").write_text("someone's")
            raise RuntimeError("failed")
    assert [p.name for p in (tmp_path / "runs" / "new").iterdir()] == ["other.txt"]


def test_atomic_folder_that_cannot_start_leaves_no_parent_folders_it_made(
    tmp_path, monkeypatch
):
    """An error before the block (here the temporary folder cannot be made)
    removes the parents made for it too; a parent another process made while
    they were being made is not this call's to remove."""
    import tempfile

    from hipmdp import data

    def no_space(*args, **kwargs):
        raise OSError(28, "No space left on device")

    out = tmp_path / "runs" / "new" / "run"
    with monkeypatch.context() as m:
        m.setattr(tempfile, "mkdtemp", no_space)
        with pytest.raises(OSError, match="No space"):
            with data.atomic_folder(out):
                pass
    assert list(tmp_path.iterdir()) == []

    real_mkdir = Path.mkdir

    def raced(self, *args, **kwargs):  # another writer makes runs/ first
        if self == (tmp_path / "runs").resolve():
            real_mkdir(self)
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", raced)
    with pytest.raises(RuntimeError, match="failed"):
        with data.atomic_folder(out):
            raise RuntimeError("failed")
    assert [p.name for p in tmp_path.iterdir()] == ["runs"]
    assert list((tmp_path / "runs").iterdir()) == []


def _fail_renames_onto(out, monkeypatch):
    """os.rename raises OSError("rename failed") when its target is ``out``
    (resolved, as atomic_folder resolves it); every other rename goes through."""
    rename = os.rename

    def failing(src, dst):
        if Path(dst) == out.resolve():
            raise OSError("rename failed")
        rename(src, dst)

    monkeypatch.setattr(os, "rename", failing)


@pytest.mark.parametrize("existed", [False, True])
def test_atomic_folder_whose_rename_fails_leaves_out_as_it_was(
    tmp_path, monkeypatch, existed
):
    """The final rename fails: out is as before, absent or an empty folder
    (accepted, as absent) with its mode (it is removed just before the rename,
    which cannot replace a folder on every system), and the rename's error is
    the one raised. Only that rename fails: other renames go through."""
    import stat

    from hipmdp import data

    out = tmp_path / "run"
    if existed:
        out.mkdir()
        out.chmod(0o705)  # no usual umask (022, 002, 027, 077) makes mkdir give it
    _fail_renames_onto(out, monkeypatch)
    with pytest.raises(OSError, match="rename failed"):
        with data.atomic_folder(out) as tmp:
            (tmp / "a.txt").write_text("whole")
    assert [p.name for p in tmp_path.iterdir()] == (["run"] if existed else [])
    if existed:
        assert list(out.iterdir()) == []
        assert stat.S_IMODE(out.stat().st_mode) == 0o705


def test_atomic_folder_raises_the_renames_error_when_out_cannot_be_put_back(
    tmp_path, monkeypatch
):
    """The final rename fails and putting the emptied out back fails too: the
    error raised is the rename's (the cause a user must see), not the mkdir's."""
    from hipmdp import data

    out = tmp_path / "run"
    out.mkdir()
    _fail_renames_onto(out, monkeypatch)
    mkdir = Path.mkdir

    def failing_mkdir(self, *args, **kwargs):
        if self == out.resolve():
            raise OSError("mkdir failed")
        mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", failing_mkdir)
    with pytest.raises(OSError, match="rename failed"):
        with data.atomic_folder(out) as tmp:
            (tmp / "a.txt").write_text("whole")
    assert list(tmp_path.iterdir()) == []  # no temporary folder either


def test_atomic_folder_follows_a_symbolic_link(tmp_path):
    from hipmdp.data import atomic_folder

    for target in (tmp_path / "empty", tmp_path / "absent"):  # a dangling link too
        if target.name == "empty":
            target.mkdir()
        link = tmp_path / f"link_to_{target.name}"
        link.symlink_to(target, target_is_directory=True)
        with atomic_folder(link) as tmp:
            (tmp / "a.txt").write_text(target.name)
        assert link.is_symlink()
        assert (link / "a.txt").read_text() == target.name
        assert (target / "a.txt").read_text() == target.name


def test_atomic_folder_refuses_a_folder_with_files_before_writing(tmp_path):
    from hipmdp.data import atomic_folder

    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "keep.txt").write_text("a user's file")
    (tmp_path / "file").write_text("not a folder")
    for path in (tmp_path / "run", tmp_path / "file"):
        with pytest.raises(ValueError, match="exists and is not an empty folder"):
            with atomic_folder(path):
                raise AssertionError("the block must not run")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "run"]
    assert (tmp_path / "run" / "keep.txt").read_text() == "a user's file"


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(names=("a", "a"), values=[[1.0, 2.0]]), "names: duplicate"),
        (dict(names=("a",), values=[[1.0, 2.0]]), "values: expected shape"),
        (dict(names=("a",), values=[[np.nan]]), "values: non-finite"),
        (dict(names="ab", values=[[1.0, 2.0]]), "names: expected a sequence of names"),
        (dict(names=("a", ""), values=[[1.0, 2.0]]), "names: expected non-empty"),
        (dict(instances=[3, 3], names=("a",), values=[[1.0], [2.0]]),
         "instances: ids must be unique"),
    ],
)  # fmt: skip
def test_parameter_table_bad_input(kw, match):
    with pytest.raises(ValueError, match=match):
        ParameterTable(**({"instances": [0]} | kw))


def test_parameter_table_rows_and_columns():
    table = ParameterTable([7, 2, 5], ("mass", "length"), [[1.0, 10.0], [2.0, 20.0],
                                                           [3.0, 30.0]])  # fmt: skip
    assert table.row(5) == {"mass": 3.0, "length": 30.0}
    np.testing.assert_array_equal(table.column("length"), [10.0, 20.0, 30.0])
    with pytest.raises(KeyError, match="instance 4 is not in the parameter table"):
        table.row(4)
    with pytest.raises(KeyError, match="parameter 'width' is not in"):
        table.column("width")
    with pytest.raises(ValueError, match="table: expected ParameterTable"):
        make().arrays({"instances": [0, 1, 2, 3]})


def test_load_rejects_other_files(tmp_path):
    np.savez(tmp_path / "x.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="format_version"):
        Transitions.load(tmp_path / "x.npz")


@pytest.mark.parametrize(
    "content",
    [b"", b"states,actions\n1,2\n", b"\x80\x04K\x01.", "cut"],
    ids=["empty", "text", "a pickle", "cut short"],
)
def test_files_that_are_not_npz_archives_are_refused_by_name(tmp_path, content):
    """Every loader of a user's file says which file is not an archive, never
    numpy's EOFError or its advice to allow pickle."""
    from hipmdp import load
    from hipmdp.data import ParameterTable

    path = tmp_path / "x.npz"
    if content == "cut":
        make(n=10).save(path)
        content = path.read_bytes()[:-30]  # a killed copy: no central directory
    path.write_bytes(content)
    for loader in (Transitions.load, ParameterTable.load, load):
        with pytest.raises(ValueError, match=f"{path}: not an .npz archive"):
            loader(path)
    with pytest.raises(ValueError, match="BytesIO.*: not an .npz archive"):
        Transitions.load(io.BytesIO(content))
    with pytest.raises(FileNotFoundError):
        Transitions.load(tmp_path / "missing.npz")
    with pytest.raises(IsADirectoryError):
        load(tmp_path)  # (Transitions.load reads a folder as a sharded run)


def member_data(content: bytes, name: str) -> slice:
    """Where the stored bytes of the member ``name`` (``"states.npy"``) are in
    the archive ``content``: after its local header, with its .npy header."""
    import struct
    import zipfile

    with zipfile.ZipFile(io.BytesIO(content)) as z:
        info = z.getinfo(name)
    start = (
        info.header_offset
        + 30
        + sum(
            struct.unpack(
                "<HH", content[info.header_offset + 26 : info.header_offset + 30]
            )
        )
    )
    return slice(start, start + info.compress_size)


def flipped(content: bytes, at: int) -> bytes:
    damaged = bytearray(content)
    damaged[at] ^= 0x10
    return bytes(damaged)


def test_a_changed_byte_is_refused_naming_the_file_and_the_array(tmp_path):
    """One byte changed inside an array gave zipfile's "Bad CRC-32 for file
    'states.npy'" without the file; every loader names the file and the array.
    Over the whole file (every 11th byte, and the end record whose offsets
    numpy seeks to), a changed byte is read or refused by a ValueError naming
    the file, never another error."""
    t = make(n=10)
    path = t.save(tmp_path / "x.npz", table=table_for(t))
    good = path.read_bytes()
    for loader, name in (
        (Transitions.load, "states"),
        (ParameterTable.load, "table_values"),
    ):
        where = member_data(good, f"{name}.npy")
        path.write_bytes(flipped(good, where.stop - 5))  # in the last value
        match = rf"{path}: array '{name}' cannot be read \(BadZipFile: Bad CRC-32"
        with pytest.raises(ValueError, match=match):
            loader(path)
    states = member_data(good, "states.npy")
    with pytest.raises(ValueError, match="BytesIO.*: array 'states' cannot be read"):
        Transitions.load(io.BytesIO(flipped(good, states.stop - 5)))
    # A name in the central directory (zipfile checks the data's CRC, not the
    # directory's names): the member reads as another array. Refused by every
    # loader, naming it; it was a KeyError, and for an optional array (rewards,
    # dones, the table) the data loaded without it.
    for name in ("table_names", "rewards", "dones", "table_instances"):
        at = good.rfind(f"{name}.npy".encode()) + 1
        assert at > len(good) // 2  # found, in the directory at the end
        path.write_bytes(flipped(good, at))
        bad = re.escape(name[0] + chr(ord(name[1]) ^ 0x10) + name[2:])
        for loader in (Transitions.load, ParameterTable.load):
            with pytest.raises(ValueError, match=rf"^{path}: holds arrays .*\({bad}\)"):
                loader(path)
    want = Transitions.load(io.BytesIO(good)), ParameterTable.load(io.BytesIO(good))
    for at in [*range(0, len(good), 11), *range(len(good) - 22, len(good))]:
        path.write_bytes(flipped(good, at))
        for loader, same in zip(
            (Transitions.load, ParameterTable.load), want, strict=True
        ):
            try:
                got = loader(path)
            except ValueError as err:
                assert str(err).startswith(f"{path}: "), (at, err)
            else:  # a byte that holds no data (a date, say): the same data
                assert got is not None, at
                for field in vars(same):
                    a, b = getattr(got, field), getattr(same, field)
                    assert a is b or np.array_equal(a, b), (at, field)


def test_a_file_refused_as_damaged_is_closed(tmp_path):
    """A damaged central directory (its first signature's byte changed) is
    refused by every loader, naming the file, and leaves no file open:
    ``np.load`` of a path kept the file it opened when the archive's directory
    could not be read, until the garbage collector warned of it. So do a file
    that is no archive at all, and a good one once read and closed: the
    descriptors this process holds are the same after each load as before,
    with the error still held (its context held the file numpy opened)."""
    t = make(n=10)
    path = t.save(tmp_path / "x.npz", table=table_for(t))
    good = path.read_bytes()
    cases = {
        "Bad magic number for central directory": flipped(
            good, good.index(b"PK\x01\x02")
        ),
        "not an .npz archive": b"no archive",
        None: good,
    }
    for error, content in cases.items():
        path.write_bytes(content)
        for loader in (Transitions.load, ParameterTable.load, load_npz):
            before = sorted(os.listdir("/proc/self/fd"))
            if error is None:
                held = loader(path)
                if loader is load_npz:
                    held.close()
            else:  # the error held, as by a caller that reports it later
                with pytest.raises(ValueError, match=f"^{re.escape(f'{path}: ')}.*"
                                   f"{error}") as held:  # fmt: skip
                    loader(path)
            assert sorted(os.listdir("/proc/self/fd")) == before, (loader, error)


def test_an_archive_dropped_unclosed_closes_its_file_quietly(tmp_path):
    """``load_npz`` opens the file itself (above); an archive its caller drops
    without closing it closes that file when collected, without the
    ResourceWarning of a file left to the garbage collector (np.load's own
    archive did the same)."""
    path = make(n=4).save(tmp_path / "x.npz")
    before = sorted(os.listdir("/proc/self/fd"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        archive = load_npz(path)
        assert sorted(os.listdir("/proc/self/fd")) != before  # open
        del archive
        gc.collect()
    assert sorted(os.listdir("/proc/self/fd")) == before
    assert [w.category for w in caught] == []


def test_the_loaders_know_every_array_a_dataset_file_can_hold():
    """FILE_ARRAYS, which the loaders check members against, is every array
    the file format writes: with every optional field given (rewards, dones,
    dt, the table), no more, no fewer."""
    from hipmdp.data import FILE_ARRAYS

    t = make(n=6, dt=0.2)
    assert set(t.arrays(table_for(t))) == FILE_ARRAYS


def test_an_archive_in_memory_loads_as_its_file_does(tmp_path):
    t = make(n=10)
    t.save(tmp_path / "x.npz")
    got = Transitions.load(io.BytesIO((tmp_path / "x.npz").read_bytes()))
    np.testing.assert_array_equal(got.states, t.states)


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 30), st.integers(1, 5), st.integers(0, 10_000))
def test_select_partitions_data(n, d, seed):
    t = make(n=n, d=d, seed=seed, angle_dims=())
    parts = [t.select(instances=int(b)) for b in t.instance_ids]
    assert sum(len(p) for p in parts) == len(t)


def test_take_by_mask_and_by_indices():
    t = make(n=20)
    idx = np.array([3, 0, 7])
    u = t.take(idx)
    np.testing.assert_array_equal(u.states, t.states[idx])
    np.testing.assert_array_equal(u.dones, t.dones[idx])
    mask = np.zeros(20, dtype=bool)
    mask[[0, 3, 7]] = True
    np.testing.assert_array_equal(t.take(mask).states, t.states[[0, 3, 7]])
    assert len(t.head(5)) == 5 and len(t.head(50)) == 20 and len(t.head(0)) == 0
    assert len(t.take([])) == 0  # an empty list reads as float64
    np.testing.assert_array_equal(t.take([-20, 19]).states, t.states[[0, 19]])
    for mask in (np.ones(3, dtype=bool), np.zeros(0, dtype=bool)):
        with pytest.raises(ValueError, match="index: expected a mask"):
            t.take(mask)  # an empty boolean mask too, unlike []


@pytest.mark.parametrize(
    "index, message",
    [
        ([20], r"indices in \[-20, 20\), got 20 to 20"),  # was numpy's IndexError
        ([0, -21], r"indices in \[-20, 20\), got -21 to 0"),
        ([1.0, 2.0], "1-d integer indices, got dtype float64"),  # was IndexError
        (
            np.zeros((2, 2), int),
            r"1-d integer indices, got dtype int64, shape \(2, 2\)",
        ),
    ],
)
def test_take_names_a_bad_index(index, message):
    with pytest.raises(ValueError, match=f"^index: expected .*{message}"):
        make(n=20).take(index)


@pytest.mark.parametrize(
    "n, message",
    [(2.5, "an integer >= 0, got 2.5"), (-5, ">= 0, got -5"), (True, ".*got True")],
)
def test_head_names_a_bad_count(n, message):
    """head(2.5) was numpy's IndexError, head(-5) silently nothing."""
    with pytest.raises(ValueError, match=f"^n: expected {message}"):
        make(n=20).head(n)


def test_save_is_byte_reproducible_and_world_readable(tmp_path, monkeypatch):
    import time
    import zipfile

    t = make(n=30)
    a = t.save(tmp_path / "a.npz", table=table_for(t)).read_bytes()
    # a later clock must not change the bytes (np.savez would stamp the time)
    monkeypatch.setattr(
        time, "localtime", lambda *_: time.struct_time((2031,) + (1,) * 8)
    )
    b = t.save(tmp_path / "b.npz", table=table_for(t)).read_bytes()
    assert a == b
    with zipfile.ZipFile(tmp_path / "a.npz") as z:
        assert {i.date_time for i in z.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    umask = os.umask(0o022)
    try:
        mode = t.save(tmp_path / "c.npz").stat().st_mode & 0o777
    finally:
        os.umask(umask)
    assert mode == 0o644


def test_load_selects_instances(tmp_path):
    t = make(n=40)
    path = t.save(tmp_path / "d.npz")
    u = Transitions.load(path, instances=[1, 3])
    np.testing.assert_array_equal(u.states, t.select(instances=[1, 3]).states)
    # none asked for failed in concatenate (a run) or gave nothing (a file); a
    # bool was instance 1
    for bad, match in [
        ([], "one or more ids"),
        ([True], "an integer array"),
        ([1.5], "integers"),
        ("1", "an integer array"),
    ]:
        with pytest.raises(ValueError, match=f"instances: expected {match}"):
            Transitions.load(path, instances=bad)


def test_fast_angle_changes_are_unwrapped_with_the_velocities():
    # a joint spinning at 30 rad/s turns 6 rad in 0.2 s: more than π
    rng = np.random.default_rng(7)
    n, dt = 50, 0.2
    theta0 = rng.uniform(-np.pi, np.pi, n)
    omega = rng.uniform(-30, 30, n)
    alpha = rng.uniform(-5, 5, n)  # constant acceleration: trapezoid is exact
    theta1 = theta0 + omega * dt + 0.5 * alpha * dt**2
    omega1 = omega + alpha * dt
    s = np.c_[wrap_angle(theta0), omega]
    s2 = np.c_[wrap_angle(theta1), omega1]
    with_dt = Transitions(
        s, np.zeros(n, int), s2, np.zeros(n, int), angle_dims=(0,), dt=dt
    )
    np.testing.assert_allclose(with_dt.deltas[:, 0], theta1 - theta0, atol=1e-12)
    plain = Transitions(s, np.zeros(n, int), s2, np.zeros(n, int), angle_dims=(0,))
    np.testing.assert_allclose(plain.deltas[:, 0], wrap_angle(theta1 - theta0))
    assert np.any(np.abs(theta1 - theta0) > np.pi)  # the case the unwrapping is for


def test_each_angle_is_unwrapped_with_its_own_mean_velocity():
    """Two joints, D = 4: joint j's velocity is dimension j + 2 (not j + 1, the
    other joint's angle), and the estimate is the mean of the two velocities:
    with accelerations up to 300 rad/s² the start velocity alone errs by up to
    6 rad, more than π, where the trapezoid is exact."""
    rng = np.random.default_rng(8)
    n, dt = 50, 0.2
    theta0 = rng.uniform(-np.pi, np.pi, (n, 2))
    omega = rng.uniform(-30, 30, (n, 2))
    alpha = rng.uniform(-300, 300, (n, 2))
    theta1 = theta0 + omega * dt + 0.5 * alpha * dt**2
    s = np.c_[wrap_angle(theta0), omega]
    s2 = np.c_[wrap_angle(theta1), omega + alpha * dt]
    t = Transitions(s, np.zeros(n, int), s2, np.zeros(n, int), angle_dims=(0, 1), dt=dt)
    np.testing.assert_allclose(t.deltas[:, :2], theta1 - theta0, atol=1e-12)
    np.testing.assert_array_equal(t.deltas[:, 2:], s2[:, 2:] - s[:, 2:])
    assert np.any(np.abs(0.5 * alpha * dt**2) > np.pi)  # the start velocity fails


def test_the_trapezoid_estimates_error_is_kept_with_its_sign():
    """A changing acceleration (constant jerk j): the trapezoid estimate v̄ dt
    errs, by -j dt³/12 (θ' - θ = ω dt + α dt²/2 + j dt³/6 while v̄ dt = ω dt +
    α dt²/2 + j dt³/4), here by up to 2 rad; Δθ is the estimate plus that
    error, which is the true change while the error is below π."""
    rng = np.random.default_rng(9)
    n, dt = 50, 0.2
    theta0 = rng.uniform(-np.pi, np.pi, n)
    omega = rng.uniform(-30, 30, n)
    alpha = rng.uniform(-5, 5, n)
    jerk = rng.uniform(-3000, 3000, n)  # |j| dt³ / 12 <= 2 rad
    theta1 = theta0 + omega * dt + alpha * dt**2 / 2 + jerk * dt**3 / 6
    omega1 = omega + alpha * dt + jerk * dt**2 / 2
    s, s2 = np.c_[wrap_angle(theta0), omega], np.c_[wrap_angle(theta1), omega1]
    t = Transitions(s, np.zeros(n, int), s2, np.zeros(n, int), angle_dims=(0,), dt=dt)
    np.testing.assert_allclose(t.deltas[:, 0], theta1 - theta0, atol=1e-12)
    error = theta1 - theta0 - 0.5 * (omega + omega1) * dt
    np.testing.assert_allclose(error, -jerk * dt**3 / 12, atol=1e-12)
    assert np.abs(error).max() > 1.0  # the estimate alone is far off


def test_dt_is_kept_by_selection_files_and_checked(tmp_path):
    t = make(n=10, dt=0.05)
    assert t.take([1, 2]).dt == 0.05 and t.select(actions=0).dt == 0.05
    for part in (t.take([1, 2]), t.select(actions=0), t.head(3)):
        assert part.angle_dims == (0, 1)  # so are the angles
    assert Transitions.load(t.save(tmp_path / "d.npz")).dt == 0.05
    with pytest.raises(ValueError, match="dt"):
        Transitions.concatenate([t, make(n=10)])
    for bad in (-1.0, 0.0):
        with pytest.raises(ValueError, match="dt: expected a finite number > 0"):
            make(dt=bad)
    with pytest.raises(ValueError, match=r"dt: needs the \(qpos, qvel\) layout"):
        make(d=3, dt=0.1, angle_dims=(0,))
    with pytest.raises(ValueError, match=r"dt: needs the \(qpos, qvel\) layout"):
        make(d=4, dt=0.1, angle_dims=(2,))  # a velocity as an angle
    # without angles dt is only recorded: any state dimension (3 was refused)
    assert make(d=3, dt=0.1, angle_dims=()).dt == 0.1


def test_negative_indices_are_refused():
    """-1 indexed the last action or state dimension silently."""
    with pytest.raises(ValueError, match=r"actions: expected integers in \[0, 3\)"):
        check_queries(np.zeros((2, 4)), np.array([0, -1]), 4, 3)
    with pytest.raises(ValueError, match=r"angle_dims: expected distinct indices"):
        make(angle_dims=(-1,))


def test_wanted_instances_are_sorted():
    # a set iterates in hash order: {10, 3, 100} as 10, 3, 100
    np.testing.assert_array_equal(wanted_instances({10, 3, 100}), [3, 10, 100])


def test_gaussian_loglik_is_the_normal_log_density():
    rng = np.random.default_rng(0)
    x, mean, var = (
        rng.normal(size=(5, 2)),
        rng.normal(size=(5, 2)),
        rng.uniform(0.1, 2.0, size=(5, 2)),
    )
    want = stats.norm.logpdf(x, mean, np.sqrt(var)).sum()
    assert gaussian_loglik(x, mean, var) == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (dict(angle_dims=(0.7,)), r"angle_dims: expected integer indices"),
        (dict(angle_dims=0), "angle_dims: expected a sequence of indices"),
        (dict(dt="x"), "dt: expected a finite number > 0"),
        (dict(states=[[0.0] * 4, [0.0] * 2]), r"states: expected an array of shape"),
        (
            dict(actions=np.array([2**63, 0], dtype=np.uint64)),
            r"actions: expected values below 2\*\*63",
        ),
        # a float at 2**63 or above was cast to -2**63 without an error
        (dict(instances=[1e19, 0.0]), r"instances: expected integers of magnitude"),
        (dict(instances=[2.0**53 + 2, 0.0]), r"instances: expected integers of magni"),
    ],
)
def test_constructor_names_the_field_of_malformed_input(change, match):
    args = dict(
        states=np.zeros((2, 4)),
        actions=[0, 1],
        next_states=np.zeros((2, 4)),
        instances=[0, 0],
    )
    with pytest.raises(ValueError, match=match):
        Transitions(**(args | change))


def test_concatenate_checks_its_parts_first():
    with pytest.raises(ValueError, match="concatenate: part 0 is int"):
        Transitions.concatenate([1, 2])


def test_load_errors_name_what_is_wrong(tmp_path):
    t = make(n=10)
    path = t.save(tmp_path / "t.npz")
    with pytest.raises(ValueError, match=r"instances \[42\] are not in"):
        Transitions.load(path, instances=[42])
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files if k != "next_states"}
    np.savez(tmp_path / "cut.npz", **arrays)
    with pytest.raises(ValueError, match="missing next_states"):
        Transitions.load(tmp_path / "cut.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="not a hipmdp Transitions file"):
        Transitions.load(tmp_path / "other.npz")


def test_a_table_without_its_values_is_refused_naming_what_is_missing(tmp_path):
    """A file with table_instances but no table_values (hand-edited or
    foreign): a ValueError naming the file and the array, not a KeyError."""
    t = make(n=10)
    path = t.save(tmp_path / "t.npz", table=table_for(t))
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files if k != "table_values"}
    np.savez(path, **arrays)
    match = rf"{path}: an incomplete parameter table \(missing table_values\)"
    with pytest.raises(ValueError, match=match):
        ParameterTable.load(path)


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [  # each was truncated by int() or float() and loaded as if valid
        ("angle_dims", np.array([0.9, 1.7]), "angle_dims: expected integer indices"),
        ("format_version", np.array(1.9), r"format_version 1.9, expected"),
        ("format_version", np.array([1]), r"format_version \[1\], expected"),
        ("dt", np.array([0.2]), r"dt: expected a scalar, got shape \(1,\)"),
        ("dt", np.array("0.2"), "dt: expected a finite number > 0"),
    ],
)
def test_load_checks_the_stored_metadata_as_the_constructor_does(
    tmp_path, key, value, match
):
    path = make(n=10, dt=0.2).save(tmp_path / "t.npz")
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    np.savez(tmp_path / "changed.npz", **(arrays | {key: value}))
    with pytest.raises(ValueError, match=match):
        Transitions.load(tmp_path / "changed.npz")
    with pytest.raises(FileNotFoundError, match="nope.json: no such file"):
        Transitions.load(tmp_path / "nope.json")


def test_real_numbers_are_ints_floats_and_0d_arrays_not_bools():
    """The checks of priors, σ_w and Sarsa rewards refused a 0-d array (np.array(1.0),
    as a loaded file gives it) that they had taken before, while taking True."""
    for ok in (1.0, 2, np.float32(0.5), np.int64(3), np.array(1.0), np.array(4)):
        assert is_real_number(ok), ok
    for bad in (True, np.bool_(True), "1", 1j, None, np.ones(1), np.array(True),
                np.array("1"), [1.0]):  # fmt: skip
        assert not is_real_number(bad), bad
    assert prior_belief(np.zeros(2), np.array(2.0)).P[0, 0] == 0.25
    check_priors(GibbsPriors(np.array(1.0), 1.0, np.float32(1.0), 3))
    state = init_state(2, 3)
    step = sarsa_update(state, np.ones(3), 0, np.array(-1.0), None, None,
                        np.full(3, 0.1), SarsaConfig())  # fmt: skip
    assert step.td_error == -1.0


def test_save_makes_missing_folders_and_stores_plain_members(tmp_path):
    """The archive's members are stored uncompressed, with the fixed date and
    mode 0644 (what makes the bytes reproducible and readable anywhere)."""
    import zipfile

    from hipmdp.data import ZIP_DATE

    path = make().save(tmp_path / "new" / "sub" / "d.npz")
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            assert info.compress_type == zipfile.ZIP_STORED
            assert info.date_time == ZIP_DATE
            assert info.external_attr >> 16 == 0o644


def test_temporaries_are_matched_by_the_whole_file_name(tmp_path):
    """Only ``.<name>.<random>.tmp`` of that very name: not a temporary of
    ``d.npzz``, nor a file named like atomic_folder's temporary folder."""
    from hipmdp.data import atomic_folder, atomic_temporaries

    for name in (".d.npz.ab12.tmp", ".d.npzz.ab12.tmp"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in atomic_temporaries(tmp_path, "d.npz")] == [
        ".d.npz.ab12.tmp"
    ]
    (tmp_path / ".out.abcd1234.tmp").write_bytes(b"not a folder")
    with atomic_folder(tmp_path / "out") as tmp:
        (tmp / "x").write_bytes(b"x")
    assert (tmp_path / ".out.abcd1234.tmp").read_bytes() == b"not a folder"


def _flag_first_member_encrypted(path):
    """Set bit 0 (encrypted) of the first central-directory entry's flags: one
    bit, on which zipfile raises RuntimeError ("password required")."""
    raw = bytearray(path.read_bytes())
    end = raw.rfind(b"PK\x05\x06")
    directory = int.from_bytes(raw[end + 16 : end + 20], "little")
    raw[directory + 8] ^= 1
    path.write_bytes(bytes(raw))


def test_a_member_flagged_encrypted_is_refused_by_name(tmp_path):
    """One flipped bit can mark a member encrypted; zipfile's RuntimeError is
    reported as a damaged file, naming it and the array (``load_npz``, which
    every loader reads through)."""
    path = make(n=10).save(tmp_path / "x.npz")
    _flag_first_member_encrypted(path)
    with pytest.raises(ValueError, match=f"{path}: array .* encrypted"):
        Transitions.load(path)


@pytest.mark.parametrize(
    ("name", "value", "match"),
    [
        ("states", lambda x: np.where(x == x[0, 0], np.nan, x), "states: non-finite"),
        ("actions", lambda x: x[:-1], r"actions: expected shape"),
        ("instances", lambda x: x + 0.5, "instances: expected integers"),
        ("table_values", lambda x: x[:, :1], r"values: expected shape"),
    ],
)
def test_load_names_the_file_of_an_invalid_array(tmp_path, name, value, match):
    """An array that reads but fails the checks (a hand-edited or foreign file)
    is refused naming the file as well as the field."""
    from hipmdp.data import ParameterTable

    data = make(n=10)
    table = ParameterTable(
        data.instance_ids, ("m", "l"), np.ones((len(data.instance_ids), 2))
    )
    path = data.save(tmp_path / "x.npz", table)
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays[name] = value(arrays[name])
    np.savez(path, **arrays)
    loader = ParameterTable.load if name.startswith("table_") else Transitions.load
    with pytest.raises(ValueError, match=f"{path}: {match}"):
        loader(path)


def test_atomic_folder_leaves_a_live_writers_temporary_folder_alone(tmp_path):
    """A second writer of the same path (another export to the same --out)
    removed the first's temporary folder as a killed writer's while the first
    was writing into it; the first then recreated the folders it wrote into
    and renamed an incomplete folder into place. A live writer's is left."""
    from hipmdp.data import atomic_folder

    out = tmp_path / "run"
    with pytest.raises(OSError):  # out is the second's by then: the first fails
        with atomic_folder(out) as first:
            (first / "a.txt").write_text("first")
            with atomic_folder(out) as second:
                left_alone = (first / "a.txt").exists()
                (second / "b.txt").write_text("second")
    assert left_alone
    assert [p.name for p in out.iterdir()] == ["b.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_atomic_folder_takes_a_killed_writers_temporary_removed_meanwhile(
    tmp_path, monkeypatch
):
    """Two writers of one path that both find a killed writer's temporary folder:
    the other removes it between this one's listing and its removal. This one
    goes on (its removal raised FileNotFoundError)."""
    import shutil

    from hipmdp import data

    stale = tmp_path / ".run.abcd1234.tmp"
    stale.mkdir()
    (stale / "a.txt").write_text("killed")
    lock_folder = data.lock_folder

    def other_removes_it_first(path, *, wait=True):
        if path == stale:
            shutil.rmtree(path)
        return lock_folder(path, wait=wait)

    monkeypatch.setattr(data, "lock_folder", other_removes_it_first)
    with data.atomic_folder(tmp_path / "run") as tmp:
        (tmp / "b.txt").write_text("this one")
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["b.txt"]


def test_a_temporary_removed_before_its_writer_locks_it_is_made_again(
    tmp_path, monkeypatch
):
    """Another writer of the same path, cleaning up, took this writer's new
    temporary folder (or file) for a killed writer's in the moment between its
    making and its locking, and removed it: the writer then wrote into a folder
    atomic_write made again, unlocked, or failed at the rename. It makes
    another and locks that."""
    import tempfile

    from hipmdp import data

    made = []
    mkdtemp, mkstemp = tempfile.mkdtemp, tempfile.mkstemp

    def removed_at_once_the_first_time(*args, **kwargs):
        name = mkdtemp(*args, **kwargs)
        made.append(name)
        if len(made) == 1:
            os.rmdir(name)
        return name

    def file_removed_at_once_the_first_time(*args, **kwargs):
        fd, name = mkstemp(*args, **kwargs)
        made.append(name)
        if len(made) == 3:
            os.unlink(name)
        return fd, name

    monkeypatch.setattr(tempfile, "mkdtemp", removed_at_once_the_first_time)
    monkeypatch.setattr(tempfile, "mkstemp", file_removed_at_once_the_first_time)
    with data.atomic_folder(tmp_path / "run") as tmp:
        assert str(tmp) == made[1] and data.folder_locked(tmp)
        data.atomic_write(tmp / "a.txt", lambda fh: fh.write(b"a"))
    assert len(made) == 4  # two folders, two files, the first of each removed
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    assert (tmp_path / "run" / "a.txt").read_bytes() == b"a"


def test_a_temporary_replaced_while_its_writer_waited_for_the_lock_is_made_again(
    tmp_path, monkeypatch
):
    """A cleaner removed the writer's temporary folder while holding its lock,
    and another writer made a folder of the same name meanwhile: the writer,
    locking its own descriptor of the removed folder, checks that the name
    still leads to it, and makes another when it does not."""
    from hipmdp import data

    lock_folder, calls = data.lock_folder, []

    def replaced_the_first_time(path, *, wait=True):
        fd = lock_folder(path, wait=wait)
        calls.append(path)
        if len(calls) == 1:
            path.rmdir()
            path.mkdir()  # another writer's, by chance of the same name
        return fd

    monkeypatch.setattr(data, "lock_folder", replaced_the_first_time)
    with data.atomic_folder(tmp_path / "run") as tmp:
        assert tmp != calls[0]
        (tmp / "b.txt").write_text("this one")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["run", calls[0].name])
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["b.txt"]


def test_a_killed_writers_temporary_is_removed_under_its_lock(tmp_path, monkeypatch):
    """What makes a writer that waited for the lock of its new temporary find it
    gone: a cleaner holds that lock while it removes (a check, then a removal
    without it, let a writer lock in between and lose its folder)."""
    import shutil

    from hipmdp import data

    stale_folder = tmp_path / ".run.abcd1234.tmp"
    stale_folder.mkdir()
    stale_file = tmp_path / ".d.npz.abcd1234.tmp"
    stale_file.write_bytes(b"half")
    held = []
    rmtree, unlink = shutil.rmtree, Path.unlink

    def checked_rmtree(path, *args, **kwargs):
        held.append(data.folder_locked(Path(path)))
        rmtree(path, *args, **kwargs)

    def checked_unlink(path, *args, **kwargs):
        held.append(data.folder_locked(path))
        unlink(path, *args, **kwargs)

    monkeypatch.setattr(shutil, "rmtree", checked_rmtree)
    monkeypatch.setattr(Path, "unlink", checked_unlink)
    with data.atomic_folder(tmp_path / "run") as tmp:
        (tmp / "a.txt").write_text("a")
    make().save(tmp_path / "d.npz")
    assert held == [True, True]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npz", "run"]


def test_a_writer_renames_its_temporary_while_it_holds_the_lock(tmp_path, monkeypatch):
    """Another writer's clean-up coming between the write and the rename: the
    temporary was closed, so unlocked, before its rename, and the clean-up
    removed it (the writer failed with FileNotFoundError). It is renamed
    under the lock now."""
    from hipmdp import data

    chmod, tried = os.chmod, []

    def another_cleans_up(path, mode, **kwargs):
        chmod(path, mode, **kwargs)
        tried.append(data.remove_unless_locked(Path(path)))

    monkeypatch.setattr(os, "chmod", another_cleans_up)
    data.atomic_write(tmp_path / "f.bin", lambda fh: fh.write(b"whole"))
    assert tried == [False]
    assert (tmp_path / "f.bin").read_bytes() == b"whole"
    assert [p.name for p in tmp_path.iterdir()] == ["f.bin"]


@pytest.mark.parametrize("kind", ["file", "folder"])
def test_ctrl_c_while_waiting_for_a_temporary_s_lock_leaves_nothing(
    kind, tmp_path, monkeypatch
):
    """Ctrl-C while a writer waits for the lock of its new temporary (a
    cleaner holds it): the temporary, its descriptor and the parent folders
    the call made are all gone (the file stayed, and the folder and its
    parents)."""
    from hipmdp import data

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    fds = len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else 0
    out = tmp_path / "sub" / "out"
    with pytest.raises(KeyboardInterrupt):
        if kind == "file":
            (tmp_path / "sub").mkdir()
            monkeypatch.setattr(data, "_lock_file", interrupted)
            data.atomic_write(out, lambda fh: fh.write(b"x"))
        else:
            monkeypatch.setattr(data, "lock_folder", interrupted)
            with data.atomic_folder(out):
                pass
    left = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))
    assert left == (["sub"] if kind == "file" else [])
    if fds:
        assert len(os.listdir("/proc/self/fd")) == fds


def test_a_temporary_that_cannot_be_locked_here_is_left(tmp_path, monkeypatch):
    """Where flock exists but fails on a file (NFS emulates it with fcntl
    locks, which need a descriptor open for writing), a live writer's
    temporary cannot be told from a killed one's: it is left, not removed
    under the writer."""
    from hipmdp import data

    stale = tmp_path / ".d.npz.abcd1234.tmp"
    stale.write_bytes(b"a live writer's, perhaps")
    monkeypatch.setattr(data, "lock_folder", lambda path, wait=True: None)
    assert data.remove_unless_locked(stale) is False
    assert stale.exists()
    monkeypatch.setattr(data, "_can_lock", lambda: False)  # not POSIX: nothing locks
    assert data.remove_unless_locked(stale) is True
    assert not stale.exists()
