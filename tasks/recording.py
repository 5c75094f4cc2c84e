"""Headless rerun recordings (``.rrd``) of experiments, for later review in the viewer.

Nothing here opens a viewer or a network connection: a :class:`Recording` writes one
``.rrd`` file, with its blueprint (the panel layout) stored inside, so that
``rerun runs/<name>/acrobot.rrd`` opens laid out. Data are sent in columns, one call
per entity per episode (``send_columns``), not row by row, which keeps recording cheap.

Timelines: ``episode`` and ``step``; the experiments count ``step`` on from one
episode to the next (``offset_steps``), so that scrubbing it plays the episodes in
turn (a step count that restarts each episode would put every episode's steps on
the same instants, where the viewer shows only one of them).

Set the environment variable ``RERUN=off`` to disable recording; every method is then
a no-op (its input still checked) and no file is written.

The file is written to a temporary name beside its destination and renamed when the
recording is closed, so an interrupted run never leaves a half-written ``.rrd``.
"""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from hipmdp.data import fsync_folder

Array = np.ndarray


#: The values of the environment variable ``RERUN`` read as on and as off.
RERUN_ON, RERUN_OFF = ("on", "1", "true", "yes", ""), ("off", "0", "false", "no")


def recording_enabled() -> bool:
    """False when the environment variable ``RERUN`` is ``off`` (or 0/false/no);
    True when it is unset or ``on`` (1/true/yes). Any other value is refused with
    a ``ValueError``: the rerun SDK would only warn of it once recording began,
    after the work."""
    value = os.environ.get("RERUN", "on").strip().lower()
    if value not in RERUN_ON + RERUN_OFF:
        raise ValueError(
            f"RERUN: expected on or off (or 1/0, true/false, yes/no), got "
            f"{os.environ['RERUN']!r}"
        )
    return value in RERUN_ON


def resolve_record(config):
    """``config`` with ``record`` False under ``RERUN=off``, so that the run's
    ``config.json``, report and traced trial say what it writes."""
    if config.record and not recording_enabled():
        return dataclasses.replace(config, record=False)
    return config


def recording_line(config, name: str) -> str:
    """A report's line on the recording ``name``: how to open it, or that the run
    wrote none."""
    if config.record:
        return f"Recording: `rerun {name}` (from this folder)."
    return "No recording (`--no-record` or `RERUN=off`)."


def offset_steps(lengths) -> list[Array]:
    """The ``step`` index of each of consecutive episodes of ``lengths`` rows:
    counted on from the previous episode's last (``[0, 1], [2, 3, 4]`` for
    lengths 2 and 3)."""
    ends = np.cumsum(lengths, dtype=np.int64)
    return [np.arange(end - n, end) for n, end in zip(lengths, ends, strict=True)]


def capsule_poses(points: Array) -> tuple[Array, Array, Array]:
    """The capsules joining consecutive points, in rerun's terms: a capsule runs
    from its translation along its local +z for its length.

    Args:
        points: shape (T, P, 3).

    Returns:
        ``translations`` (T, P − 1, 3), the segments' starts; ``lengths``
        (T, P − 1); ``quaternions`` (T, P − 1, 4), unit, scalar last (x, y, z, w),
        each turning +z onto its segment (the identity for a segment of length 0,
        a half turn about x for one along −z).
    """
    points = np.asarray(points, dtype=float)
    start, segment = points[:, :-1], np.diff(points, axis=1)
    lengths = np.linalg.norm(segment, axis=-1)
    unit = np.divide(
        segment, lengths[..., None], out=np.zeros_like(segment),
        where=lengths[..., None] > 0,
    )  # fmt: skip
    unit[lengths == 0] = (0.0, 0.0, 1.0)
    # the half-way quaternion: axis z × u, angle between z and u
    q = np.concatenate(
        [-unit[..., 1:2], unit[..., 0:1], np.zeros_like(lengths)[..., None],
         1.0 + unit[..., 2:3]],
        axis=-1,
    )  # fmt: skip
    opposite = q[..., 3] < 1e-12  # u = −z: any half turn about an axis ⟂ z
    q[opposite] = (1.0, 0.0, 0.0, 0.0)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return start, lengths, q


