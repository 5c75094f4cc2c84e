"""Headless rerun recordings: written atomically, verifiable, with the rows we sent."""

from __future__ import annotations

import numpy as np
import pytest
import rerun.blueprint as rrb

from tasks.recording import Recording, recording_enabled, rrd_contents


def _blueprint():
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.TimeSeriesView(origin="/belief", name="weights"),
            rrb.Spatial3DView(origin="/rollout", name="rollout"),
        )
    )


def test_recording_reads_back_with_entities_and_rows(tmp_path):
    path = tmp_path / "r.rrd"
    n_steps = [7, 11]
    with Recording(path, application_id="hipmdp-test", blueprint=_blueprint()) as rec:
        for ep, n in enumerate(n_steps):
            step = np.arange(n)
            rec.scalars("/belief/w1/mean", np.sin(step), episode=ep, step=step)
            rec.strips("/rollout/real", np.zeros((n, 3, 3)), episode=ep, step=step)
        rec.scalars("/returns/hipmdp", [-100.0, -80.0], episode=[0, 1])
        rec.text("/notes", "what the panels show")
    rows = rrd_contents(path)
    assert rows["/belief/w1/mean"] == sum(n_steps)
    # the strips entity: one row per step plus one static style row
    assert rows["/rollout/real"] == sum(n_steps) + 1
    assert rows["/returns/hipmdp"] == 2
    assert any(e.startswith("/view/") for e in rows)  # the blueprint is in the file
    assert [p.name for p in tmp_path.iterdir()] == ["r.rrd"]  # no temp file left


def test_rerun_off_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("RERUN", "off")
    assert not recording_enabled()
    with Recording(tmp_path / "r.rrd", application_id="t") as rec:
        rec.scalars("/x", [1.0, 2.0], episode=0, step=np.arange(2))
    assert list(tmp_path.iterdir()) == []


def test_crash_leaves_no_file(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        with Recording(tmp_path / "r.rrd", application_id="t") as rec:
            rec.scalars("/x", [1.0], episode=0, step=np.arange(1))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_bad_input(tmp_path):
    with pytest.raises(ValueError, match="path: expected a .rrd"):
        Recording(tmp_path / "r.txt", application_id="t")
    with Recording(tmp_path / "r.rrd", application_id="t", enabled=True) as rec:
        with pytest.raises(ValueError, match="strips: expected shape"):
            rec.strips("/s", np.zeros((3, 2)), episode=0)
        with pytest.raises(ValueError, match="step: expected shape"):
            rec.scalars("/x", [1.0, 2.0], episode=0, step=np.arange(3))
