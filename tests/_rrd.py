"""Reading a recording's time indexes back, for the tests: ``rerun rrd print
-vvv`` prints every chunk as a table whose first columns are the row id and the
timelines."""

from __future__ import annotations

import os
import re

import numpy as np

from tasks.recording import rerun_rrd

TIMELINES = ("episode", "step", "transition")


def rrd_times(path: str | os.PathLike, entity: str) -> dict[str, np.ndarray]:
    """The time index of every row of ``entity`` (its static rows excluded), per
    timeline, in the order the rows were sent. Empty if nothing matched (every
    caller then fails on the timelines it expects)."""
    printed = rerun_rrd("print", "-vvv", str(path))
    printed.check_returncode()
    times: dict[str, list[int]] = {}
    columns: list[str] | None = None
    ours = False
    for line in printed.stdout.splitlines():
        chunk = re.match(r"Chunk\(\S+\) with \d+ rows \([^)]*\) - (\S+) - ", line)
        if chunk:
            columns = None
            ours = chunk.group(1) == entity
            continue
        if not ours or not line.startswith("│ │ "):
            continue
        cells = [c.strip() for c in line.strip("│ ").split("┆")]
        if cells[0] == "RowId":
            columns = cells
        elif columns and cells[0].startswith("row_"):
            for name, cell in zip(columns, cells, strict=False):
                if name in TIMELINES:
                    times.setdefault(name, []).append(int(cell))
    return {name: np.array(v) for name, v in times.items()}
