"""Transitions: batches of (s, a, s', r) from many instances, as plain arrays.

Symbols: ``N`` transitions, ``D`` state dimensions, ``b`` instance id, ``a`` discrete
action index. The state convention is the simulator's physics state ``s`` (for MuJoCo
``(qpos, qvel)``) with angle dimensions wrapped to (-π, π]; the model predicts
``Δs = s' - s``. ``Transitions`` neither wraps nor checks the angles of the
states it is given (``Δs`` comes out the same either way, below): wrap them
with :func:`wrap_angle` if your simulator does not, as the GPs over states see
θ and θ + 2π as far apart unless ``FitConfig(periodic=True)``.

Angle changes: a fast joint turns by more than π in one step (the acrobot's elbow
reaches 30 rad/s, 6 rad per 0.2 s action), so wrapping ``θ' - θ`` to (-π, π] would
make ``Δθ`` jump by 2π across the state space. Given the step ``dt``, the change is
unwrapped around the trapezoid estimate from the velocities,
``Δθ = v̄ dt + wrap(θ' - θ - v̄ dt)`` with ``v̄ = (θ̇ + θ̇')/2``, which is the true
change whenever the estimate errs by less than π. The velocity of angle dimension
``i`` is dimension ``i + D/2`` (the ``(qpos, qvel)`` layout of hinge and slide
joints). Without ``dt`` the change is wrapped to (-π, π].

Files are ``.npz`` archives read with ``allow_pickle=False`` and written atomically
(temporary name in the same folder, then rename), so a crash never leaves a
half-written dataset behind. A per-instance parameter table (e.g. masses and lengths)
can travel in the same file.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import io
import os
import re
import shutil
import stat
import tempfile
import weakref
import zipfile
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

Array = np.ndarray

FORMAT_VERSION = 1
#: Every archive member gets this date (the zip epoch), so files are reproducible.
ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def wrap_angle(x: Array | float) -> Array:
    """Wrap angles to (-π, π]."""
    x = np.asarray(x, dtype=float)
    y = np.mod(x + np.pi, 2.0 * np.pi) - np.pi  # in [-π, π)
    return np.where(y == -np.pi, np.pi, y)


def gaussian_loglik(observed: Array, mean: Array, var: Array) -> float:
    """Σ_i Σ_d log N(observed[i,d]; mean[i,d], var[i,d]): the log-likelihood of
    observed Δs under Gaussian predictions scored one (i, d) at a time."""
    r = observed - mean
    return float(-0.5 * np.sum(r * r / var + np.log(2 * np.pi * var)))


def _umask() -> int:
    """The process's umask: from ``/proc`` where there is one (no change to the
    process state, so safe beside other threads), else set and restored."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    umask = os.umask(0)
    os.umask(umask)
    return umask


