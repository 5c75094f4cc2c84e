"""Sharded datasets: a manifest, shard files with checksums, resuming, lazy loading.

A run directory holds `manifest.json` and one `shard-XXXXX.npz` per block of
instances. A shard is what `hipmdp.Transitions.save` writes (the same keys, with the
shard's `ParameterTable`), so `Transitions.load` and `ParameterTable.load` read one
shard; but its bytes are reproducible: every archive member is stored uncompressed
with a fixed date (`np.savez` stamps the current time), so the same data give the
same bytes and the same SHA-256.

The manifest (JSON, written atomically when the run starts and when it completes)
holds:

- `format`: `FORMAT`;
- `config`: everything that determines the data (domain, policy, distribution,
  counts, seed, shard size), never how it was executed (workers, scheduler, paths);
- `parameter_names`, `angle_dims`;
- `shards`: per shard its `index`, `file`, `instances` (ids), `parameters` (one row
  per instance, the `ParameterTable` values), and once written its `sha256`,
  `counts` (`episodes`, `transitions`, `diverged_episodes`) and `diverged`
  episodes; `sha256` is null until the shard file is in place (`tasks.generate`
  also records each instance's MuJoCo steps per action, `sub_steps`);
- `complete`: every shard written;
- written by `tasks.generate`: `software` (package versions and a digest of the
  source) and, for a run continued by other software, `earlier_software`.

While the run goes on, each finished shard's `sha256`, `counts` and `diverged`
are appended as one line to `progress.jsonl` (flushed to disk), not written into
the manifest: rewriting a manifest that lists every instance after every shard
costs O(shards × instances), and at 90,000 instances more than the data. Reading
a manifest (`read_manifest`, `Dataset`) applies those lines, so an unfinished run
reads as if the manifest held them (a manifest replaced while the log is read
is read again); the completed run's manifest holds them all, and the log is
deleted. A line cut short by a kill is ignored.

A shard counts as finished only if the manifest (with the log) holds its checksum
and the file's bytes match it; anything else (missing, truncated, corrupt) is
redone on resume.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hipmdp.data import (
    ParameterTable,
    Transitions,
    atomic_temporaries,
    atomic_write,
    is_integer,
    is_real_number,
    npz_bytes,
    wanted_instances,
)

Array = np.ndarray

FORMAT = "hipmdp-shards/1"
MANIFEST = "manifest.json"
PROGRESS = "progress.jsonl"
#: What a progress line records of a finished shard (besides its `index`).
PROGRESS_FIELDS = ("sha256", "counts", "diverged")


def shard_name(index: int) -> str:
    """File name of shard `index`: `shard-00007.npz`."""
    return f"shard-{index:05d}.npz"


def shard_bytes(transitions: Transitions, table: ParameterTable) -> bytes:
    """The bytes `Transitions.save(path, table)` writes (reproducible, see
    `hipmdp.data.npz_bytes`)."""
    return npz_bytes(transitions.arrays(table))


def sha256(data: bytes) -> str:
    """Hex SHA-256 of `data`."""
    return hashlib.sha256(data).hexdigest()


def write_shard(directory: Path, index: int, data: bytes) -> str:
    """Write shard `index` atomically; returns its SHA-256."""
    atomic_write(Path(directory) / shard_name(index), lambda fh: fh.write(data))
    return sha256(data)


def shard_is_valid(directory: Path, entry: Mapping[str, Any]) -> bool:
    """Whether the manifest `entry` has a checksum and its file matches it."""
    path = Path(directory) / entry["file"]
    if entry.get("sha256") is None or not path.is_file():
        return False
    return sha256(path.read_bytes()) == entry["sha256"]


def read_manifest(directory: Path) -> dict[str, Any] | None:
    """The manifest in `directory`, with the shards finished since it was written
    (`progress.jsonl`) applied, or None if there is none.

    Raises:
        ValueError: if `manifest.json` exists but is not a manifest of this format.
    """
    path = Path(directory) / MANIFEST
    if not path.is_file():
        return None
    for _ in range(3):  # a manifest replaced while the log was read: again
        before = _identity(path)
        try:
            manifest = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise ValueError(f"{path} is not valid JSON ({error})") from None
        progress = read_progress(directory)
        if _identity(path) == before:
            break
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise ValueError(f"{path} is not a {FORMAT} manifest")
    entries = manifest.get("shards")
    if not isinstance(entries, list) or any(
        not isinstance(e, dict) or e.get("index") != i for i, e in enumerate(entries)
    ):
        raise ValueError(f"{path}: expected shards listed by index 0, 1, ...")
    for index, record in progress.items():
        if index < len(entries):
            entries[index].update(record)
    _check_manifest(path, manifest)
    return manifest


def _check_manifest(path: Path, manifest: Mapping[str, Any]) -> None:
    """Raise ValueError naming the field of `manifest` (read from `path`) that
    the readers use and that is missing or of the wrong kind (they failed as
    KeyErrors and TypeErrors, and "complete": "no" read as complete)."""

    def bad(field: str, expected: str) -> ValueError:
        return ValueError(f"{path}: {field}: expected {expected}")

    if not isinstance(manifest.get("complete"), bool):
        raise bad("complete", "true or false")
    names = manifest.get("parameter_names")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise bad("parameter_names", "a list of names")
    if not isinstance(manifest.get("config"), dict):
        raise bad("config", "an object")
    for i, entry in enumerate(manifest["shards"]):
        where = f"shards[{i}]"
        if entry.get("file") != shard_name(i):
            raise bad(f"{where}.file", repr(shard_name(i)))
        ids = entry.get("instances")
        if not isinstance(ids, list) or not all(is_integer(b) and b >= 0 for b in ids):
            raise bad(f"{where}.instances", "a list of instance ids")
        rows = entry.get("parameters")
        if not (
            isinstance(rows, list)
            and len(rows) == len(ids)
            and all(
                isinstance(r, list)
                and len(r) == len(names)
                and all(is_real_number(x) for x in r)
                for r in rows
            )
        ):
            raise bad(
                f"{where}.parameters",
                f"one row of {len(names)} numbers per instance ({len(ids)})",
            )
        digest = entry.get("sha256")
        if digest is not None and not (isinstance(digest, str) and len(digest) == 64):
            raise bad(f"{where}.sha256", "null or a SHA-256 in hex")
        counts = entry.get("counts")
        if counts is not None and not (
            isinstance(counts, dict)
            and is_integer(counts.get("transitions"))
            and counts["transitions"] >= 0
        ):
            raise bad(
                f"{where}.counts", "null or an object with a count of transitions"
            )


def _identity(path: Path) -> tuple[int, int]:
    """What changes when a file is replaced (``os.replace``) or rewritten."""
    st = path.stat()
    return st.st_ino, st.st_mtime_ns


def write_manifest(directory: Path, manifest: Mapping[str, Any]) -> Path:
    """Write `manifest.json` atomically (sorted keys, so equal content, equal bytes)."""
    text = json.dumps(manifest, indent=1, sort_keys=True) + "\n"
    return atomic_write(Path(directory) / MANIFEST, lambda fh: fh.write(text.encode()))


def append_progress(directory: Path, entry: Mapping[str, Any]) -> None:
    """Record a finished shard: one line of `progress.jsonl` with its `index` and
    `PROGRESS_FIELDS`, flushed to disk before returning (O(1), whatever the size
    of the run)."""
    record = {"index": entry["index"], **{k: entry[k] for k in PROGRESS_FIELDS}}
    line = json.dumps(record, sort_keys=True).encode() + b"\n"
    with open(Path(directory) / PROGRESS, "a+b") as fh:
        if fh.seek(0, os.SEEK_END):  # after a line a kill cut short: a new line
            fh.seek(-1, os.SEEK_END)
            line = line if fh.read(1) == b"\n" else b"\n" + line
        fh.write(line)  # (appended, wherever the position is)
        fh.flush()
        os.fsync(fh.fileno())


def read_progress(directory: Path) -> dict[int, dict[str, Any]]:
    """The finished shards `progress.jsonl` records, by index (the last line for an
    index wins); a line that is not a whole record (cut short by a kill) is
    skipped: its shard is redone on resume."""
    path = Path(directory) / PROGRESS
    if not path.is_file():
        return {}
    out: dict[int, dict[str, Any]] = {}
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if (
            isinstance(record, dict)
            and isinstance(record.get("index"), int)
            and not isinstance(record["index"], bool)  # JSON true was shard 1
            and record["index"] >= 0
            and all(k in record for k in PROGRESS_FIELDS)
        ):
            out[record["index"]] = {k: record[k] for k in PROGRESS_FIELDS}
    return out


def remove_progress(directory: Path) -> None:
    """Delete `progress.jsonl`, once the manifest holds what it recorded."""
    (Path(directory) / PROGRESS).unlink(missing_ok=True)


def flat_config(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A manifest config with its nested mappings flattened: `{"distribution":
    {"sigma": 0.1}}` gives `{"distribution.sigma": 0.1}`."""
    flat: dict[str, Any] = {}
    for key, value in config.items():
        if isinstance(value, Mapping):
            flat.update(flat_config(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def config_differences(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """Keys whose values differ between two manifest configs, as `key: old -> new`,
    sorted; a nested mapping's keys one by one (`distribution.sigma: ...`)."""
    old, new = flat_config(old), flat_config(new)
    keys = sorted(set(old) | set(new))
    return [
        f"{k}: {old.get(k)!r} -> {new.get(k)!r}"
        for k in keys
        if old.get(k) != new.get(k)
    ]


def remove_temporaries(directory: Path) -> list[Path]:
    """Delete the temporary files a killed `atomic_write` left (`.NAME.*.tmp` for
    the manifest and shards); returns them."""
    found = atomic_temporaries(directory, MANIFEST)
    found += atomic_temporaries(directory, "shard-*.npz")
    for path in found:
        path.unlink()
    return found


class Dataset:
    """A sharded run read lazily: the manifest now, shards when asked for.

    Attributes:
        directory: the run directory.
        manifest: the parsed manifest.

    Raises:
        FileNotFoundError: if `path` does not exist.
        ValueError: if there is no manifest of this format at `path`.
    """

    def __init__(self, path: str | Path) -> None:
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file or folder")
        if path.is_file() and path.name != MANIFEST:
            raise ValueError(
                f"{path}: expected a run folder or its {MANIFEST}, got another file"
            )
        self.directory = path.parent if path.name == MANIFEST else path
        manifest = read_manifest(self.directory)
        if manifest is None:
            npz = sorted(f.name for f in self.directory.glob("*.npz"))
            hint = (
                f" (an experiment's run folder? read one of its .npz files with "
                f"hipmdp.Transitions.load, e.g. {self.directory / npz[0]})"
                if npz
                else ""
            )
            raise ValueError(f"no {MANIFEST} in {self.directory}{hint}")
        self.manifest = manifest

    @property
    def complete(self) -> bool:
        return bool(self.manifest["complete"])

    @property
    def instances(self) -> Array:
        """Every instance id `b` of the run, in shard order, shape `(B,)`."""
        ids = [b for entry in self.manifest["shards"] for b in entry["instances"]]
        return np.array(ids, dtype=np.int64)

    @property
    def parameters(self) -> ParameterTable:
        """The parameters of every instance (from the manifest, no shard read)."""
        rows = [r for entry in self.manifest["shards"] for r in entry["parameters"]]
        return ParameterTable(
            instances=self.instances,
            names=tuple(self.manifest["parameter_names"]),
            values=np.array(rows, dtype=float).reshape(len(rows), -1),
        )

    @property
    def n_transitions(self) -> int:
        """Transitions in the finished shards."""
        entries = self.manifest["shards"]
        return sum(e["counts"]["transitions"] for e in entries if e["counts"])

    def load(self, instances: int | Iterable[int] | None = None) -> Transitions:
        """The transitions of `instances` (default all), reading only their shards,
        each checked against its checksum.

        Raises:
            ValueError: for an id not in the run, or a needed shard that is not
                finished or does not match its checksum.
        """
        wanted = None if instances is None else wanted_instances(instances)
        if wanted is not None:
            unknown = np.setdiff1d(wanted, self.instances)
            if unknown.size:
                ids = np.unique(self.instances)
                have = (
                    f"{ids[0]} to {ids[-1]}"
                    if ids.size > 1
                    and np.array_equal(ids, np.arange(ids[0], ids[-1] + 1))
                    else str(ids.tolist()[:20]) + (" ..." if ids.size > 20 else "")
                )
                raise ValueError(
                    f"instances {unknown.tolist()[:10]} are not in the run "
                    f"(its instances: {have})"
                )
        parts = []
        for entry in self.manifest["shards"]:
            if wanted is not None and not np.isin(entry["instances"], wanted).any():
                continue
            data = self._read(entry)
            part = Transitions.load(io.BytesIO(data))
            if wanted is not None:  # the shard's own of the ids asked for
                part = part.select(instances=np.intersect1d(wanted, part.instance_ids))
            parts.append(part)
        return Transitions.concatenate(parts)

    def verify(self) -> None:
        """Check every shard against its checksum, reading each once.

        Raises:
            ValueError: naming the first shard that is not finished or does not
                match its checksum.
        """
        for entry in self.manifest["shards"]:
            self._read(entry)

    def _read(self, entry: Mapping[str, Any]) -> bytes:
        path = self.directory / entry["file"]
        resume = f"--resume (the command that made the run, --out {self.directory})"
        if entry.get("sha256") is None:
            raise ValueError(
                f"{self.directory}: shard {entry['file']} is not finished; continue "
                f"it with {resume}"
            )
        if not path.is_file():  # finished, then deleted or not copied
            raise ValueError(
                f"{self.directory}: shard {entry['file']} is missing (the manifest "
                f"lists it as finished); redo it with {resume}"
            )
        data = path.read_bytes()
        if sha256(data) != entry["sha256"]:
            raise ValueError(
                f"{self.directory}: shard {entry['file']} does not match its checksum "
                f"(corrupt or truncated); redo it with {resume}"
            )
        # the manifest has no checksum: its instances and parameters must be the
        # shard's own (an edited one read other instances, or none, silently)
        table = ParameterTable.load(io.BytesIO(data))
        rows = np.array(entry["parameters"], dtype=float)
        if not (
            table is not None
            and table.instances.tolist() == entry["instances"]
            and list(table.names) == list(self.manifest["parameter_names"])
            and rows.shape == table.values.shape
            and np.array_equal(rows, table.values)
        ):
            raise ValueError(
                f"{self.directory}: {MANIFEST} does not match shard {entry['file']} "
                "(its instances or parameters differ from the shard's own table); "
                "the manifest was edited or damaged"
            )
        return data


def load_dataset(path: str | Path) -> Transitions | Dataset:
    """One shard (or any `.npz` dataset) as `Transitions`, or a run directory (or
    its `manifest.json`) as a lazy `Dataset` (`.instances`, `.parameters`,
    `.load(instances=...)`)."""
    path = Path(path)
    if path.suffix == ".npz":
        return Transitions.load(path)
    return Dataset(path)