class Recording:
    """One headless ``.rrd`` file, written atomically.

    Use as a context manager; on an exception the temporary file is removed.

    Args:
        path: destination ``.rrd`` file.
        application_id: rerun application id (groups recordings in the viewer).
        blueprint: a ``rerun.blueprint.Blueprint`` stored as the default layout.
        enabled: False turns recording off. ``RERUN=off`` wins over True: the
            rerun SDK itself reads it and would write nothing.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        application_id: str,
        blueprint=None,
        enabled: bool | None = None,
    ) -> None:
        self.path = Path(path)
        if self.path.suffix != ".rrd":
            raise ValueError(f"path: expected a .rrd file name, got {self.path.name!r}")
        # `enabled` first: a Recording told not to record does not read RERUN
        self.enabled = (enabled is None or bool(enabled)) and recording_enabled()
        self._rec = None
        self._styled: set[str] = set()
        if not self.enabled:
            return
        import rerun as rr  # imported lazily: RERUN=off runs never load it

        self._rr = rr
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        self._rec = rr.RecordingStream(application_id)
        self._rec.save(str(self._tmp), default_blueprint=blueprint)

    # -- logging in columns --------------------------------------------------------

    def _indexes(
        self, n: int, episode: int | Array, step: Array | None, timeline: str = "step"
    ) -> list | None:
        """The time columns of ``n`` rows (checked): ``episode``, and ``step`` on
        the timeline named ``timeline``; None when disabled."""
        ep = np.broadcast_to(np.asarray(episode, dtype=np.int64), (n,))
        if step is not None:
            step = np.asarray(step, dtype=np.int64)
            if step.shape != (n,):
                raise ValueError(f"step: expected shape ({n},), got {step.shape}")
        if self._rec is None:
            return None
        idx = [self._rr.TimeColumn("episode", sequence=ep)]
        if step is not None:
            idx.append(self._rr.TimeColumn(timeline, sequence=step))
        return idx

    def scalars(
        self,
        entity: str,
        values: Array,
        *,
        episode: int | Array,
        step: Array | None = None,
        timeline: str = "step",
    ) -> None:
        """A time series: ``values`` shape (T,), one row per (episode, step);
        ``step`` on the timeline named ``timeline``."""
        values = np.asarray(values, dtype=float).reshape(-1)
        indexes = self._indexes(values.size, episode, step, timeline)
        if indexes is None:
            return
        self._rec.send_columns(
            entity, indexes=indexes, columns=self._rr.Scalars.columns(scalars=values)
        )

    def belief(
        self,
        means: Array,
        sds: Array,
        truth: dict[str, float],
        *,
        episode: int,
        step: Array,
        timeline: str = "step",
    ) -> None:
        """The weight-belief panel: per weight ``k`` the series ``/belief/w{k}/mean``,
        ``/upper`` and ``/lower`` (mean ± 2σ), and each true parameter as a
        constant ``/belief/true/<name>``. ``means``, ``sds``: shape (T, K)."""
        at = {"episode": episode, "step": step, "timeline": timeline}
        for k in range(np.shape(means)[1]):
            base = f"/belief/w{k + 1}"
            mean, sd = means[:, k], sds[:, k]
            self.scalars(f"{base}/mean", mean, **at)
            self.scalars(f"{base}/upper", mean + 2 * sd, **at)
            self.scalars(f"{base}/lower", mean - 2 * sd, **at)
        for name, value in truth.items():
            self.scalars(f"/belief/true/{name}", np.full(len(step), float(value)), **at)

    def strips(
        self,
        entity: str,
        strips: Array,
        *,
        episode: int | Array,
        step: Array | None = None,
        color: tuple[int, int, int] | None = None,
        radius: float = 0.03,
    ) -> None:
        """A moving 3D polyline: ``strips`` shape (T, P, 3), one strip per row."""
        strips = np.asarray(strips, dtype=np.float32)
        if strips.ndim != 3 or strips.shape[2] != 3:
            raise ValueError(f"strips: expected shape (T, P, 3), got {strips.shape}")
        self._moving(
            entity, "LineStrips3D", strips=strips, episode=episode, step=step,
            style={"radii": [radius]}, color=color,
        )  # fmt: skip

    def boxes(
        self,
        entity: str,
        centers: Array,
        half_size: tuple[float, float, float],
        *,
        episode: int | Array,
        step: Array | None = None,
        color: tuple[int, int, int] | None = None,
    ) -> None:
        """A moving solid box (a cart): ``centers`` shape (T, 3), one per row;
        ``half_size`` constant."""
        centers = np.asarray(centers, dtype=np.float32)
        if centers.ndim != 2 or centers.shape[1] != 3:
            raise ValueError(f"centers: expected shape (T, 3), got {centers.shape}")
        self._moving(
            entity, "Boxes3D", centers=centers, episode=episode, step=step,
            style={"half_sizes": [half_size], "fill_mode": "solid"}, color=color,
        )  # fmt: skip

    def capsules(
        self,
        entity: str,
        points: Array,
        radius: float,
        *,
        episode: int | Array,
        step: Array | None = None,
        color: tuple[int, int, int] | None = None,
    ) -> None:
        """Moving solid links: per row of ``points`` (shape (T, P, 3)) a capsule
        of ``radius`` from each point to the next (P − 1 per row), posed by
        :func:`capsule_poses`."""
        points = np.asarray(points, dtype=float)
        if points.ndim != 3 or points.shape[1] < 2 or points.shape[2] != 3:
            raise ValueError(
                f"points: expected shape (T, P, 3) with P >= 2, got {points.shape}"
            )
        if not radius > 0:
            raise ValueError(f"radius: expected a value > 0, got {radius}")
        translations, lengths, quaternions = capsule_poses(points)
        per_row = points.shape[1] - 1
        self._moving(
            entity, "Capsules3D", episode=episode, step=step,
            style={"radii": [radius], "fill_mode": "solid"}, color=color,
            per_row=per_row,
            translations=translations.reshape(-1, 3).astype(np.float32),
            lengths=lengths.reshape(-1).astype(np.float32),
            quaternions=quaternions.reshape(-1, 4).astype(np.float32),
        )  # fmt: skip

    def _moving(
        self,
        entity: str,
        archetype: str,
        *,
        episode,
        step,
        style,
        color,
        per_row: int = 1,
        **moving,
    ) -> None:
        """Rows of the rerun ``archetype`` whose fields in ``moving`` change row
        by row, ``per_row`` instances each (one ``send_columns``), its constant
        ``style`` and ``color`` logged once per entity, statically."""
        n_rows = len(next(iter(moving.values()))) // per_row
        indexes = self._indexes(n_rows, episode, step)
        if indexes is None:
            return
        kind = getattr(self._rr, archetype)
        columns = kind.columns(**moving)
        if per_row > 1:
            columns = columns.partition(np.full(n_rows, per_row))
        self._rec.send_columns(entity, indexes=indexes, columns=columns)
        if entity not in self._styled:
            self._styled.add(entity)
            if color is not None:
                style = style | {"colors": [color]}
            self._rec.log(entity, kind.from_fields(**style), static=True)

    def text(self, entity: str, text: str) -> None:
        """A static Markdown note (e.g. what the panels show)."""
        if self._rec is None:
            return
        self._rec.log(
            entity,
            self._rr.TextDocument(text, media_type=self._rr.MediaType.MARKDOWN),
            static=True,
        )

    # -- lifecycle -------------------------------------------------------------------

    def close(self) -> Path | None:
        """Flush, finish the file and move it to ``path``; None if disabled."""
        if self._rec is None:
            return None
        self._rec.flush()
        self._rec.disconnect()
        self._rec = None
        # on disk before the rename, as atomic_write (a writable handle: Windows'
        # FlushFileBuffers needs one)
        with open(self._tmp, "r+b") as fh:
            os.fsync(fh.fileno())
        os.replace(self._tmp, self.path)
        fsync_folder(self.path.parent)
        return self.path

    def abort(self) -> None:
        """Stop recording and remove the temporary file."""
        if self._rec is None:
            return
        self._rec.disconnect()
        self._rec = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def rerun_rrd(*args: str) -> subprocess.CompletedProcess:
    """``rerun rrd <args>`` (the CLI installed with rerun-sdk), its output captured
    as text; rerun's own log quietened."""
    exe = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    env = dict(os.environ, RUST_LOG="error")
    return subprocess.run([exe, "rrd", *args], capture_output=True, text=True, env=env)


def rrd_contents(path: str | os.PathLike) -> dict[str, int]:
    """Rows per entity in an ``.rrd`` file, read back with ``rerun rrd print``.

    Also runs ``rerun rrd verify`` first and raises ``RuntimeError`` if the file does
    not verify. Used by tests and for a quick look at a recording without a viewer.
    """
    verify = rerun_rrd("verify", str(path))
    if verify.returncode != 0:
        raise RuntimeError(f"rerun rrd verify failed on {path}: {verify.stderr[-500:]}")
    printed = rerun_rrd("print", str(path))
    printed.check_returncode()
    rows: dict[str, int] = {}
    pattern = r"with (\d+) rows \([^)]*\) - (\S+) - data columns"
    for m in re.finditer(pattern, printed.stdout):
        rows[m.group(2)] = rows.get(m.group(2), 0) + int(m.group(1))
    return rows
