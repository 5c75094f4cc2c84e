"""The energy check: its energy decomposition, banded errors and noisy simulator on
known inputs, and the check itself on a finished (tiny) swing-up run."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from scipy import stats

from tasks import acrobot, acrobot_energy, agents
from tasks.acrobot import AcrobotParams
from tasks.agents import ACROBOT, SimulatorModel
from tests.test_acrobot_swingup import TINY

PARAMS = AcrobotParams(0.9, 1.1, 1.0, 1.0)


@pytest.fixture(autouse=True)
def _own_worker_state(monkeypatch):
    """``_init`` installs a worker's models and options in the module's
    ``_STATE``; tests that call it (some with stand-ins such as ``hip=None``)
    each get their own, so none leaves its stand-ins to a later test."""
    monkeypatch.setattr(acrobot_energy, "_STATE", {})


def _states(rng, n):
    return rng.uniform(-1, 1, (n, 4)) * [np.pi, np.pi, 4.0, 8.0]


def test_velocity_errors_of_either_sign_add_half_eps_m_eps():
    """Positions exact, velocity errors ±ε in pairs: the linear term cancels and
    the energy error is the mean of ½ εᵀ M ε > 0, computed here directly."""
    rng = np.random.default_rng(0)
    true_next = _states(rng, 200)
    true_next = np.concatenate([true_next, true_next])
    eps = rng.normal(0, 0.3, (200, 2))
    eps = np.concatenate([eps, -eps])
    predicted = true_next.copy()
    predicted[:, 2:] += eps
    start = _states(rng, 400)
    terms = acrobot_energy.energy_terms(predicted, true_next, start, PARAMS)
    mass = acrobot.mass_matrix(true_next, PARAMS)
    quadratic = np.mean([0.5 * e @ m @ e for e, m in zip(eps, mass, strict=True)])
    assert terms["quadratic"] == pytest.approx(quadratic, rel=1e-12)
    assert terms["quadratic"] > 0.05
    assert terms["linear"] == pytest.approx(0.0, abs=1e-12)
    assert terms["total"] == pytest.approx(quadratic, rel=1e-10)
    assert terms["positional"] == pytest.approx(0.0, abs=1e-10)
    gain = acrobot.energy(true_next, PARAMS) - acrobot.energy(start, PARAMS)
    assert terms["true_gain"] == pytest.approx(gain.mean(), rel=1e-12)


def test_the_kinetic_terms_take_m_at_the_true_next_state():
    """Errors in θ₂ and the velocities together: linear and quadratic use M(s'),
    not M(ŝ'); the positional term is the rest."""
    rng = np.random.default_rng(4)
    true_next = _states(rng, 100)
    predicted = true_next.copy()
    predicted[:, 1] += 0.5
    eps = rng.normal(0, 0.3, (100, 2))
    predicted[:, 2:] += eps
    terms = acrobot_energy.energy_terms(predicted, true_next, true_next, PARAMS)
    mass = acrobot.mass_matrix(true_next, PARAMS)
    linear = [e @ m @ q for e, m, q in zip(eps, mass, true_next[:, 2:], strict=True)]
    quadratic = [0.5 * e @ m @ e for e, m in zip(eps, mass, strict=True)]
    assert terms["linear"] == pytest.approx(np.mean(linear), rel=1e-10)
    assert terms["quadratic"] == pytest.approx(np.mean(quadratic), rel=1e-10)
    total = acrobot.energy(predicted, PARAMS) - acrobot.energy(true_next, PARAMS)
    assert terms["total"] == pytest.approx(total.mean(), rel=1e-10)
    rest = total.mean() - np.mean(linear) - np.mean(quadratic)
    assert terms["positional"] == pytest.approx(rest, rel=1e-8)
    assert abs(rest) > 0.1  # M(ŝ') differs from M(s') here: the test can see it


def test_position_errors_go_to_the_positional_term():
    rng = np.random.default_rng(1)
    true_next = _states(rng, 50)
    predicted = true_next.copy()
    predicted[:, 0] += 0.1  # the shoulder angle only: velocities exact
    terms = acrobot_energy.energy_terms(predicted, true_next, true_next, PARAMS)
    assert terms["linear"] == terms["quadratic"] == 0.0
    total = acrobot.energy(predicted, PARAMS) - acrobot.energy(true_next, PARAMS)
    assert terms["positional"] == pytest.approx(total.mean(), rel=1e-12)
    assert abs(terms["positional"]) > 1e-3


def test_banded_errors_put_each_state_in_its_band():
    states = np.zeros((4, 4))
    states[:, 3] = [1.0, -2.0, 3.5, 20.0]  # bands 0-2, 2-4 (its lower edge), 2-4, 14-
    true_next = np.zeros((4, 4))
    true_next[:, 1] = [0.3, 1.0, 2.0, 3.0]  # M differs row by row, and from M(s)
    predicted = true_next.copy()
    predicted[:, 2:] = [[1.0, 2.0], [3.0, 0.0], [4.0, 0.0], [0.0, 5.0]]
    out = acrobot_energy.banded_errors(predicted, true_next, states, PARAMS)
    np.testing.assert_array_equal(out["share"], [0.25, 0.5, 0, 0, 0, 0, 0.25])
    mass = acrobot.mass_matrix(true_next, PARAMS)
    energies = [0.5 * e @ m @ e for e, m in zip(predicted[:, 2:], mass, strict=True)]
    expected = np.array(
        [energies[0], energies[1] + energies[2], 0, 0, 0, 0, energies[3]]
    )
    np.testing.assert_allclose(out["kinetic_share"], expected / sum(energies))
    np.testing.assert_allclose(out["rmse"][0], [1.0, 2.0])
    np.testing.assert_allclose(out["rmse"][1], [np.sqrt(12.5), 0.0])
    np.testing.assert_allclose(out["rmse"][6], [0.0, 5.0])
    assert np.all(np.isnan(out["rmse"][2:6]))


def test_elbow_wrap_marks_steps_near_or_across_theta2_pi():
    states = np.zeros((4, 4))
    true_next = np.zeros((4, 4))
    states[:, 1] = [0.0, np.pi - 0.5, 3.0, -1.0]
    true_next[:, 1] = [0.3, np.pi - 0.4, -3.0, -1.2]  # the third crosses ±π
    states[2, 1] = np.pi - 0.7  # ... from outside the band
    np.testing.assert_array_equal(
        acrobot_energy.elbow_wrap(states, true_next), [False, True, True, False]
    )
    predicted = true_next.copy()
    predicted[:, 2] = [1.0, 0.0, 2.0, 0.0]
    out = acrobot_energy.banded_errors(predicted, true_next, states, PARAMS)
    assert out["wrap_share"] == 0.5
    mass = acrobot.mass_matrix(true_next, PARAMS)
    energies = 0.5 * mass[:, 0, 0] * predicted[:, 2] ** 2
    assert out["wrap_kinetic_share"] == pytest.approx(energies[2] / energies.sum())


def test_elbow_wrap_is_symmetric_and_judged_from_the_starting_state():
    """Near −π counts as near +π; a step that ends near the wrap without
    starting near it or crossing it does not count (the wrap share is of steps
    that start there)."""
    states = np.zeros((3, 4))
    true_next = np.zeros((3, 4))
    states[:, 1] = [-np.pi + 0.3, np.pi - 1.0, 0.0]
    true_next[:, 1] = [-np.pi + 0.2, np.pi - 0.1, 0.1]  # the second ends near π
    np.testing.assert_array_equal(
        acrobot_energy.elbow_wrap(states, true_next), [True, False, False]
    )
    predicted = true_next.copy()
    predicted[:, 2] = [1.0, 1.0, 0.0]
    out = acrobot_energy.banded_errors(predicted, true_next, states, PARAMS)
    assert out["wrap_share"] == pytest.approx(1 / 3)
    mass = acrobot.mass_matrix(true_next, PARAMS)[:, 0, 0]
    assert out["wrap_kinetic_share"] == pytest.approx(mass[0] / (mass[0] + mass[1]))


def test_exact_predictions_have_zero_energy_shares_without_warnings():
    """With no velocity error there is no ½ εᵀ M ε to share out: every share is
    0, not 0/0. Empty bands are the rule (few states reach |θ̇₂| ≥ 14 rad/s), so
    they must not warn either: numpy's warnings would fill the printout."""
    states = _states(np.random.default_rng(6), 20) * [1, 1, 1, 0.2]  # |θ̇₂| < 2
    true_next = _states(np.random.default_rng(7), 20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = acrobot_energy.banded_errors(true_next, true_next, states, PARAMS)
    np.testing.assert_array_equal(out["kinetic_share"], 0.0)
    assert out["wrap_kinetic_share"] == 0.0
    np.testing.assert_array_equal(out["rmse"][0], 0.0)
    assert np.all(np.isnan(out["rmse"][1:]))


def test_noisy_simulator_adds_unbiased_noise_to_velocities_only():
    simulator = SimulatorModel(ACROBOT, PARAMS)
    noisy = acrobot_energy.NoisySimulator(simulator, 0.25, np.random.default_rng(2))
    rng = np.random.default_rng(3)
    states = np.repeat(_states(rng, 1), 2000, axis=0)
    actions = np.full(2000, 2)
    err = noisy.predict(states, actions) - simulator.predict(states, actions)
    np.testing.assert_array_equal(err[:, :2], 0.0)
    # within 4 standard errors: of the mean σ/√n, of the sd about σ/√(2n), of a
    # correlation of independent columns 1/√n
    assert np.all(np.abs(err[:, 2:].mean(axis=0)) < 4 * 0.25 / np.sqrt(2000))
    np.testing.assert_allclose(err[:, 2:].std(axis=0), 0.25, rtol=4 / np.sqrt(2 * 2000))
    # one draw per velocity: the two columns are independent
    assert abs(np.corrcoef(err[:, 2], err[:, 3])[0, 1]) < 4 / np.sqrt(2000)
    # and Gaussian, as documented: Kolmogorov-Smirnov on the 4000 independent
    # errors, false-alarm probability 1e-4 (uniform noise of the same sd fails)
    assert stats.kstest(err[:, 2:].ravel(), stats.norm(0, 0.25).cdf).pvalue > 1e-4


def test_energy_conserving_model_adds_exactly_the_torques_work():
    """The noisy simulator's steps, rescaled: each changes the energy of the
    instance by τ Δθ₂, with the actions' torques."""
    simulator = SimulatorModel(ACROBOT, PARAMS)
    noisy = acrobot_energy.NoisySimulator(simulator, 0.5, np.random.default_rng(4))
    model = agents.EnergyConserving(noisy, PARAMS)
    rng = np.random.default_rng(5)
    states = _states(rng, 50)
    actions = rng.integers(0, 3, 50)
    out = model.predict(states, actions)
    turn = (out[:, 1] - states[:, 1] + np.pi) % (2 * np.pi) - np.pi  # slow: no wrap
    work = acrobot.ACTIONS[actions] * turn
    change = acrobot.energy(out, PARAMS) - acrobot.energy(states, PARAMS)
    # every row can reach E(s) + τ Δθ₂ at its predicted pose (above the pose's
    # potential, its energy at rest), so every row must add exactly the work; a
    # share of rows with velocities 0 would let a wrong "unreachable" pass
    rest = out * [1, 1, 0, 0]
    reachable = acrobot.energy(states, PARAMS) + work > acrobot.energy(rest, PARAMS)
    assert reachable.all()
    np.testing.assert_allclose(change, work, atol=1e-9)
    noisy_change = acrobot.energy(
        acrobot_energy.NoisySimulator(simulator, 0.5, np.random.default_rng(4)).predict(
            states, actions
        ),
        PARAMS,
    ) - acrobot.energy(states, PARAMS)
    # without the rescaling every step misses the work by far more than the check's
    # tolerance (a miss below 1e-6 has probability ~1e-6 per row under the noise),
    # so the check above can fail
    assert np.all(np.abs(noisy_change - work) > 1e-6)


def test_columns_take_the_exact_models_columns_on_fast_rows_only():
    class Constant:
        def __init__(self, value):
            self.value, self.asked = value, []

        def predict(self, states, actions):
            self.asked.append(len(states))
            return np.full(states.shape, self.value)

    model, exact = Constant(1.0), Constant(2.0)
    states = np.zeros((3, 4))
    states[:, 3] = [0.0, 6.0, -5.0]
    out = acrobot_energy.Columns(model, exact, 5.0, slice(2, 4)).predict(
        states, np.zeros(3, dtype=int)
    )
    np.testing.assert_array_equal(out, [[1, 1, 1, 1], [1, 1, 2, 2], [1, 1, 2, 2]])
    assert exact.asked == [2]


def test_columns_take_the_angles_predicted_for_each_fast_rows_own_action():
    """exact_fast_angles: the exact model's angle columns, predicted with each fast
    row's own action (an exact model that echoes the action in every column, so
    a column or action taken from the wrong place shows)."""

    class Echo:
        def predict(self, states, actions):
            return np.asarray(actions)[:, None] + [10.0, 20.0, 30.0, 40.0]

    states = np.zeros((3, 4))
    states[:, 3] = [0.0, 6.0, -7.0]
    out = acrobot_energy.Columns(_Constant(0.0), Echo(), 5.0, slice(0, 2)).predict(
        states, np.array([0, 1, 2])
    )
    np.testing.assert_array_equal(out, [[0, 0, 0, 0], [11, 21, 0, 0], [12, 22, 0, 0]])


def test_sampled_weights_draw_the_training_instances_weights(run):
    import hipmdp

    hip = hipmdp.load(run[0] / "hipmdp_model.npz")
    sampled = acrobot_energy.SampledWeights(hip, np.random.default_rng(1))
    rows = {tuple(np.round(sampled.draw().belief.mean, 9)) for _ in range(200)}
    assert rows == {tuple(np.round(w[1:], 9)) for w in hip.weights.T}


def test_sampled_planning_draws_a_model_per_episode_and_plans_as_plan_does(run):
    """With every draw the prior-mean model, one-episode-at-a-time planning is
    ``plan`` in one call: the same start states and exploration."""
    import hipmdp
    from hipmdp.planning import LearnedModel, plan
    from hipmdp.sarsa import init_state

    hip = hipmdp.load(run[0] / "hipmdp_model.npz")
    mean = LearnedModel(hip, hip.prior(), ACROBOT.angle_dims)
    sampled = acrobot_energy.SampledWeights(hip, np.random.default_rng(0))
    drawn = []
    sampled.draw = lambda: drawn.append(1) or mean
    basis = ACROBOT.basis()
    task = ACROBOT.planning_task(PARAMS, 30)
    starts = _states(np.random.default_rng(2), 5) * 0.05
    state = init_state(ACROBOT.n_actions, basis.n_features, ACROBOT.initial_value)
    args = (state, basis)
    got = acrobot_energy._plan(
        *args, sampled, task, starts, 3, np.random.default_rng(4)
    )
    want = plan(
        *args, ACROBOT.sarsa, mean, task, starts, 3, rng=np.random.default_rng(4)
    )
    assert len(drawn) == 3
    np.testing.assert_array_equal(got.steps, want.steps)
    np.testing.assert_array_equal(got.state.weights, want.state.weights)


def test_batch_distance_is_normalised_and_wraps_the_angles():
    batch = np.array([[0.0, 0.0, 0.0, 0.0], [np.pi - 0.01, 0.0, 0.0, 0.0]])
    distance = acrobot_energy.BatchDistance(batch)
    queries = np.array(
        [
            [0.0, 0.0, 4 * np.pi, 0.0],  # one box half-width in θ̇₁
            [0.0, 0.0, 0.0, -4.5 * np.pi],  # half of one in θ̇₂
            [-np.pi + 0.01, 0.0, 0.0, 0.0],  # 0.02 rad across the wrap
            [0.0, np.pi / 2, 0.0, 0.0],
            [0.0, 0.0, 7 * np.pi, 0.0],  # 1.75 box half-widths: velocities do not wrap
            [np.nextafter(-np.pi, -4), 0.0, 0.0, 0.0],  # a hair below −π wraps
        ]
    )
    np.testing.assert_allclose(
        distance(queries), [1.0, 0.5, 0.02 / np.pi, 0.5, 1.75, 0.01 / np.pi]
    )


def test_nanmean_averages_the_finite_entries_and_leaves_empty_columns_nan():
    """The banded summaries average over trials the bands a trial had states in;
    a band no trial reached stays NaN (not 0, which reads as no error)."""
    x = np.array([[1.0, np.nan, np.nan], [3.0, 4.0, np.nan]])
    got = acrobot_energy._nanmean(x)
    np.testing.assert_array_equal(got[:2], [2.0, 4.0])
    assert np.isnan(got[2])


def test_band_medians_take_each_bands_own_values():
    states = np.zeros((5, 4))
    states[:, 3] = [0.5, 1.0, 1.5, -3.0, 20.0]
    medians = acrobot_energy.band_medians(np.array([1.0, 2.0, 9.0, 4.0, 5.0]), states)
    np.testing.assert_array_equal(medians[[0, 1, 6]], [2.0, 4.0, 5.0])
    assert np.all(np.isnan(medians[2:6]))


class _Constant:
    def __init__(self, value):
        self.value, self.asked = value, []

    def predict(self, states, actions):
        self.asked.append((states[:, 3].tolist(), list(actions)))
        return np.full_like(states, self.value)


def test_split_asks_each_model_for_its_own_rows_only():
    slow, fast = _Constant(1.0), _Constant(2.0)
    split = acrobot_energy.Split(slow, fast, 8.0)
    states = np.zeros((4, 4))
    states[:, 3] = [0.0, -8.0, 7.9, 12.0]
    out = split.predict(states, np.array([0, 1, 2, 0]))
    np.testing.assert_array_equal(out[:, 0], [1.0, 2.0, 1.0, 2.0])
    assert slow.asked == [([0.0, 7.9], [0, 2])]
    assert fast.asked == [([-8.0, 12.0], [1, 0])]
    split.predict(states[:1], np.zeros(1, dtype=int))  # no fast rows: not asked
    assert len(fast.asked) == 1


@pytest.fixture(scope="module")
def run(tiny_swingup_run):
    out = tiny_swingup_run
    options = dict(
        trials=2, models=acrobot_energy.MODELS, identify=30, noise=0.2, fast=1.0,
        n_states=50, last=1, workers=1, progress=False,
    )  # fmt: skip
    with pytest.MonkeyPatch.context() as m:  # its workers' _STATE, not the module's
        m.setattr(acrobot_energy, "_STATE", {})
        return out, options, acrobot_energy.main(out, **options)


def _edited_copy(run_dir, tmp_path, edit):
    """A copy of the finished run ``run_dir`` as ``tmp_path / "run"``, with
    ``edit`` applied to its config.json (a dict edited in place)."""
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    config = json.loads((copy / "config.json").read_text())
    edit(config)
    (copy / "config.json").write_text(json.dumps(config))
    return copy


def _two_test_settings(config):
    config["test_masses"] = [[0.9, 1.1], [1.1, 0.9]]


def test_writes_promised_delivered_and_energy_per_model(run):
    out, options, results = run
    data = json.loads((out / "energy.json").read_text())
    assert data["models"] == list(acrobot_energy.MODELS)
    shape = (len(TINY.test_masses), options["trials"])
    for m in data["models"]:
        promised = np.array(data["promised_steps"][m])
        delivered = np.array(data["delivered_steps"][m])
        assert promised.shape == delivered.shape == shape
        assert np.all((promised >= 1) & (promised <= TINY.transfer.planning_max_steps))
        assert np.all((delivered >= 1) & (delivered <= TINY.transfer.max_steps))
    for m in acrobot_energy.LEARNED:
        for k in acrobot_energy.TERMS:
            assert np.array(data["energy_terms"][m][k]).shape == shape
        assert np.all(np.array(data["energy_terms"][m]["quadratic"]) > 0)
        assert np.array(data["band_rmse"][m]).shape == (7, 2)
        assert sum(data["band_kinetic_share"][m]) == pytest.approx(1.0)
        assert 0 <= data["elbow_wrap_kinetic_share"][m]["mean"] <= 1
    assert sum(data["band_share"]) == pytest.approx(1.0)
    distance = np.array(data["band_batch_distance"], dtype=float)
    assert distance.shape == (7,) and np.all(distance[np.isfinite(distance)] >= 0)
    assert np.isfinite(distance[0])  # slow states: every trial has some
    # the simulator's agent is its own reference
    assert "true" not in data["delivered_minus_true"]
    # the same seed, the same numbers
    # (but for "environment"'s git state: a working tree edited between the two
    # runs reads as another commit)
    first = json.loads((out / "energy.json").read_text())
    acrobot_energy.main(out, **options)
    again = json.loads((out / "energy.json").read_text())
    for written in (first, again):
        written["environment"].pop("git_commit")
    assert again == first
    np.testing.assert_array_equal(
        results.summary["delivered_steps"]["prior"], data["delivered_steps"]["prior"]
    )


def test_a_model_exact_everywhere_has_no_energy_error(run, tmp_path):
    """exact_slow with the band edge above every state is the simulator itself:
    every energy term and band error exactly 0, its plans the simulator's. (A
    swapped split, wrong actions for the true next state or the prior for the
    exact rows would show here; the smoke test above checks shapes.)"""
    out, options, _ = run
    summary = acrobot_energy.main(
        out, **{**options, "models": ("true", "exact_slow"), "fast": 1e6, "noise": None,
                "out": tmp_path / "e.json"},
    ).summary  # fmt: skip
    for k in acrobot_energy.TERMS:
        if k != "true_gain":
            np.testing.assert_array_equal(summary["energy_terms"]["exact_slow"][k], 0)
    rmse = np.array(summary["band_rmse"]["exact_slow"], dtype=float)
    assert np.all(rmse[np.isfinite(rmse)] == 0) and np.isfinite(rmse).any()
    np.testing.assert_array_equal(
        summary["promised_steps"]["exact_slow"], summary["promised_steps"]["true"]
    )


def test_promised_delivered_and_their_differences_are_in_steps(
    run, tmp_path, monkeypatch
):
    """promised: the mean steps of the last ``last`` planned episodes; delivered:
    the mean steps of the ``real`` real episodes; the differences are delivered
    minus promised, and a model's delivered minus the simulator's agent's (above
    0 is worse). The tiny run plans one episode, and every episode of it runs to
    the step limit, so first and last, or one model and another, would look
    alike: a copy of it plans three episodes, relabelled 1, 2, 3 steps, and its
    real episodes are cut to 10, 20, 30 steps for ``true`` and 40, 50, 60 for
    ``prior``. (``n_states`` above what the planner visited is accepted.)"""

    def three_planning_episodes(config):
        config["transfer"]["initial_planning_episodes"] = 3

    copy = _edited_copy(run[0], tmp_path, three_planning_episodes)
    planned, lengths = [], iter([10, 20, 30, 40, 50, 60])
    plan, run_episode = acrobot_energy._plan, acrobot_energy.run_episode

    def relabelled(*args):
        planned.append(plan(*args))
        return planned[-1]._replace(steps=np.arange(1.0, 4.0))

    def cut(*args, **kwargs):
        episode = run_episode(*args, **kwargs)
        return episode._replace(actions=np.zeros(next(lengths), dtype=np.int64))

    monkeypatch.setattr(acrobot_energy, "_plan", relabelled)
    monkeypatch.setattr(acrobot_energy, "run_episode", cut)
    summary = acrobot_energy.main(
        copy, models=("true", "prior"), trials=1, last=2, real=3, n_states=10**6,
        workers=1, progress=False, out=tmp_path / "e.json",
    ).summary  # fmt: skip
    assert [len(p.steps) for p in planned] == [3, 3]
    assert next(lengths, None) is None  # three real episodes per model
    for m, delivered in (("true", 20.0), ("prior", 50.0)):
        assert summary["promised_steps"][m] == [[2.5]]  # episodes 2 and 3
        assert summary["promised_steps_mean"][m]["mean"] == 2.5
        assert summary["delivered_steps"][m] == [[delivered]]
        assert summary["delivered_steps_mean"][m]["mean"] == delivered
        assert summary["delivered_minus_promised"][m]["mean"] == delivered - 2.5
    assert summary["delivered_minus_true"]["prior"]["mean"] == 30.0


def test_identified_beliefs_are_filtered_on_each_settings_transitions(
    run, tmp_path, monkeypatch
):
    """The beliefs handed to the trials, rebuilt from --seed: the prior updated
    on ``identify`` transitions of the setting's instance (not the prior), on a
    copy of the tiny run with two test settings (with one, every setting's
    belief would be setting 0's)."""

    import hipmdp
    from tasks.acrobot_swingup import run_test_instances
    from tasks.prediction import gather_split

    class Captured(Exception):
        pass

    def capture(fn, jobs, *, initargs, **kwargs):
        seen.extend(initargs[3])
        raise Captured

    seen = []
    monkeypatch.setattr(acrobot_energy, "pool_map", capture)
    out = _edited_copy(run[0], tmp_path, _two_test_settings)
    with pytest.raises(Captured):
        acrobot_energy.main(
            out, models=("true", "identified"), identify=30, last=1, seed=7,
            workers=1, progress=False, out=tmp_path / "e.json",
        )  # fmt: skip
    hip = hipmdp.load(out / "hipmdp_model.npz")
    settings = run_test_instances(json.loads((out / "config.json").read_text()))
    streams = np.random.SeedSequence(7).spawn(2)[1].spawn(len(settings))
    assert len(seen) == len(settings) == 2
    for belief, params, ss in zip(seen, settings, streams, strict=True):
        train = gather_split(ACROBOT, params, 30, 0, rng=np.random.default_rng(ss))
        want = hip.update(hip.prior(), train.train)
        np.testing.assert_array_equal(belief.h, want.h)
        np.testing.assert_array_equal(belief.P, want.P)
        assert not np.array_equal(belief.P, hip.prior().P)


def test_without_noise_there_is_no_noisy_model(run, tmp_path):
    out, options, _ = run
    summary = acrobot_energy.main(
        out, **{**options, "models": None, "noise": None, "out": tmp_path / "e.json"}
    ).summary
    assert summary["models"] == ["true", "average", "prior", "identified"]
    assert "noisy" not in summary["energy_terms"]


def test_rejects_bad_options(tmp_path, run):
    out = run[0]
    with pytest.raises(FileNotFoundError, match="has no config.json"):
        acrobot_energy.main(tmp_path)
    with pytest.raises(ValueError, match="trials: expected >= 1"):
        acrobot_energy.main(out, trials=0)
    with pytest.raises(ValueError, match="noise: expected a positive finite"):
        acrobot_energy.main(out, noise=-1.0)
    with pytest.raises(ValueError, match="last: expected <= the run's initial"):
        acrobot_energy.main(out, last=2)
    with pytest.raises(ValueError, match="models: expected 'true' and some of"):
        acrobot_energy.main(out, last=1, models=("average", "prior"))
    with pytest.raises(ValueError, match="models: expected 'true' and some of"):
        acrobot_energy.main(out, last=1, models=("true",))
    with pytest.raises(ValueError, match="fast: expected a positive finite"):
        acrobot_energy.main(out, last=1, fast=0.0)
    with pytest.raises(ValueError, match=r"unknown: exact, prior2"):
        acrobot_energy.main(out, last=1, models=("true", "prior2", "exact"))
    with pytest.raises(ValueError, match="states: expected >= 1"):
        acrobot_energy.main(out, last=1, n_states=0)
    with pytest.raises(ValueError, match="noise: expected a σ .* exactly when"):
        acrobot_energy.main(out, last=1, models=("true", "noisy"))
    with pytest.raises(ValueError, match="noise: expected a σ .* exactly when"):
        acrobot_energy.main(out, last=1, models=("true", "prior"), noise=0.1)
    # σ 0 is the simulator itself; infinite σ and --fast are no model; a count of
    # 0 would plan or average nothing (--last 0 would take every planned episode)
    for option, value in (("noise", 0.0), ("noise", np.inf), ("fast", np.inf)):
        with pytest.raises(ValueError, match=f"{option}: expected a positive finite"):
            acrobot_energy.main(out, last=1, **{option: value})
    for option in ("identify", "real", "last", "workers"):
        with pytest.raises(ValueError, match=f"{option}: expected >= 1"):
            acrobot_energy.main(out, **{"last": 1, option: 0})
    with pytest.raises(ValueError, match="seed: expected"):
        acrobot_energy.main(out, last=1, seed=-1)


def test_a_subset_of_models_gives_the_same_numbers_for_them(run, tmp_path):
    """Models do not share random streams: dropping some changes no other."""
    out, options, results = run
    models = ("exact_slow", "true", "noisy")
    subset = acrobot_energy.main(
        out, **{**options, "models": models, "out": tmp_path / "e.json"}
    ).summary
    assert subset["models"] == ["true", "noisy", "exact_slow"]
    for key in ("promised_steps", "delivered_steps"):
        for m in ("true", "noisy", "exact_slow"):
            np.testing.assert_array_equal(subset[key][m], results.summary[key][m])
    np.testing.assert_array_equal(
        subset["energy_terms"]["noisy"]["total"],
        results.summary["energy_terms"]["noisy"]["total"],
    )


def test_out_writes_the_named_file_and_leaves_the_default_alone(run, tmp_path):
    out, options, _ = run
    before = (out / "energy.json").read_text()
    path = tmp_path / "split.json"
    result = acrobot_energy.main(
        out, **{**options, "models": ("true", "exact_fast"), "noise": None, "out": path}
    )
    assert result.out == path
    assert json.loads(path.read_text())["models"] == ["true", "exact_fast"]
    assert (out / "energy.json").read_text() == before


def test_the_models_are_built_with_their_masses_columns_and_streams(run):
    import hipmdp
    from hipmdp import baselines
    from hipmdp.planning import LearnedModel

    out = run[0]
    hip = hipmdp.load(out / "hipmdp_model.npz")
    batch = hipmdp.Transitions.load(out / "batch.npz")
    average = baselines.batch_only(batch, rng=np.random.default_rng(0), n_max=50)
    acrobot_energy._init([(0.9, 1.1)], hip, average, [], {"fast": 5.0, "noise": 0.1})
    simulator = SimulatorModel(ACROBOT, PARAMS)
    ss_noise, ss_weights = np.random.SeedSequence(3).spawn(2)
    names = [m for m in acrobot_energy.MODELS if m not in ("true", "identified")]
    models = acrobot_energy._build_models(
        names, 0, PARAMS, simulator, ss_noise, ss_weights
    )
    assert models["prior_energy"]._params == PARAMS
    assert models["average_energy"]._params == PARAMS
    assert models["prior_energy_nominal"]._params == AcrobotParams()
    assert models["average_energy"]._model.model is average
    assert models["prior_energy"]._model.belief is not None
    want = acrobot_energy.SampledWeights(hip, np.random.default_rng(ss_weights))
    got = models["train_sampled"]
    for _ in range(20):  # a different stream matches 20 draws by chance rarely
        np.testing.assert_array_equal(got.draw().belief.mean, want.draw().belief.mean)
    # By their predictions, on states either side of the --fast 5 rad/s: the
    # simulator's on fast rows (all columns, or only the angles' or the
    # velocities'), the prior-mean model's elsewhere; exact_slow the reverse.
    states = _states(np.random.default_rng(7), 40)
    actions = np.random.default_rng(8).integers(3, size=40)
    fast = np.abs(states[:, 3]) >= 5.0
    assert 5 < fast.sum() < 35
    exact, prior = (
        simulator.predict(states, actions),
        models["prior"].predict(states, actions),
    )
    # every entry tells them apart, by far more than the round-off of the prior
    # model's batched algebra on a subset of rows (the tolerance below)
    assert np.abs(exact - prior).min() > 1e-6
    assert isinstance(models["prior"], LearnedModel)
    for name, rows, columns in (
        ("exact_fast", fast, slice(0, 4)),
        ("exact_slow", ~fast, slice(0, 4)),
        ("exact_fast_angles", fast, slice(0, 2)),
        ("exact_fast_velocities", fast, slice(2, 4)),
    ):
        want = prior.copy()
        want[np.ix_(rows, np.arange(4)[columns])] = exact[rows, columns]
        np.testing.assert_allclose(
            models[name].predict(states, actions), want, rtol=0, atol=1e-10,
            err_msg=name,
        )  # fmt: skip
    # noisy: the --noise σ, on the ss_noise stream
    states = _states(np.random.default_rng(8), 10)
    actions = np.zeros(10, dtype=int)
    want = acrobot_energy.NoisySimulator(
        simulator, 0.1, np.random.default_rng(ss_noise)
    )
    np.testing.assert_array_equal(
        models["noisy"].predict(states, actions), want.predict(states, actions)
    )


def test_each_setting_gets_its_own_identified_belief(run):
    import hipmdp

    hip = hipmdp.load(run[0] / "hipmdp_model.npz")
    beliefs = [hip.prior(), hip.prior()]
    acrobot_energy._init([PARAMS, PARAMS], hip, None, beliefs, {"fast": 5.0})
    simulator = SimulatorModel(ACROBOT, PARAMS)
    for setting, belief in enumerate(beliefs):
        models = acrobot_energy._build_models(
            ["identified"], setting, PARAMS, simulator, None, None
        )
        assert models["identified"].belief is belief


def test_cli_refuses_bad_input_as_usage_and_shows_later_errors_whole(
    run, monkeypatch, capsys
):
    """--last beyond the run's planning is checked against the run's config: a
    usage error (exit status 2). An error in the trials, after the inputs are
    checked, keeps its type and traceback."""
    out = str(run[0])
    with pytest.raises(SystemExit) as stopped:
        acrobot_energy.cli([out, "--last", "2", "--workers", "1"])
    assert stopped.value.code == 2
    assert "last: expected <= the run's initial" in capsys.readouterr().err

    def failing(*args, **kwargs):
        raise ValueError("a failure in the trials")

    monkeypatch.setattr(acrobot_energy, "pool_map", failing)
    with pytest.raises(ValueError, match="a failure in the trials"):
        acrobot_energy.cli([out, "--last", "1", "--workers", "1", "--trials", "1"])


class _Shifted:
    """A stand-in simulator: every next state is the state with θ̇₂ 10 rad/s
    higher (so the next states fall in other |θ̇₂| bands than the states)."""

    def __init__(self, domain, params):
        pass

    def predict(self, states, actions):
        return np.asarray(states, dtype=np.float64) + [0.0, 0.0, 0.0, 10.0]


def test_a_trial_uses_all_start_states_real_step_limits_and_visited_states(
    monkeypatch,
):
    """One trial of the simulator's agent, with real step limits (7) other than the
    planning's (5) and 3 start states. Planning is replaced by asking the model for
    three hand-picked states; each real episode applies no torque until the
    environment ends it: from the hanging start an unforced acrobot cannot reach
    the goal (its energy stays far below the goal's), so it runs to the real step
    limit. The batch distance is stood in for by θ₁, so the band medians show
    which states were banded: the visited ones, θ̇₂ 1, −1 and 3 rad/s (bands 0 and
    1), not their next states at 11, 9 and 13 (bands 8-10 and 10-14)."""
    from tasks.transfer import TransferConfig

    asked = []
    visited = np.array(
        [[0.1, 0.0, 0.0, 1.0], [0.2, 0.0, 0.0, -1.0], [0.6, 0.0, 0.0, 3.0]]
    )

    def planned(state, basis, model, task, starts, n_episodes, rng):
        asked.append((np.array(starts), task.max_steps))
        model.predict(visited, np.array([0, 1, 2]))
        steps = np.ones(n_episodes, dtype=np.int64)
        return acrobot_energy.PlanResult(state, steps, steps * 0.0, steps < 0)

    def unforced(env, basis, config, state, *, rng):
        time_step, n = env.reset(), 0
        while not time_step.last():
            time_step, n = env.step(1), n + 1  # ACTIONS[1] is 0 N·m
        return agents.Episode(state, None, np.zeros(n, dtype=np.int64), None, False)

    monkeypatch.setattr(acrobot_energy, "_plan", planned)
    monkeypatch.setattr(acrobot_energy, "run_episode", unforced)
    monkeypatch.setattr(acrobot_energy, "SimulatorModel", _Shifted)
    monkeypatch.setattr(
        acrobot_energy,
        "_build_models",
        lambda names, setting, params, simulator, *_: {
            "true": acrobot_energy._Recorder(simulator)
        },
    )
    transfer = TransferConfig(
        initial_planning_episodes=2, n_start_states=3, max_steps=7,
        planning_max_steps=5,
    )  # fmt: skip
    options = dict(
        transfer=transfer, models=["true"], last=1, real=2, n_states=100,
        batch_distance=lambda states: states[:, 0],
    )  # fmt: skip
    acrobot_energy._init([PARAMS], None, None, [], options)
    setting, trial, out = acrobot_energy._job((0, 1, (5, (0, 0))))
    assert (setting, trial) == (0, 1)
    ((starts, planning_max_steps),) = asked
    assert starts.shape == (3, 4)
    assert len({tuple(s) for s in starts}) == 3  # three resets, not one
    assert planning_max_steps == 5
    assert out["delivered"]["true"] == 7.0
    np.testing.assert_allclose(out["batch_distance"][:2], [0.15, 0.6])
    assert np.all(np.isnan(out["batch_distance"][2:]))


def _two_settings_with_made_up_trials(run, tmp_path, monkeypatch):
    """A copy of the tiny run with a second test setting, whose trials are made
    up: trial ``j = 2 i + t`` (setting ``i``, trial ``t``) promises ``10 + j``
    steps to ``true`` and ``20 + j`` to ``prior``, delivers ``30 + j`` and
    ``40 + j``, has all its states in band ``j``, all its ½ εᵀ M ε in band
    ``j + 1`` and a share ``j / 10`` of its steps at the elbow's wrap. The
    models: true and prior; two trials per setting."""

    copy = _edited_copy(run[0], tmp_path, _two_test_settings)

    def trial(j):
        terms = dict.fromkeys(acrobot_energy.TERMS, 0.0)
        bands = {
            "share": np.eye(7)[j],
            "rmse": np.ones((7, 2)),
            "kinetic_share": np.eye(7)[j + 1],
            "wrap_share": j / 10,
            "wrap_kinetic_share": 0.5,
        }
        return {
            "promised": {"true": 10.0 + j, "prior": 20.0 + j},
            "delivered": {"true": 30.0 + j, "prior": 40.0 + j},
            "energy": {"prior": terms},
            "bands": {"prior": bands},
            "batch_distance": np.ones(7),
        }

    def made_up(fn, jobs, **kwargs):
        return [(i, t, trial(2 * i + t)) for i, t, _ in jobs]

    monkeypatch.setattr(acrobot_energy, "pool_map", made_up)
    return copy


def test_the_banded_and_wrap_shares_are_averaged_over_settings_and_trials(
    run, tmp_path, monkeypatch
):
    """Trials 0-3 put their states in bands 0-3 and their ½ εᵀ M ε in bands 1-4,
    with 0, 0.1, 0.2, 0.3 of their steps at the wrap: the summary's shares are the
    means over all four, a quarter in each band, and 0.15."""
    copy = _two_settings_with_made_up_trials(run, tmp_path, monkeypatch)
    summary = acrobot_energy.main(
        copy, models=("true", "prior"), trials=2, last=1, workers=1,
        progress=False, out=tmp_path / "e.json",
    ).summary  # fmt: skip
    np.testing.assert_allclose(summary["band_share"], [0.25] * 4 + [0] * 3)
    np.testing.assert_allclose(
        summary["band_kinetic_share"]["prior"], [0] + [0.25] * 4 + [0] * 2
    )
    assert summary["elbow_wrap_share"] == pytest.approx(0.15)


def test_cli_prints_promised_and_delivered_over_every_settings_trials(
    run, tmp_path, monkeypatch, capsys
):
    """Two settings of two trials: the means are over 4 trials; true promised
    10-13 steps (mean 11.5) and delivered 30-33 (31.5), prior 20-23 (21.5) and
    40-43 (41.5), 10 more than true's."""
    copy = _two_settings_with_made_up_trials(run, tmp_path, monkeypatch)
    assert acrobot_energy.cli(
        [str(copy), "--models", "true", "prior", "--trials", "2", "--last", "1",
         "--workers", "1", "--no-progress", "--out", str(tmp_path / "e.json")]
    ) == 0  # fmt: skip
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "steps to the goal, mean [95% interval] over 4 trials"
    assert lines[1].split()[:3] == ["model", "promised", "delivered"]
    rows = {line.split()[0]: line.split() for line in lines[2:4]}
    # model, promised mean, [low, high], delivered mean, [low, high], difference
    assert rows["true"][1] == "11.5" and rows["true"][4] == "31.5"
    assert rows["prior"][1] == "21.5" and rows["prior"][4] == "41.5"
    assert rows["prior"][7] == "+10"
    assert len(rows["true"]) == 7  # no difference for the simulator's own agent
