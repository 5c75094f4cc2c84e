"""Reading a recording back, for the tests: ``rerun rrd print -vvv`` prints every
chunk as a table whose first columns are the row id and the timelines, then its
components (``Archetype:field``)."""

from __future__ import annotations

import os
import re
from collections.abc import Iterator

import numpy as np

from tasks.recording import rerun_rrd

TIMELINES = ("episode", "step", "transition")


def _chunks(path: str | os.PathLike, entity: str) -> Iterator[tuple[list, list]]:
    """Per chunk of ``entity``: its column names and its rows' cells."""
    printed = rerun_rrd("print", "-vvv", str(path))
    printed.check_returncode()
    columns: list[str] | None = None
    rows: list[list[str]] = []
    ours = False
    for line in printed.stdout.splitlines():
        chunk = re.match(r"Chunk\(\S+\) with \d+ rows \([^)]*\) - (\S+) - ", line)
        if chunk:
            if ours and columns:
                yield columns, rows
            columns, rows = None, []
            ours = chunk.group(1) == entity
            continue
        if not ours or not line.startswith("│ │ "):
            continue
        cells = [c.strip() for c in line.strip("│ ").split("┆")]
        if cells[0] == "RowId" and columns is None:
            columns = cells
        elif columns and cells[0].startswith("row_"):
            rows.append(cells)
    if ours and columns:
        yield columns, rows


def rrd_times(path: str | os.PathLike, entity: str) -> dict[str, np.ndarray]:
    """The time index of every row of ``entity`` (its static rows excluded), per
    timeline, in the order the rows were sent. Empty if nothing matched (every
    caller then fails on the timelines it expects)."""
    times: dict[str, list[int]] = {}
    for columns, rows in _chunks(path, entity):
        for cells in rows:
            for name, cell in zip(columns, cells, strict=False):
                if name in TIMELINES:
                    times.setdefault(name, []).append(int(cell))
    return {name: np.array(v) for name, v in times.items()}


def rrd_components(path: str | os.PathLike, entity: str) -> set[str]:
    """The components (``Archetype:field``) logged on ``entity``, static or not."""
    return {
        name for columns, _ in _chunks(path, entity) for name in columns if ":" in name
    }


def rrd_scalars(path: str | os.PathLike, entity: str) -> np.ndarray:
    """The ``Scalars:scalars`` values of ``entity``'s rows, in the order they were
    sent, shape (rows, values per row); the print gives each as Python's repr,
    so they are read back exactly."""
    values = []
    for columns, rows in _chunks(path, entity):
        if "Scalars:scalars" not in columns:
            continue
        at = columns.index("Scalars:scalars")
        for cells in rows:
            values.append([float(v) for v in cells[at].strip("[]").split(",")])
    return np.array(values)


def rrd_static_row(path: str | os.PathLike, entity: str) -> dict[str, str]:
    """The one row of ``entity`` with no time column (logged statically), as
    {column: printed cell}, the row id left out."""
    (row,) = [
        dict(zip(columns[1:], cells[1:], strict=True))
        for columns, rows in _chunks(path, entity)
        for cells in rows
        if not set(columns) & set(TIMELINES) and "log_time" not in columns
    ]
    return row