def fsync_folder(path: Path) -> None:
    """Make a rename in the folder ``path`` durable (POSIX; a no-op elsewhere)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # e.g. Windows, where folders cannot be opened
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, write, *, clean: bool = False) -> Path:
    """Call ``write(file_object)`` on a temporary file beside ``path``, then rename.

    A crash or kill mid-write leaves at most a stray ``.<name>.<random>.tmp``
    file, never a truncated ``path``. The writer holds an ``flock`` on its
    temporary file. With ``clean``, a write that succeeds then removes the
    temporary files that killed writes of the same ``path`` left, sparing those a
    live writer holds. That lists the folder once per write, so a folder of many
    files written one by one (a generate run's shards) leaves it to
    `hipmdp.shards.remove_temporaries`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, held, tmp = _locked_temporary(
        lambda: tempfile.mkstemp(
            prefix=f".{path.name}.", suffix=".tmp", dir=path.parent
        ),
        lambda fd, _: _lock_file(fd),
    )
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
            os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 -> what open() gives
            if held is not None:  # renamed under the lock: no cleaner takes it
                os.replace(tmp, path)
        if held is None:  # (where nothing locks, e.g. Windows: closed first)
            os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    fsync_folder(path.parent)
    if clean:
        stale = re.compile(rf"\.{re.escape(path.name)}\.[a-z0-9_]{{8}}\.tmp")
        for left in atomic_temporaries(path.parent, glob.escape(path.name)):
            if stale.fullmatch(left.name):
                remove_unless_locked(left)
    return path


def _lock_file(fd: int) -> int | None:
    """An ``flock`` on the open file ``fd``, held until it is closed (waiting
    while a cleaner holds it: :func:`remove_unless_locked`); ``fd``, or None
    where files cannot be locked."""
    try:
        import fcntl

        fcntl.flock(fd, fcntl.LOCK_EX)
    except (ImportError, OSError):
        return None
    return fd


def _locked_temporary(make, lock) -> tuple[int | None, int | None, str]:
    """``make()``'s new temporary ``(fd, name)`` (``fd`` None for a folder) and
    ``lock(fd, name)``'s descriptor holding its lock (None where nothing can be
    locked), checked to be still there once locked: a writer of the same path
    cleaning up may take it for a killed writer's between its making and its
    locking, and remove it. :func:`remove_unless_locked` holds the lock while it
    removes, so once this one holds it the temporary stays. One removed is made
    again. Returns ``(fd, lock descriptor, name)``."""
    for _ in range(100):
        fd, name = make()
        held = None
        try:
            held = lock(fd, name)
            if held is None and os.path.exists(name):
                return fd, None, name  # nothing can be locked here
            if held is not None and os.path.samestat(os.fstat(held), os.stat(name)):
                return fd, held, name
        except FileNotFoundError:
            pass  # os.stat: a cleaner removed it while this waited for the lock
        except BaseException:  # e.g. Ctrl-C while waiting for a cleaner's lock
            for each in {fd, held} - {None}:
                os.close(each)
            with contextlib.suppress(OSError):  # ours: no one else's to keep
                if fd is None:
                    os.rmdir(name)
                else:
                    os.unlink(name)
            raise
        for each in {fd, held} - {None}:
            os.close(each)  # removed by another writer cleaning up: make another
    raise OSError(f"{name}: removed by another writer each time it was made")


def _can_lock() -> bool:
    """Whether this system has ``flock`` (POSIX): where it has not, nothing is
    locked and a killed writer's temporary cannot be told from a live one's."""
    try:
        import fcntl  # noqa: F401
    except ImportError:
        return False
    return True


def remove_unless_locked(path: Path) -> bool:
    """Remove the file or folder ``path``, a killed writer's temporary, unless a
    live writer holds its lock (:func:`lock_folder`), or it cannot be locked
    here to tell (a file system without working ``flock``, such as NFS: left
    alone); whether it was removed. Where nothing locks (not POSIX), it is
    removed.

    The lock is held while removing, so a writer that has just made ``path``
    and is waiting for the lock finds it gone and makes another
    (:func:`_locked_temporary`). One that another cleaner removes first counts
    as removed."""
    try:
        fd = lock_folder(path, wait=False)
    except BlockingIOError:
        return False
    if fd is None and _can_lock() and os.path.lexists(path):
        # there but not lockable here (e.g. NFS, where flock is emulated and
        # needs a descriptor open for writing): a live writer's, perhaps. A
        # stray temporary is harmless; a live writer's removed is not
        return False
    try:
        with contextlib.suppress(FileNotFoundError):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()
    finally:
        if fd is not None:
            os.close(fd)
    return True


def atomic_temporaries(directory: str | os.PathLike, pattern: str) -> list[Path]:
    """The temporary files that writes of files matching the glob ``pattern`` in
    ``directory`` left when killed (:func:`atomic_write` names them
    ``.<name>.<random>.tmp``), sorted."""
    return sorted(Path(directory).glob(f".{pattern}.*.tmp"))


def check_empty_folder(path: str | os.PathLike, name: str = "path") -> Path:
    """``path`` if it is absent or an empty folder; else a ``ValueError`` naming
    ``name``."""
    path = Path(path)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise ValueError(f"{name}: {path} exists and is not an empty folder")
    return path


def lock_folder(path: Path, *, wait: bool = True) -> int | None:
    """An open descriptor of the folder ``path`` holding an exclusive
    ``flock`` on it, released when it is closed or the process dies (a SIGKILL
    included); None where folders cannot be opened or locked (not POSIX).

    Raises:
        BlockingIOError: if ``wait`` is False and another open of the folder
            (another process's, or another of this one's) holds the lock.
    """
    try:
        import fcntl
    except ImportError:
        return None
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except OSError as err:
        os.close(fd)
        if isinstance(err, BlockingIOError):
            raise
        return None
    except BaseException:  # e.g. Ctrl-C while waiting
        os.close(fd)
        raise
    return fd


def folder_locked(path: Path) -> bool:
    """Whether a live process (or another open of this one) holds
    :func:`lock_folder`'s lock on ``path`` (or, for a file, the lock
    :func:`atomic_write` holds on its temporary file)."""
    try:
        fd = lock_folder(path, wait=False)
    except BlockingIOError:
        return True
    if fd is not None:
        os.close(fd)
    return False


def _folder_temporaries(path: Path) -> list[Path]:
    """The temporary folders :func:`atomic_folder` made for ``path`` (exactly
    ``tempfile.mkdtemp``'s names: 8 random characters, never a dot, so those of
    a neighbour such as ``path.old`` do not match)."""
    name = re.compile(rf"\.{re.escape(path.name)}\.[a-z0-9_]{{8}}\.tmp")
    return sorted(
        p for p in path.parent.iterdir() if name.fullmatch(p.name) and p.is_dir()
    )


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike):
    """Write a folder's files into a temporary folder beside ``path``, then rename it.

        with atomic_folder(out) as tmp:
            atomic_write(tmp / "model.npz", ...)

    ``path`` appears, whole, only when the block ends without an error; an error
    removes the temporary folder, and the parent folders this call made for it
    while they are empty, and leaves ``path`` as it was. A kill leaves at most a
    hidden ``.<name>.<random>.tmp`` folder beside it, which the next
    ``atomic_folder`` on the same ``path`` removes. A live writer holds an
    ``flock`` on its temporary folder, which is left alone: of two writers of one
    ``path`` at once, the second to finish fails at the rename (``path`` exists),
    and neither leaves a part-written ``path``. A symbolic link is followed: the
    folder is made where it points.

    Raises:
        ValueError: before anything is written, if ``path`` exists and is not an
            empty folder.
    """
    path = check_empty_folder(Path(path).resolve())
    made = _make_parents(path)
    try:
        for stale in _folder_temporaries(path):  # a killed writer's
            # a live writer (another process on the same path) holds a lock on
            # its own: removing it under that writer made it recreate the
            # folders it wrote into and rename an incomplete folder into place
            remove_unless_locked(stale)
        _, lock, tmp = _locked_temporary(
            lambda: (
                None,
                tempfile.mkdtemp(
                    prefix=f".{path.name}.", suffix=".tmp", dir=path.parent
                ),
            ),
            lambda _, name: lock_folder(Path(name)),
        )
        tmp = Path(tmp)
    except BaseException:
        _remove_empty(made)
        raise
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp's 0700 -> what mkdir would give
        emptied = path.is_dir()
        if emptied:
            mode = stat.S_IMODE(path.stat().st_mode)
            path.rmdir()  # empty, as checked (os.rename cannot replace a folder
            # on every system)
        try:
            os.rename(tmp, path)
        except BaseException:
            if emptied:  # put back as it was; the rename's error is the one raised
                with contextlib.suppress(OSError):
                    path.mkdir()
                    os.chmod(path, mode)
            raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty(made)
        raise
    finally:
        if lock is not None:
            os.close(lock)
    fsync_folder(path.parent)


