"""Headless rerun recordings: written atomically, verifiable, with the rows we sent."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import rerun as rr
import rerun.blueprint as rrb
from scipy.spatial.transform import Rotation

from tasks import acrobot_swingup, cartpole_prediction
from tasks.recording import (
    Recording,
    capsule_poses,
    offset_steps,
    recording_enabled,
    recording_line,
    resolve_record,
    rrd_contents,
)
from tests._rrd import rrd_components, rrd_static_row, rrd_times


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
            links = np.random.default_rng(ep).normal(size=(n, 3, 3))
            rec.capsules("/rollout/links", links, 0.04, episode=ep, step=step)
        rec.scalars("/returns/hipmdp", [-100.0, -80.0], episode=[0, 1])
        rec.text("/notes", "what the panels show")
    rows = rrd_contents(path)
    assert rows["/belief/w1/mean"] == sum(n_steps)
    # the strips entity: one row per step plus one static style row
    assert rows["/rollout/real"] == sum(n_steps) + 1
    assert rows["/rollout/links"] == sum(n_steps) + 1
    np.testing.assert_array_equal(
        rrd_times(path, "/rollout/links")["step"],
        np.concatenate([np.arange(n) for n in n_steps]),
    )
    assert {"Capsules3D:translations", "Capsules3D:radii"} <= rrd_components(
        path, "/rollout/links"
    )
    assert rows["/returns/hipmdp"] == 2
    assert rows["/notes"] == 1
    assert any(e.startswith("/view/") for e in rows)  # the blueprint is in the file
    assert [p.name for p in tmp_path.iterdir()] == ["r.rrd"]  # no temp file left


@pytest.mark.parametrize("value", ["garbage", "of", "2"])
def test_an_unknown_rerun_value_is_refused(monkeypatch, capsys, value):
    """The SDK took it as on and only warned once recording began, after the
    work; the experiments read it in ``resolve_record``, before."""
    monkeypatch.setenv("RERUN", value)
    with pytest.raises(ValueError, match=f"^RERUN: expected on or off.*'{value}'"):
        recording_enabled()
    # a Recording told not to record does not read it
    assert not Recording("r.rrd", application_id="t", enabled=False).enabled
    for on in ("on", "1", "TRUE", "yes", "", " on\n"):
        monkeypatch.setenv("RERUN", on)
        assert recording_enabled()
    for off in ("off", "0", "False", "no", " OFF "):
        monkeypatch.setenv("RERUN", off)
        assert not recording_enabled()
    # the experiments' command lines say so as a usage error, naming it
    monkeypatch.setenv("RERUN", value)
    for parse_args in (acrobot_swingup.parse_args, cartpole_prediction.parse_args):
        with pytest.raises(SystemExit) as stopped:
            parse_args([])
        assert stopped.value.code == 2
        assert "RERUN: expected on or off" in capsys.readouterr().err
        parse_args(["--no-record"])  # no recording: RERUN is not read


def test_rerun_off_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("RERUN", "off")
    assert not recording_enabled()
    with Recording(tmp_path / "r.rrd", application_id="t") as rec:
        rec.scalars("/x", [1.0, 2.0], episode=0, step=np.arange(2))
    assert list(tmp_path.iterdir()) == []


def test_rerun_off_wins_over_enabled_and_input_is_still_checked(tmp_path, monkeypatch):
    """The rerun SDK reads RERUN=off itself and writes nothing; a Recording told
    enabled=True used to expect a file then, and failed on closing."""
    monkeypatch.setenv("RERUN", "off")
    with Recording(tmp_path / "r.rrd", application_id="t", enabled=True) as rec:
        assert not rec.enabled
        with pytest.raises(ValueError, match="strips: expected shape"):
            rec.strips("/s", np.zeros((3, 2)), episode=0)
        with pytest.raises(ValueError, match="strips: expected shape"):
            rec.strips("/s", np.zeros((3, 2, 2)), episode=0)  # 2D points
        with pytest.raises(ValueError, match="centers: expected shape"):
            rec.boxes("/b", np.zeros((3, 2)), (1.0, 1.0, 1.0), episode=0)
        with pytest.raises(ValueError, match="points: expected shape"):
            rec.capsules("/c", np.zeros((3, 1, 3)), 0.1, episode=0)
        with pytest.raises(ValueError, match="radius: expected a value > 0"):
            rec.capsules("/c", np.zeros((3, 2, 3)), 0.0, episode=0)
        with pytest.raises(ValueError, match="step: expected shape"):
            rec.scalars("/x", [1.0, 2.0], episode=0, step=np.arange(3))
    assert list(tmp_path.iterdir()) == []


def test_resolve_record_turns_recording_off_under_rerun_off(monkeypatch):
    from tasks.acrobot_swingup import SwingupConfig

    config = SwingupConfig()
    assert config.record and resolve_record(config) is config
    monkeypatch.setenv("RERUN", "off")
    assert not resolve_record(config).record
    assert resolve_record(config) == dataclasses.replace(config, record=False)
    # a config that does not record does not read RERUN, whatever its value
    monkeypatch.setenv("RERUN", "garbage")
    unrecorded = dataclasses.replace(config, record=False)
    assert resolve_record(unrecorded) is unrecorded


def test_recording_line_says_whether_there_is_a_recording():
    from tasks.acrobot_swingup import SwingupConfig

    config = SwingupConfig()
    assert (
        recording_line(config, "acrobot.rrd")
        == "Recording: `rerun acrobot.rrd` (from this folder)."
    )
    unrecorded = dataclasses.replace(config, record=False)
    assert recording_line(unrecorded, "acrobot.rrd").startswith("No recording")


def test_capsules_join_consecutive_points():
    """Each capsule runs from its point along its rotated +z, for its length, to
    the next point: at random, along ±z and for a segment of length 0."""
    points = np.random.default_rng(0).normal(size=(40, 3, 3))
    points[0, 1] = points[0, 0] + (0.0, 0.0, -2.0)  # the half turn
    points[1, 1] = points[1, 0] + (0.0, 0.0, 3.0)  # the identity
    points[2, 2] = points[2, 1]  # length 0
    start, lengths, q = capsule_poses(points)
    assert start.shape == (40, 2, 3) and lengths.shape == (40, 2)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    axis = np.zeros((80, 3))
    axis[:, 2] = lengths.ravel()
    ends = start + Rotation.from_quat(q.reshape(-1, 4)).apply(axis).reshape(40, 2, 3)
    np.testing.assert_allclose(ends, points[:, 1:], atol=1e-12)
    np.testing.assert_array_equal(start, points[:, :-1])
    assert lengths[2, 1] == 0.0


def test_offset_steps_count_on_across_episodes():
    steps = offset_steps([2, 3, 1])
    assert [s.tolist() for s in steps] == [[0, 1], [2, 3, 4], [5]]
    assert offset_steps([]) == []


def test_crash_leaves_no_file(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        with Recording(tmp_path / "r.rrd", application_id="t") as rec:
            rec.scalars("/x", [1.0], episode=0, step=np.arange(1))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_the_file_appears_only_when_closed(tmp_path):
    """Written beside its destination (in a folder made for it) and renamed on
    closing, so that a run killed mid-recording leaves no half-written .rrd."""
    path = tmp_path / "run" / "r.rrd"
    rec = Recording(path, application_id="t")
    rec.scalars("/x", [1.0, 2.0], episode=0, step=np.arange(2))
    assert not path.exists()
    assert rec.close() == path
    assert [p.name for p in path.parent.iterdir()] == ["r.rrd"]
    assert rrd_contents(path)["/x"] == 2


def test_rrd_contents_refuses_a_file_that_does_not_verify(tmp_path):
    path = tmp_path / "r.rrd"
    path.write_bytes(b"not a recording")
    with pytest.raises(RuntimeError, match="rerun rrd verify failed"):
        rrd_contents(path)


def test_style_and_notes_are_static_with_the_values_given(tmp_path):
    """Each moving entity's look (radius, half sizes, solid fill, color) and the
    Markdown note are logged once, statically (no time column), so that they
    apply at every instant of every timeline. A color is rerun's packed RGBA:
    opaque red 0xFF0000FF = 255·2²⁴ + 255; a fill mode is its enum value. The
    sizes are exact in float32, so they print back as given."""
    path = tmp_path / "r.rrd"
    step = np.arange(2)
    with Recording(path, application_id="t") as rec:
        rec.strips("/s", np.zeros((2, 2, 3)), episode=0, step=step,
                   color=(255, 0, 0), radius=0.5)  # fmt: skip
        rec.boxes("/b", np.zeros((2, 3)), (0.5, 0.25, 2.0), episode=0, step=step)
        rec.capsules("/c", np.ones((2, 3, 3)), 0.125, episode=0, step=step)
        rec.text("/notes", "what the *panels* show")
    solid = f"[{rr.components.FillMode.Solid.value}]"
    assert rrd_static_row(path, "/s") == {
        "LineStrips3D:colors": f"[{255 * 2**24 + 255}]",
        "LineStrips3D:radii": "[0.5]",
    }
    assert rrd_static_row(path, "/b") == {
        "Boxes3D:half_sizes": "[[0.5, 0.25, 2.0]]",
        "Boxes3D:fill_mode": solid,
    }
    assert rrd_static_row(path, "/c") == {
        "Capsules3D:radii": "[0.125]",
        "Capsules3D:fill_mode": solid,
    }
    assert rrd_static_row(path, "/notes") == {
        "TextDocument:text": "[what the *panels* show]",
        "TextDocument:media_type": "[text/markdown]",
    }


def test_bad_input(tmp_path):
    with pytest.raises(ValueError, match="path: expected a .rrd"):
        Recording(tmp_path / "r.txt", application_id="t")
    with Recording(tmp_path / "r.rrd", application_id="t", enabled=True) as rec:
        with pytest.raises(ValueError, match="strips: expected shape"):
            rec.strips("/s", np.zeros((3, 2)), episode=0)
        with pytest.raises(ValueError, match="step: expected shape"):
            rec.scalars("/x", [1.0, 2.0], episode=0, step=np.arange(3))


def _capture(rec: Recording) -> dict[str, list]:
    """What `rec` sends to rerun, decoded: per entity, its (indexes, values)
    batches, the indexes as {timeline: array}."""
    sent: dict[str, list] = {}
    send = rec._rec.send_columns

    def capture(entity, indexes, columns):
        times = {i.timeline_name(): i.as_arrow_array().to_numpy() for i in indexes}
        (column,) = list(columns)
        values = column.as_arrow_array().flatten().to_numpy(zero_copy_only=False)
        sent.setdefault(entity, []).append((times, values))
        return send(entity, indexes=indexes, columns=columns)

    rec._rec.send_columns = capture
    return sent


def test_belief_panel_sends_mean_and_two_sigma_band_on_the_steps(tmp_path):
    """The values and time indexes themselves (the row counts above cannot tell
    a band of ±1σ from ±2σ, or a zeroed episode timeline): per weight the mean,
    mean ± 2σ, and the true parameters as constants, at (episode, step)."""
    means = np.array([[0.5, 1.0], [0.6, 1.1], [0.7, 1.3]])
    sds = np.array([[0.1, 0.2], [0.05, 0.1], [0.02, 0.3]])
    step = np.array([0, 4, 9])
    with Recording(tmp_path / "r.rrd", application_id="t", enabled=True) as rec:
        sent = _capture(rec)
        rec.belief(means, sds, {"link_mass_2": 0.9}, episode=3, step=step)
    expected = {"/belief/true/link_mass_2": np.full(3, 0.9)}
    for k in range(2):
        base = f"/belief/w{k + 1}"
        expected[f"{base}/mean"] = means[:, k]
        expected[f"{base}/upper"] = means[:, k] + 2 * sds[:, k]
        expected[f"{base}/lower"] = means[:, k] - 2 * sds[:, k]
    assert set(sent) == set(expected)
    for entity, values in expected.items():
        ((times, got),) = sent[entity]
        np.testing.assert_array_equal(got, values, err_msg=entity)
        np.testing.assert_array_equal(times["episode"], [3, 3, 3], err_msg=entity)
        np.testing.assert_array_equal(times["step"], step, err_msg=entity)


def test_time_columns_carry_per_row_episodes_and_the_named_timeline(tmp_path):
    """An episode per row (the returns: one row per episode) and a step sent on
    another timeline (the prediction experiment's ``transition``)."""
    with Recording(tmp_path / "r.rrd", application_id="t", enabled=True) as rec:
        sent = _capture(rec)
        rec.scalars("/returns", [-3.0, -2.0, -1.0], episode=[0, 1, 2])
        rec.scalars("/mse", [0.1, 0.2], episode=4, step=[5, 6], timeline="transition")
    ((times, values),) = sent["/returns"]
    assert set(times) == {"episode"}
    np.testing.assert_array_equal(times["episode"], [0, 1, 2])
    np.testing.assert_array_equal(values, [-3.0, -2.0, -1.0])
    ((times, values),) = sent["/mse"]
    assert set(times) == {"episode", "transition"}
    np.testing.assert_array_equal(times["episode"], [4, 4])
    np.testing.assert_array_equal(times["transition"], [5, 6])
