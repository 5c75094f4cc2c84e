"""`python -m tasks.generate`: in-process smoke runs, reproducible files, the grid,
and bad options that stop before anything is written."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hipmdp import Transitions
from hipmdp.data import ParameterTable
from tasks import generate

TINY = ["--instances", "2", "--episodes-per-instance", "2", "--max-steps", "10"]


def test_main_writes_a_loadable_dataset_and_its_summary(tmp_path, capsys):
    out = tmp_path / "data"
    result = generate.main(
        ["--domain", "acrobot", "--seed", "3", "--out", str(out), *TINY]
    )
    assert sorted(p.name for p in out.iterdir()) == [
        "acrobot_seed3.json",
        "acrobot_seed3.npz",
    ]
    data = Transitions.load(out / "acrobot_seed3.npz")
    table = ParameterTable.load(out / "acrobot_seed3.npz")
    summary = json.loads((out / "acrobot_seed3.json").read_text())
    assert summary["dataset"] == "acrobot_seed3.npz" and summary["seed"] == 3
    assert summary["counts"] == {
        "instances": 2,
        "episodes": 4,
        "transitions": len(data),
        "diverged_episodes": 0,
    }
    assert len(data) == 4 * 10 and data.angle_dims == (0, 1)
    np.testing.assert_array_equal(data.states, result.collection.transitions.states)
    masses = table.values[:, :2]
    assert np.all((masses >= 0.7) & (masses <= 1.3)) and len(np.unique(masses)) == 4
    np.testing.assert_array_equal(table.values[:, 2:], 1.0)  # lengths stay nominal
    assert "wrote" in capsys.readouterr().out


def test_same_arguments_write_identical_files(tmp_path):
    for name in ("a", "b"):
        generate.main(["--domain", "cartpole", "--out", str(tmp_path / name), *TINY])
    first = (tmp_path / "a" / "cartpole_seed0.npz").read_bytes()
    assert first == (tmp_path / "b" / "cartpole_seed0.npz").read_bytes()
    generate.main(
        ["--domain", "cartpole", "--seed", "1", "--out", str(tmp_path / "c"), *TINY]
    )
    assert first != (tmp_path / "c" / "cartpole_seed1.npz").read_bytes()


def test_grid_takes_every_combination(tmp_path):
    argv = ["--domain", "cartpole", "--grid", "2", "--out", str(tmp_path)]
    argv += ["--vary", "pole_mass=0.1:0.3", "--vary", "pole_half_length=0.4:0.6"]
    argv += ["--episodes-per-instance", "1", "--max-steps", "5", "--no-progress"]
    table = generate.main(argv).collection.parameters
    assert table.names == ("cart_mass", "pole_mass", "pole_half_length")
    np.testing.assert_allclose(
        table.values,
        [[1, 0.1, 0.4], [1, 0.1, 0.6], [1, 0.3, 0.4], [1, 0.3, 0.6]],
    )


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--domain", "pendulum"], "invalid choice"),
        (["--domain", "acrobot", "--instances", "0"], "--instances must be >= 1"),
        (["--domain", "acrobot", "--episodes-per-instance", "0"], "must be >= 1"),
        (["--domain", "acrobot", "--grid", "2", "--instances", "3"], "exclusive"),
        (
            ["--domain", "acrobot", "--grid", "2", "--distribution", "uniform"],
            "not allowed",
        ),
        (["--domain", "acrobot", "--vary", "pole_mass=0.1:0.2"], "acrobot parameters"),
        (["--domain", "acrobot", "--vary", "link_mass_1=0.1:1"], "lower bound 0.2"),
        (["--domain", "acrobot", "--vary", "link_mass_1=1"], "NAME=LOW:HIGH"),
        (["--domain", "acrobot", "--vary", "link_mass_1=1.2:0.9"], "LOW must be"),
        (["--domain", "cartpole", "--policy", "sarsa"], "invalid choice"),
    ],
)
def test_bad_options_stop_with_a_message_and_write_nothing(
    tmp_path, capsys, argv, message
):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as stopped:
        generate.main([*argv, "--out", str(out)])
    assert stopped.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_help_describes_the_options(capsys):
    with pytest.raises(SystemExit) as stopped:
        generate.main(["--help"])
    assert stopped.value.code == 0
    text = capsys.readouterr().out
    for option in ("--domain", "--instances", "--grid", "--vary", "--seed", "--out"):
        assert option in text