def _make_parents(path: Path) -> list[Path]:
    """Make ``path``'s missing parent folders; those this call made, deepest
    first (one that another process makes meanwhile is not counted: it is not
    ours to remove)."""
    made = []
    try:
        for parent in reversed([p for p in path.parents if not p.exists()]):
            try:
                parent.mkdir()
            except FileExistsError:
                if not parent.is_dir():
                    raise
                continue
            made.append(parent)
    except BaseException:  # e.g. no permission one level down
        _remove_empty(made[::-1])
        raise
    return made[::-1]


def _remove_empty(folders: list[Path]) -> None:
    """Remove ``folders`` (deepest first) as long as they are empty: one that
    something else was put into meanwhile stays, and so do its parents."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            break


#: The dtype each kind of array is hashed at (:meth:`Transitions.sha256`).
_DIGEST_DTYPES = {"f": "<f8", "i": "<i8", "u": "<i8", "b": "|b1"}

#: What reading damaged bytes of an archive raises: zipfile's checks (a CRC or a
#: header that does not match, an unknown compression method), the
#: decompressor's, numpy's reading of an array's header and data, and the seeks
#: to offsets read from the archive.
_DAMAGED = (
    zipfile.BadZipFile, zlib.error, EOFError, ValueError, NotImplementedError,
    OSError,  # e.g. a seek to a damaged offset (the file itself opened)
    RuntimeError,  # zipfile: a member flagged encrypted (one bit of its header)
)  # fmt: skip


def load_npz(path: str | os.PathLike | io.IOBase) -> NpzArchive:
    """``np.load(path, allow_pickle=False)`` of an ``.npz`` archive (a path or a
    binary file object), refusing a file that is not one (empty, cut short, or
    another kind of file) with a ``ValueError`` that names it, where numpy would
    raise ``EOFError`` or advise loading the file with pickle; and a damaged one
    (a byte changed: ``zipfile.BadZipFile``, e.g. a bad CRC-32) with a
    ``ValueError`` naming it, and the array where one is being read
    (:class:`NpzArchive`). Errors opening the file (a missing file, a folder, a
    permission) stay ``OSError``s; once it is open, an ``OSError`` while reading
    it (a seek to an offset read from damaged bytes, but also a failing disk)
    is reported as a ``ValueError`` that names the file and keeps the error's
    text."""
    # a path is opened here, not by np.load: numpy leaves the file it opened
    # open when the archive's directory cannot be read (its NpzFile raises)
    owned = isinstance(path, (str, os.PathLike))
    fh = open(path, "rb") if owned else path  # OSError: cannot be read at all
    try:
        is_zip = zipfile.is_zipfile(fh)
        fh.seek(0)
        if not is_zip:
            raise ValueError(
                f"{path}: not an .npz archive (empty, cut short, or another kind of "
                "file)"
            )
        try:
            npz = np.load(fh, allow_pickle=False)
        except _DAMAGED as err:
            raise ValueError(
                f"{path}: not a readable .npz archive ({type(err).__name__}: "
                f"{err}); is the file damaged?"
            ) from None
    except BaseException:
        if owned:
            fh.close()
        raise
    return NpzArchive(npz, path, fh if owned else None)


class NpzArchive(Mapping):
    """An open ``.npz`` archive, as ``np.load`` gives it (``files``, ``[name]``,
    ``in``, ``with``), whose reads of damaged bytes (or of an array numpy cannot
    read without pickle) raise ``ValueError`` naming the file and the array
    instead of zipfile's or numpy's error."""

    def __init__(self, npz, path, file=None) -> None:
        self._npz, self._path = npz, path
        # the file this archive opened (``file``) is closed with it, or when it
        # is collected unclosed (np.load's own archive closed its file then)
        self._close_file = None if file is None else weakref.finalize(self, file.close)

    @property
    def files(self) -> list[str]:
        return self._npz.files

    def __getitem__(self, key: str) -> Array:
        try:
            return self._npz[key]
        except _DAMAGED as err:
            raise ValueError(
                f"{self._path}: array {key!r} cannot be read ({type(err).__name__}: "
                f"{err}); is the file damaged?"
            ) from None

    def __contains__(self, key: object) -> bool:
        return key in self._npz  # without reading the array

    def __iter__(self):
        return iter(self._npz)

    def __len__(self) -> int:
        return len(self._npz)

    def close(self) -> None:
        self._npz.close()
        if self._close_file is not None:
            self._close_file()

    def __enter__(self) -> NpzArchive:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _sharded(path: Any) -> Any:
    """A :class:`hipmdp.shards.Dataset` if ``path`` names a run's folder or its
    ``manifest.json``, else None (a file or an open file object)."""
    if isinstance(path, str | os.PathLike):
        path = Path(path)
        if path.is_dir() or path.suffix == ".json":
            from hipmdp.shards import Dataset  # shards builds on this module

            return Dataset(path)
    return None


#: Every array a dataset file may hold (:meth:`Transitions.arrays`).
FILE_ARRAYS = frozenset(
    ["format_version", "states", "actions", "next_states", "instances",
     "angle_dims", "rewards", "dones", "dt",
     "table_instances", "table_names", "table_values"]
)  # fmt: skip


def _check_members(path, archive: NpzArchive) -> None:
    """Raise ``ValueError`` naming ``path`` if the archive holds an array that
    no dataset file has: a member name with a damaged byte (zipfile checks the
    data's CRC, not the central directory's names), which would otherwise read
    as that optional array (``rewards``, ``dones``, ``dt``, the table) missing."""
    unknown = sorted(set(archive.files) - FILE_ARRAYS)
    if unknown:
        raise ValueError(
            f"{path}: holds arrays no hipmdp dataset file has ({', '.join(unknown)}):"
            " a damaged member name, or not a file hipmdp wrote"
        )


def npz_bytes(arrays: dict[str, Array]) -> bytes:
    """An ``.npz`` archive of ``arrays`` whose bytes depend only on the arrays.

    ``np.savez`` stamps the current time into every member; here members are
    stored uncompressed with the date ``ZIP_DATE``, so equal data give equal bytes
    (and equal checksums). Readable by ``np.load(..., allow_pickle=False)``.
    """
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_STORED) as archive:
        for key, value in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=ZIP_DATE)
            info.external_attr = 0o644 << 16
            archive.writestr(info, member.getvalue())
    return buffer.getvalue()


def check_queries(
    states, actions, state_dim: int, n_actions: int
) -> tuple[Array, Array]:
    """Validate a model query: states (n, D) finite, actions (n,) in [0, A).

    Actions are discrete: integers, or floats with whole values; fractional
    actions (a continuous action would be truncated to its index) and bools are
    refused. Returns the states as floats and the actions as integers.
    """
    shape = f"(n, {state_dim})"
    states = _finite_float("states", states, shape, 2)
    if states.shape[1] != state_dim:
        raise ValueError(f"states: expected shape {shape}, got {states.shape}")
    actions = _int_array("actions", actions, len(states))
    if len(actions) and (actions.min() < 0 or actions.max() >= n_actions):
        raise ValueError(f"actions: expected integers in [0, {n_actions})")
    return states, actions


def read_only(value: Any, dtype) -> Array:
    """A read-only copy of ``value`` as ``dtype``, for the arrays of a frozen
    object (a model's coefficients are computed from them once)."""
    out = np.array(value, dtype=dtype)
    out.setflags(write=False)
    return out


def is_integer(value: Any) -> bool:
    """A Python or numpy integer; not a bool, a float or a string."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def check_rng(rng: Any) -> None:
    """Raise ``ValueError`` naming ``rng`` unless it is a numpy Generator."""
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng: expected a numpy Generator, got {rng!r}")


def check_integer(name: str, value: Any, minimum: int) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is an integer
    (:func:`is_integer`) >= ``minimum``."""
    if not is_integer(value):
        raise ValueError(
            f"{name}: expected an integer >= {minimum}, got {value!r} "
            f"({type(value).__name__})"
        )
    if value < minimum:
        raise ValueError(f"{name}: expected >= {minimum}, got {value}")


def is_real_number(value: Any) -> bool:
    """A real number: a Python or numpy int or float, or a 0-d numpy array of
    one; not a bool (True would pass as 1), a string or a complex."""
    if isinstance(value, float):  # the common case first: updates call this per step
        return True
    if isinstance(value, bool | np.bool_):
        return False
    if isinstance(value, int | np.integer | np.floating):
        return True
    return (
        isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "iuf"
    )


def check_angle_dims(angle_dims: Any, d: int | None) -> tuple[int, ...]:
    """``angle_dims`` as a tuple of distinct int indices in ``[0, d)`` (``d``
    None: any index >= 0); a ValueError naming ``angle_dims`` otherwise."""
    try:
        raw = tuple(angle_dims)
    except TypeError:
        raise ValueError(
            f"angle_dims: expected a sequence of indices, got {angle_dims!r}"
        ) from None
    if not all(is_integer(i) for i in raw):
        raise ValueError(f"angle_dims: expected integer indices, got {raw}")
    angles = tuple(int(i) for i in raw)
    high = np.inf if d is None else d
    if any(i < 0 or i >= high for i in angles) or len(set(angles)) != len(angles):
        bound = ">= 0" if d is None else f"in [0, {d})"
        raise ValueError(f"angle_dims: expected distinct indices {bound}, got {angles}")
    return angles


def wanted_instances(instances: int | Iterable[int]) -> Array:
    """The instance ids a load asks for, as int64 (n >= 1,); a ValueError names
    ``instances`` for none, bools or non-integers."""
    return _ids("instances", instances, empty=False)


def _ids(name: str, ids: int | Iterable[int], *, empty: bool) -> Array:
    """``ids`` (an integer, a sequence, an array or a set, taken sorted) as int64
    (n,); a ValueError naming ``name`` for bools, non-integers or, unless
    ``empty``, none."""
    if isinstance(ids, set | frozenset):
        ids = sorted(ids)
    raw = np.atleast_1d(np.asarray(ids))
    if raw.ndim != 1 or (raw.size == 0 and not empty):
        raise ValueError(f"{name}: expected one or more ids, got {ids!r}")
    if raw.size == 0:
        return np.zeros(0, dtype=np.int64)
    return _int_array(name, raw, raw.size)


def _scalar_dt(path, dt: Array):
    """A file's stored ``dt``, a 0-d array, as its scalar (checked by the
    constructor)."""
    if dt.shape != ():
        raise ValueError(f"{path}: dt: expected a scalar, got shape {dt.shape}")
    return dt[()]


def _finite_float(name: str, x, shape_desc: str, ndim: int) -> Array:
    try:
        arr = np.asarray(x)
    except ValueError:  # ragged nested lists
        raise ValueError(f"{name}: expected an array of shape {shape_desc}") from None
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise ValueError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
    if arr.ndim != ndim:
        raise ValueError(f"{name}: expected shape {shape_desc}, got {arr.shape}")
    arr = arr.astype(float)
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(
            f"{name}: non-finite value at index {tuple(int(i) for i in bad)}"
        )
    return arr


def _int_array(name: str, x, n: int) -> Array:
    try:
        arr = np.asarray(x)
    except ValueError:  # ragged nested lists
        raise ValueError(f"{name}: expected an array of shape ({n},)") from None
    if arr.ndim != 1 or arr.shape[0] != n:
        raise ValueError(f"{name}: expected shape ({n},), got {arr.shape}")
    if np.issubdtype(arr.dtype, np.floating):
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise ValueError(f"{name}: expected integers, got non-integer values")
        if arr.size and np.abs(arr).max() > 2**53:  # beyond, floats skip integers
            raise ValueError(
                f"{name}: expected integers of magnitude <= 2**53 as floats (pass "
                f"an integer array for larger ids), got {np.abs(arr).max():g}"
            )
    elif not np.issubdtype(arr.dtype, np.integer) or arr.dtype == bool:
        raise ValueError(f"{name}: expected an integer array, got dtype {arr.dtype}")
    elif arr.dtype == np.uint64 and arr.size and arr.max() > np.iinfo(np.int64).max:
        raise ValueError(f"{name}: expected values below 2**63, got {arr.max()}")
    return arr.astype(np.int64)


@dataclass(frozen=True, eq=False)
class ParameterTable:
    """The physical parameters of each instance.

    Attributes:
        instances: instance ids ``b``, shape (n,), unique.
        names: parameter names (e.g. ``("link_mass_1", "link_mass_2")``), length p.
        values: parameter values, shape (n, p).
    """

    instances: Array
    names: tuple[str, ...]
    values: Array

    def __post_init__(self) -> None:
        ids = _int_array("instances", self.instances, np.asarray(self.instances).size)
        if isinstance(self.names, str):  # "ab" would become ("a", "b")
            raise ValueError(
                f"names: expected a sequence of names, got the string {self.names!r}"
            )
        names = tuple(self.names)
        if not all(isinstance(s, str) and s for s in names):
            raise ValueError("names: expected non-empty strings")
        if len(set(names)) != len(names):
            raise ValueError(f"names: duplicate parameter name in {names}")
        if len(np.unique(ids)) != len(ids):
            raise ValueError("instances: ids must be unique")
        vals = _finite_float("values", self.values, "(n_instances, n_params)", 2)
        if vals.shape != (len(ids), len(names)):
            raise ValueError(
                f"values: expected shape ({len(ids)}, {len(names)}), got {vals.shape}"
            )
        object.__setattr__(self, "instances", ids)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "values", vals)

    def row(self, instance: int) -> dict[str, float]:
        """The parameters of one instance as ``{name: value}``."""
        hit = np.flatnonzero(self.instances == int(instance))
        if hit.size == 0:
            raise KeyError(f"instance {instance} is not in the parameter table")
        return {
            n: float(v) for n, v in zip(self.names, self.values[hit[0]], strict=True)
        }

    def column(self, name: str) -> Array:
        """One parameter for every instance, shape (n,)."""
        if name not in self.names:
            raise KeyError(f"parameter {name!r} is not in {self.names}")
        return self.values[:, self.names.index(name)]

    def _arrays(self) -> dict[str, Array]:
        return {
            "table_instances": self.instances,
            "table_names": np.array(self.names, dtype=np.str_),
            "table_values": self.values,
        }

    @classmethod
    def load(cls, path: str | os.PathLike) -> ParameterTable | None:
        """The table stored in a dataset file (:meth:`Transitions.save`), or None
        if it has none; or a sharded dataset's (its directory or
        ``manifest.json``: every planned instance's row, from the manifest,
        :attr:`hipmdp.shards.Dataset.parameters`)."""
        dataset = _sharded(path)
        if dataset is not None:
            return dataset.parameters
        with load_npz(path) as f:
            _check_members(path, f)
            if "table_instances" not in f:
                return None
            missing = [k for k in ("table_names", "table_values") if k not in f]
            if missing:
                raise ValueError(
                    f"{path}: an incomplete parameter table (missing "
                    f"{', '.join(missing)})"
                )
            try:
                return cls(
                    instances=f["table_instances"],
                    names=tuple(str(s) for s in f["table_names"]),
                    values=f["table_values"],
                )
            except ValueError as err:  # a damaged array: name the file too
                raise ValueError(f"{path}: {err}") from None


@dataclass(frozen=True, eq=False)
class Transitions:
    """A batch of transitions ``(s, a, s', r, done)`` tagged by instance.

    Attributes:
        states: ``s``, shape (N, D), finite.
        actions: discrete action indices ``a``, shape (N,), integers >= 0.
        next_states: ``s'``, shape (N, D), finite.
        instances: instance id ``b`` of each transition, shape (N,), integers.
        rewards: shape (N,), or None.
        dones: episode ended after this transition, bool shape (N,), or None.
        angle_dims: state dimensions that are angles.
        dt: seconds per transition; if given, angle changes in ``deltas`` are
            unwrapped with the velocities (see the module docstring).
    """

    states: Array
    actions: Array
    next_states: Array
    instances: Array
    rewards: Array | None = None
    dones: Array | None = None
    angle_dims: tuple[int, ...] = ()
    dt: float | None = None

    def __post_init__(self) -> None:
        s = _finite_float("states", self.states, "(N, D)", 2)
        n, d = s.shape
        s2 = _finite_float("next_states", self.next_states, f"({n}, {d})", 2)
        if s2.shape != s.shape:
            raise ValueError(f"next_states: expected shape {s.shape}, got {s2.shape}")
        a = _int_array("actions", self.actions, n)
        if n and a.min() < 0:
            raise ValueError(f"actions: expected indices >= 0, got {a.min()}")
        b = _int_array("instances", self.instances, n)
        r = self.rewards
        if r is not None:
            r = _finite_float("rewards", r, f"({n},)", 1)
            if r.shape != (n,):
                raise ValueError(f"rewards: expected shape ({n},), got {r.shape}")
        done = self.dones
        if done is not None:
            done = np.asarray(done)
            if done.shape != (n,):
                raise ValueError(f"dones: expected shape ({n},), got {done.shape}")
            if done.dtype != bool:
                if not np.all(np.isin(done, (0, 1))):
                    raise ValueError("dones: expected booleans (or 0/1)")
                done = done.astype(bool)
        angles = check_angle_dims(self.angle_dims, d)
        dt = self.dt
        if dt is not None:
            if isinstance(dt, bool) or not isinstance(dt, int | float | np.number):
                raise ValueError(f"dt: expected a finite number > 0, got {dt!r}")
            dt = float(dt)
            if not (np.isfinite(dt) and dt > 0):
                raise ValueError(f"dt: expected a finite number > 0, got {self.dt}")
            # dt unwraps angle changes with their velocities; without angles it is
            # only recorded (a fitted model checks it), whatever the layout
            if angles and (d % 2 or any(i >= d // 2 for i in angles)):
                raise ValueError(
                    f"dt: needs the (qpos, qvel) layout, an even state dimension with"
                    f" angles in the first half; got D = {d}, angle_dims {angles}"
                )
        for name, v in [
            ("dt", dt),
            ("states", s),
            ("actions", a),
            ("next_states", s2),
            ("instances", b),
            ("rewards", r),
            ("dones", done),
            ("angle_dims", angles),
        ]:
            object.__setattr__(self, name, v)

    # -- shape facts ------------------------------------------------------------------

    def __repr__(self) -> str:
        """A summary, not the arrays: ``Transitions(N=2400, D=2, actions=3,
        instances=8, rewards, angle_dims=(0,), dt=0.1)``."""
        parts = [
            f"N={len(self)}",
            f"D={self.state_dim}",
            f"actions={self.n_actions}",
            f"instances={len(self.instance_ids)}",
        ]
        parts += [
            name for name in ("rewards", "dones") if getattr(self, name) is not None
        ]
        if self.angle_dims:
            parts.append(f"angle_dims={self.angle_dims}")
        if self.dt is not None:
            parts.append(f"dt={self.dt:g}")
        return f"Transitions({', '.join(parts)})"

    def __len__(self) -> int:
        return self.states.shape[0]

    @property
    def n_transitions(self) -> int:
        return self.states.shape[0]

    @property
    def state_dim(self) -> int:
        return self.states.shape[1]

    @property
    def n_actions(self) -> int:
        """``max(action) + 1`` (0 for an empty batch)."""
        return int(self.actions.max()) + 1 if len(self) else 0

    @property
    def instance_ids(self) -> Array:
        """Sorted unique instance ids."""
        return np.unique(self.instances)

    @property
    def deltas(self) -> Array:
        """``Δs = s' - s``, shape (N, D).

        Angle changes are unwrapped around ``v̄ dt`` if ``dt`` is set, else wrapped
        to (-π, π] (module docstring).
        """
        delta = self.next_states - self.states
        if self.angle_dims:
            idx = list(self.angle_dims)
            if self.dt is None:
                delta[:, idx] = wrap_angle(delta[:, idx])
            else:
                vel = [i + self.state_dim // 2 for i in idx]
                guess = 0.5 * (self.states[:, vel] + self.next_states[:, vel]) * self.dt
                delta[:, idx] = guess + wrap_angle(delta[:, idx] - guess)
        return delta

    # -- selection and concatenation ---------------------------------------------------

    def take(self, index: Array) -> Transitions:
        """The transitions at ``index``: a boolean mask (N,) or integer indices."""
        mask = np.asarray(index)
        if mask.shape == (0,) and mask.dtype.kind == "f":  # [] reads as float64
            mask = mask.astype(np.int64)
        if mask.dtype == bool:
            if mask.shape != (len(self),):
                raise ValueError(f"index: expected a mask of shape ({len(self)},)")
        elif mask.dtype.kind not in "iu" or mask.ndim != 1:
            raise ValueError(
                f"index: expected a boolean mask or 1-d integer indices, got "
                f"dtype {mask.dtype}, shape {mask.shape}"
            )
        elif mask.size and not -len(self) <= mask.min() <= mask.max() < len(self):
            raise ValueError(
                f"index: expected indices in [-{len(self)}, {len(self)}), got "
                f"{mask.min()} to {mask.max()}"
            )
        return Transitions(
            states=self.states[mask],
            actions=self.actions[mask],
            next_states=self.next_states[mask],
            instances=self.instances[mask],
            rewards=None if self.rewards is None else self.rewards[mask],
            dones=None if self.dones is None else self.dones[mask],
            angle_dims=self.angle_dims,
            dt=self.dt,
        )

    def select(
        self,
        instances: int | Iterable[int] | None = None,
        actions: int | Iterable[int] | None = None,
    ) -> Transitions:
        """The transitions of the given instance ids and/or action indices (each
        an integer, a sequence, an array or a set).

        Raises:
            ValueError: for ids or actions that are not integers, and for
                instance ids that are not in the data (an action without
                transitions only selects none).
        """
        mask = np.ones(len(self), dtype=bool)
        if instances is not None:
            ids = _ids("instances", instances, empty=True)
            unknown = np.setdiff1d(ids, self.instance_ids)
            if unknown.size:
                raise ValueError(
                    f"instances: ids {unknown.tolist()[:10]} are not in the data"
                )
            mask &= np.isin(self.instances, ids)
        if actions is not None:
            mask &= np.isin(self.actions, _ids("actions", actions, empty=True))
        return self.take(mask)

    def head(self, n: int) -> Transitions:
        """The first ``n`` transitions (all of them if there are fewer)."""
        check_integer("n", n, 0)
        return self.take(np.arange(min(n, len(self))))

    @classmethod
    def concatenate(cls, parts: Sequence[Transitions]) -> Transitions:
        """Stack batches with the same state dimension and angle dimensions.

        ``rewards``/``dones`` are kept only if every part has them.
        """
        parts = list(parts)
        if not parts:
            raise ValueError("concatenate: expected at least one Transitions")
        for i, p in enumerate(parts):
            if not isinstance(p, Transitions):
                raise ValueError(f"concatenate: part {i} is {type(p).__name__}")
        d, angles, dt = parts[0].state_dim, parts[0].angle_dims, parts[0].dt
        for i, p in enumerate(parts):
            if p.state_dim != d or p.angle_dims != angles or p.dt != dt:
                raise ValueError(
                    f"concatenate: part {i} has state_dim {p.state_dim}, angle_dims"
                    f" {p.angle_dims} and dt {p.dt}, expected {d}, {angles} and {dt}"
                )

        def cat(name: str) -> Array | None:
            vals = [getattr(p, name) for p in parts]
            if any(v is None for v in vals):
                return None
            return np.concatenate(vals)

        return cls(
            states=cat("states"),
            actions=cat("actions"),
            next_states=cat("next_states"),
            instances=cat("instances"),
            rewards=cat("rewards"),
            dones=cat("dones"),
            angle_dims=angles,
            dt=dt,
        )

    # -- files ---------------------------------------------------------------------

    def arrays(self, table: ParameterTable | None = None) -> dict[str, Array]:
        """The arrays of the file format (what :meth:`save` writes).

        Every instance in the data must have a row in ``table`` if one is given.
        """
        arrays: dict[str, Array] = {
            "format_version": np.array(FORMAT_VERSION),
            "states": self.states,
            "actions": self.actions,
            "next_states": self.next_states,
            "instances": self.instances,
            "angle_dims": np.array(self.angle_dims, dtype=np.int64),
        }
        if self.rewards is not None:
            arrays["rewards"] = self.rewards
        if self.dones is not None:
            arrays["dones"] = self.dones
        if self.dt is not None:
            arrays["dt"] = np.array(self.dt)
        if table is not None:
            if not isinstance(table, ParameterTable):
                raise ValueError(f"table: expected ParameterTable, got {type(table)}")
            missing = np.setdiff1d(self.instance_ids, table.instances)
            if missing.size:
                raise ValueError(
                    f"table: no parameters for instances {missing.tolist()[:10]}"
                )
            arrays.update(table._arrays())
        return arrays

    def sha256(self) -> str:
        """The SHA-256 (hex) of the data: each of :meth:`arrays`' arrays but the
        format's version, by name, shape and values at a fixed little-endian
        dtype per kind (float64, int64, bool); not the bytes of an ``.npz``
        (numpy's archive layout) nor the platform's default integer. Equal data
        give equal digests, however and wherever they were read or built;
        ``hipmdp.fit`` records its data's in the model's ``info["data_sha256"]``."""
        h = hashlib.sha256()
        for name, value in self.arrays().items():
            if name == "format_version":
                continue
            x = np.ascontiguousarray(value, dtype=_DIGEST_DTYPES[value.dtype.kind])
            h.update(f"{name}:{x.shape};".encode())
            h.update(x.tobytes())
        return h.hexdigest()

    def save(
        self, path: str | os.PathLike, table: ParameterTable | None = None
    ) -> Path:
        """Write an ``.npz`` (no pickle) atomically; optionally with the parameters.

        The bytes depend only on the data (see :func:`npz_bytes`). Returns the
        path; a ``path`` not ending in ``.npz`` is refused (``ValueError``).
        """
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"path: expected a .npz file name, got {path.name!r}")
        data = npz_bytes(self.arrays(table))
        return atomic_write(path, lambda fh: fh.write(data), clean=True)

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        instances: int | Iterable[int] | None = None,
    ) -> Transitions:
        """Read a file written by :meth:`save` (``allow_pickle=False``), or a sharded
        dataset (its directory or ``manifest.json``, see :mod:`hipmdp.shards`).

        Args:
            path: an ``.npz`` file (or an open binary file), a run directory or its
                manifest.
            instances: only these instance ids; a sharded dataset then reads only
                the shards that hold them (each checked against its checksum).
        """
        dataset = _sharded(path)
        if dataset is not None:
            return dataset.load(instances=instances)
        data = cls._load_file(path)
        if instances is None:
            return data
        wanted = wanted_instances(instances)
        unknown = sorted(set(wanted.tolist()) - set(data.instance_ids.tolist()))
        if unknown:
            raise ValueError(f"instances {unknown} are not in {path}")
        return data.select(instances=wanted)

    @classmethod
    def _load_file(cls, path) -> Transitions:
        with load_npz(path) as f:
            if "format_version" not in f:
                raise ValueError(
                    f"{path}: not a hipmdp Transitions file (no format_version)"
                )
            version = f["format_version"]
            if version.shape != () or version != FORMAT_VERSION:
                raise ValueError(
                    f"{path}: format_version {version.tolist()}, expected "
                    f"{FORMAT_VERSION}"
                )
            _check_members(path, f)
            required = ("states", "actions", "next_states", "instances", "angle_dims")
            missing = [k for k in required if k not in f]
            if missing:
                raise ValueError(
                    f"{path}: not a complete hipmdp Transitions file (missing "
                    f"{', '.join(missing)})"
                )
            arrays = {
                "states": f["states"],
                "actions": f["actions"],
                "next_states": f["next_states"],
                "instances": f["instances"],
                "rewards": f["rewards"] if "rewards" in f else None,
                "dones": f["dones"] if "dones" in f else None,
                "angle_dims": f["angle_dims"].tolist(),  # checked as integers
                "dt": _scalar_dt(path, f["dt"]) if "dt" in f else None,
            }
        try:
            return cls(**arrays)
        except ValueError as err:  # a damaged array: name the file too
            raise ValueError(f"{path}: {err}") from None
