"""The benchmarks run, compare the right things, and report what they say.

No timing here (speed lives in ``benchmarks/``): `benchmarks.timing`'s statistics
are checked on a stand-in clock and stand-in measurements with hand-worked medians
and ratios; each script's agreement check is run at tiny sizes, and, with one side
made wrong by a little (far beyond the check's tolerance, far below anything a
reader of the printed figures would notice), must raise naming that comparison.
"""

from __future__ import annotations

import concurrent.futures as cf
from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks import control, generate, model, sampler, simulation, timing
from hipmdp import gibbs_dense, gibbs_eigen
from hipmdp.baselines import GPBaseline
from hipmdp.fitting import FitConfig
from hipmdp.model import HipMDP

OFF = 1 + 1e-7  # "off by a little": 100x the checks' relative 1e-9

# --- benchmarks.timing -------------------------------------------------------


class Clock:
    """A stand-in for `time.perf_counter`: it moves only when a stand-in call
    says it took so long."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now

    def taking(self, durations):
        """A call that advances the clock by the next of ``durations``."""
        left = list(durations)
        return lambda: setattr(self, "now", self.now + left.pop(0))


@pytest.mark.parametrize(
    "durations, median",
    [([5.0], 5.0), ([1.0, 6.0, 2.0], 2.0), ([1.0, 2.0, 4.0, 10.0], 3.0)],
)
def test_seconds_is_the_median_of_n_calls(monkeypatch, durations, median):
    """Hand-worked: the means would be 5, 3 and 4.25; a single call is itself."""
    clock = Clock()
    # timing's own `time`, not the time module everyone shares
    monkeypatch.setattr(timing, "time", SimpleNamespace(perf_counter=clock))
    assert timing.seconds(clock.taking(durations), len(durations)) == median


def test_paired_alternates_the_order_and_keeps_repeats_paired():
    """Three sides, four repeats: a b c, c b a, a b c, c b a after one warm-up
    of each; each side's values are in repeat order, so that a[i] / b[i] were
    measured in the same repeat. The value returned is the call's position."""
    log: list[str] = []

    def side(name):
        return lambda: (log.append(name), len(log) - 1)[1]

    out = timing.paired(
        {name: side(name) for name in "abc"},
        4,
        warm_up={name: side("warm " + name) for name in "abc"},
    )
    assert log == ["warm a", "warm b", "warm c", *"abccbaabccba"]
    np.testing.assert_array_equal(out["a"], [3, 8, 9, 14])
    np.testing.assert_array_equal(out["b"], [4, 7, 10, 13])
    np.testing.assert_array_equal(out["c"], [5, 6, 11, 12])
    assert all(v.dtype == float and v.shape == (4,) for v in out.values())


def test_paired_without_warm_up_and_bad_repeats():
    calls = []
    out = timing.paired({"a": lambda: calls.append(1) or 2.5}, 1)
    assert calls == [1] and out["a"].tolist() == [2.5]
    with pytest.raises(ValueError, match="repeats"):
        timing.paired({"a": lambda: 1.0}, 0)


def test_ratio_text_is_the_median_of_the_paired_ratios():
    """num / den = 2, 3, 10: the median is 3 (the mean 5; the ratio of the
    medians 9 / 1 = 9; den / num would be 0.33)."""
    assert timing.ratio_text([2.0, 9.0, 10.0], [1.0, 3.0, 1.0]) == "3.00x (2.00-10.00)"


@pytest.mark.parametrize(
    "num, den, digits, text",
    [
        ([6.0], [2.0], None, "3.00x"),  # one repeat: no range
        ([9.99], [1.0], None, "9.99x"),
        ([10.0], [1.0], None, "10.0x"),  # 1 digit from 10 on
        ([99.94], [1.0], None, "99.9x"),
        ([100.0], [1.0], None, "100x"),  # none from 100 on
        ([1234.4, 1000.0], [1.0, 2.0], None, "867x (500-1,234)"),
        ([12345.0], [1.0], None, "12,345x"),
        ([3.0, 1.0], [1.0, 1.0], 0, "2x (1-3)"),
        ([1.0], [3.0], 4, "0.3333x"),
    ],
)
def test_ratio_text_digits_and_separators(num, den, digits, text):
    assert timing.ratio_text(np.array(num), np.array(den), digits) == text


# --- the relative 1e-9 comparisons of sampler and model ----------------------


@pytest.mark.parametrize("close", [sampler.close, model.close])
def test_close_is_relative_1e9_with_zeros_relative_to_the_largest(close):
    """want = (1000, 0): allowed |got - want| = 1e-9·1000 + 1e-9·|want|, i.e.
    2e-6 at 1000 and 1e-6 at the zero."""
    want = np.array([1000.0, 0.0])
    close(want + [1.5e-6, 0.9e-6], want, "inside")
    for off in ([3e-6, 0.0], [0.0, 2e-6]):
        with pytest.raises(AssertionError, match="outside"):
            close(want + off, want, "outside")


# --- benchmarks.sampler ------------------------------------------------------

M = 20  # support points: the dense side at m = 20 takes milliseconds


def test_sampler_sweeps_check_and_fields(monkeypatch):
    """`sweeps` checks the dense sweep against the structured one, and puts each
    side's measurements in its own field: with `seconds` replaced by a stand-in
    that reports 1 for a structured sweep at N_w = 1000, 2 at N_w = 4 and 30 for
    the dense one (told apart by the priors `gibbs_sweep` was called with)."""
    seen: list[int] = []
    real = sampler.gibbs_sweep

    def spy(state, data, priors, cache, *, rng):
        seen.append(priors.n_w)
        return real(state, data, priors, cache, rng=rng)

    def fake_seconds(fn, n=1):
        seen.clear()
        fn()
        return {(1000,): 1.0, (4,): 2.0, (): 30.0}[tuple(seen)]

    monkeypatch.setattr(sampler, "gibbs_sweep", spy)
    monkeypatch.setattr(sampler, "seconds", fake_seconds)
    sw = sampler.sweeps(M, with_dense=True, repeats=2)
    assert sw.n_features >= 1
    assert sw.fast_1000.tolist() == [1.0, 1.0]
    assert sw.fast_4.tolist() == [2.0, 2.0]
    assert sw.dense_4.tolist() == [30.0, 30.0]
    assert np.isnan(sampler.sweeps(M, with_dense=False, repeats=1).dense_4).all()


@pytest.mark.parametrize(
    "part, what", [(0, "sweep z"), (1, "sweep w"), (2, "sweep f"), (3, "sweep mu_w")]
)
def test_sampler_sweep_check_raises_when_the_dense_side_is_off(monkeypatch, part, what):
    """The second `sweep` of `check_sweeps` is the dense one: one of its outputs
    off by a little (z: one decision flipped) fails that comparison."""
    data = sampler.synthetic(M, rng=np.random.default_rng(0))
    cache = sampler.prepare(data)
    state = sampler.warm_state(data, sampler.priors_at(1000), cache)
    priors = sampler.priors_at(4)
    sampler.check_sweeps(state, data, priors, cache)  # agrees as it is
    real, calls = sampler.sweep, []

    def off_on_second(*args, **kwargs):
        out = list(real(*args, **kwargs))
        calls.append(1)
        if len(calls) == 2:
            if part == 0:
                out[0] = out[0].copy()
                out[0].flat[0] = not out[0].flat[0]
            else:
                out[part] = out[part] * OFF
        return tuple(out)

    monkeypatch.setattr(sampler, "sweep", off_on_second)
    with pytest.raises(AssertionError, match=what):
        sampler.check_sweeps(state, data, priors, cache)
    calls.clear()  # and `sweeps` checks before it times
    with pytest.raises(AssertionError, match=what):
        sampler.sweeps(M, with_dense=True, repeats=1)


def test_sampler_conditionals_check_and_ratio_direction(monkeypatch, capsys):
    """The four conditionals agree at m = 20 and the printed ratio is dense over
    structured: with a stand-in `seconds` giving 1e-3 s for a structured call (the
    median of 5) and 1 s for a dense one, 1,000x, and 1,000,000x for the new
    feature (1000 draws per structured call)."""
    monkeypatch.setattr(
        sampler, "seconds", lambda fn, n=1: (fn(), 1e-3 if n == 5 else 1.0)[1]
    )
    sampler.conditionals(M, 1)
    lines = capsys.readouterr().out.splitlines()
    ratios = {line[:30].strip(): line.split()[-1] for line in lines if "  " in line}
    assert ratios["f-block, one row (k=3)"] == "1,000x"
    assert ratios["z decision (one k, r)"] == "1,000x"
    assert ratios["new feature, per weight draw"] == "1,000,000x"
    assert ratios["w-block (all instances)"] == "1,000x"


def _off(fn, change):
    return lambda *args, **kwargs: change(fn(*args, **kwargs))


def _mean_off(g):
    return g._replace(mean=g.mean * OFF)


def _cov_off(g):
    return g._replace(cov=g.cov * OFF)


@pytest.mark.parametrize(
    "module, name, change, what",
    [
        (gibbs_dense, "f_posterior", _mean_off, "f-block mean"),
        (gibbs_dense, "f_posterior", _cov_off, "f-block cov"),
        (gibbs_eigen, "z_llr", lambda x: x * OFF, "z decision"),
        (gibbs_dense, "marginal_llr", lambda x: x * OFF, "z decision"),
        (gibbs_eigen, "new_llr", lambda x: x * OFF, "new feature"),
        (gibbs_dense, "w_posterior", _mean_off, "w-block mean"),
        (gibbs_eigen, "w_posterior", lambda p: (p[0], p[1] * OFF), "w-block cov"),
    ],
)
def test_sampler_conditional_checks_raise_when_a_side_is_off(
    monkeypatch, module, name, change, what
):
    monkeypatch.setattr(module, name, _off(getattr(module, name), change))
    with pytest.raises(AssertionError, match=what):
        sampler.conditionals(M, 1)


# --- benchmarks.model --------------------------------------------------------

SMALL = ["--small", "--sweeps", "3", "--chains", "1", "--repeats", "1"]


def test_model_runs_small(capsys):
    """--small's sizes are what its comment says: 300 transitions per instance,
    m = 30, 50 filter transitions, 1,000 batched states; --sweeps and --chains
    are taken as given."""
    model.main(SMALL)
    out = capsys.readouterr().out
    assert "B=7 instances x 300 transitions" in out
    assert "m=30, 3 sweeps x 1 chains; 50 filter transitions" in out
    assert out.count("(1000 states, ") == 3


class Stop(Exception):
    pass


def test_model_full_size_is_the_papers_scale(monkeypatch, capsys):
    """Without --small: 7 x 6,000 transitions, m = 750, 250 sweeps, FitConfig's
    chains and its 1,000 transitions per action for the hyperparameters (the
    run stops at its first stage)."""
    seen = {}

    def first_stage(states, actions, deltas, instances, n_actions, **kwargs):
        seen.update(n=len(states), n_subsample=kwargs["n_subsample"])
        raise Stop

    monkeypatch.setattr(model, "fit_hyper_set", first_stage)
    with pytest.raises(Stop):
        model.main([])
    out = capsys.readouterr().out
    assert "B=7 instances x 6000 transitions" in out
    assert f"m=750, 250 sweeps x {FitConfig.n_chains} chains; 200 filter" in out
    assert seen == dict(n=7 * 6000, n_subsample=1000)


def _off_when(batched: bool):
    """A mean made off by a little, only for batched calls (more than one state)
    or only for single states."""

    def change(mean, states):
        return mean * OFF if (len(states) > 1) == batched else mean

    return change


@pytest.mark.parametrize(
    "side, batched, what",
    [
        ("predict_mean", False, "single-state means"),
        ("mean_predictor", False, "single-state means"),
        ("predict_mean", True, "batched predict_mean"),
        ("mean_predictor", True, "batched mean_predictor"),
        ("predict", True, "batched predict_mean"),
    ],
)
def test_model_checks_raise_when_a_side_is_off(monkeypatch, side, batched, what):
    change = _off_when(batched)
    real = getattr(HipMDP, side)
    if side == "predict_mean":

        def wrong(self, states, actions, belief):
            return change(real(self, states, actions, belief), states)
    elif side == "mean_predictor":

        def wrong(self, belief):
            fused = real(self, belief)
            return lambda states, actions: change(fused(states, actions), states)
    else:

        def wrong(self, states, actions, belief):
            mean, var = real(self, states, actions, belief)
            return change(mean, states), var

    monkeypatch.setattr(HipMDP, side, wrong)
    with pytest.raises(AssertionError, match=what):
        model.main(SMALL)


# --- benchmarks.control ------------------------------------------------------

TINY = [
    "--episodes", "1", "--raw-steps", "10", "--plan-episodes", "1",
    "--model-steps", "5", "--parallel", "2", "--gp-size", "20",
    "--repeats", "1", "--no-progress",
]  # fmt: skip


def test_control_runs_tiny():
    rates = control.main(TINY)
    assert len(rates) == 8 and all(r > 0 for r in rates.values())


def _plus_1e6(mean):
    return mean + 1e-6


@pytest.mark.parametrize(
    "owner, side, change, what",
    [
        # predict off: the first side compared with it, predict_mean, is named
        (control.FullPredict, "predict", lambda mv: (_plus_1e6(mv[0]), mv[1]),
         "predict_mean"),
        (control.MeanOnly, "predict_mean", _plus_1e6, "predict_mean"),
        (GPBaseline, "mean_predictor", lambda f: _off(f, _plus_1e6), "mean_predictor"),
    ],
    ids=["predict", "predict_mean", "mean_predictor"],
)  # fmt: skip
def test_control_check_raises_when_a_gp_side_is_off(
    monkeypatch, owner, side, change, what
):
    """One GP row's means off by 1e-6 (absolute; the allowed round-off is at
    most 1e-13 σ_f²‖α‖₁, ~1e-10 here, or 1e-9 of the mean)."""
    monkeypatch.setattr(owner, side, _off(getattr(owner, side), change))
    with pytest.raises(AssertionError, match=f"^{what}: predictions differ"):
        control.main(TINY)


def _stand_in_gp():
    """A = 2 actions, D = 2 dimensions; σ_f²‖α‖₁ = [[8, 0 (no data)], [2, 1e6]]
    (the largest σ_f²|α_j| would give 6e5 for the last)."""

    def post(signal_var, alpha):
        return SimpleNamespace(
            hyper=SimpleNamespace(signal_var=signal_var), alpha=np.array(alpha)
        )

    return SimpleNamespace(
        posteriors=[
            [post(2.0, [3.0, -1.0]), None],
            [post(0.5, [1.0, 1.0, -2.0]), post(2.0, [2e5, -3e5])],
        ]
    )


# three states, actions 0, 1, 1; the allowed error per entry, hand-worked as
# max(1e-13 · scale[a], 1e-9 · |want|):
WANT = np.array([[1.0, 1.0], [1.0, 2.0], [-3.0, 0.5]])
ALLOWED = np.array([[1e-9, 1e-9], [1e-9, 1e-7], [3e-9, 1e-7]])


@pytest.mark.parametrize("name", ["predict_mean", "mean_predictor"])
@pytest.mark.parametrize("entry", [(1, 1), (2, 0), (0, 1)])
def test_control_check_tolerance_is_as_documented(name, entry):
    """At 0.8 of the allowed error everywhere the check passes; at 1.25 of it in
    one entry (one in the σ_f²‖α‖₁ branch, two in the 1e-9 |mean| one) it fails,
    naming the side, the entry and the error."""
    data = SimpleNamespace(states=np.zeros((3, 2)), actions=np.array([0, 1, 1]))

    def predicts(mean):
        return SimpleNamespace(predict=lambda s, a: mean)

    def models(err):
        return {
            "predict (mean+var)": predicts(WANT),
            "predict_mean": predicts(WANT + (err if name == "predict_mean" else 0)),
            "mean_predictor": predicts(WANT + (err if name != "predict_mean" else 0)),
        }

    control.check_same_predictions(_stand_in_gp(), models(0.8 * ALLOWED), data)
    err = np.zeros_like(WANT)
    err[entry] = -1.25 * ALLOWED[entry]
    i, j, allowed = *entry, ALLOWED[entry]
    message = (
        rf"^{name}: predictions differ from predict's by {1.25 * allowed:.3e} at "
        rf"\((np\.int64\()?{i}\)?, (np\.int64\()?{j}\)?\), allowed {allowed:.3e}$"
    )
    with pytest.raises(AssertionError, match=message):
        control.check_same_predictions(_stand_in_gp(), models(err), data)


# --- benchmarks.simulation and benchmarks.generate ---------------------------


@pytest.mark.parametrize("name", ["acrobot", "cartpole"])
def test_simulation_check_passes_on_the_environments(name):
    """The raw side is the environment's physics, bit for bit, over 60 steps:
    more than one cart-pole episode under random actions, so a reset is
    crossed."""
    factory, module = simulation.DOMAINS[name]
    env = factory(seed=0)
    simulation.check_same_physics(env, module, 60, np.random.default_rng(0))


@pytest.mark.parametrize(
    "change",
    [
        # 1 - 1e-9 rather than 1 + 1e-9: the actuator clips controls to [-1, 1]
        lambda m: {"ACTIONS": m.ACTIONS * (1 - 1e-9)},
        lambda m: {"ACTIONS": m.ACTIONS[::-1]},
        lambda m: {"N_SUB_STEPS": m.N_SUB_STEPS + 1},
        lambda m: {"N_SUB_STEPS": m.N_SUB_STEPS - 1},
    ],
    ids=["control 1e-9 off", "table reversed", "one sub-step more", "one fewer"],
)
def test_simulation_check_fails_when_the_raw_side_is_other_physics(change):
    """A raw side whose controls are off by a relative 1e-9, whose action table
    is reversed, or that takes one sub-step more or fewer than the environment
    is refused at the first step (the seed's first action is 2, control +1)."""
    env = simulation.DOMAINS["acrobot"][0](seed=0)
    m = simulation.acrobot
    other = SimpleNamespace(
        __name__="tasks.acrobot", ACTIONS=m.ACTIONS, N_SUB_STEPS=m.N_SUB_STEPS
    )
    vars(other).update(change(m))
    message = r"^tasks\.acrobot: env\.step and raw mj_step differ in q(pos|vel) after "
    with pytest.raises(AssertionError, match=message + r"step 1 \(action 2\)"):
        simulation.check_same_physics(env, other, 5, np.random.default_rng(0))


def test_simulation_checks_before_timing(monkeypatch):
    """main runs the check on each domain before any timing of it: a failing
    check stops the run with nothing timed."""

    def refuse(env, module, n_steps, rng):
        raise AssertionError(f"{module.__name__} checked over {n_steps} steps")

    def timed(*args):
        raise RuntimeError("timed before the check")

    monkeypatch.setattr(simulation, "check_same_physics", refuse)
    monkeypatch.setattr(simulation, "paired_rates", timed)
    with pytest.raises(AssertionError, match=r"^tasks\.acrobot checked over 7 steps$"):
        simulation.main(["--steps", "7", "--repeats", "1"])


def test_simulation_prints_env_over_raw(monkeypatch, capsys):
    """The printed ratio is env / raw (the fraction of raw speed kept): with
    stand-in rates of 200 (raw) and 50 (env) control steps/s, 0.25."""
    monkeypatch.setattr(simulation, "raw_steps_per_second", lambda *a: 200.0)
    monkeypatch.setattr(simulation, "env_steps_per_second", lambda *a: 50.0)
    simulation.main(["--steps", "3", "--repeats", "2"])
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[2:]]
    assert [r[0] for r in rows] == ["acrobot", "cartpole"]
    for name, n_sub, raw_mj, raw, env, ratio, spread in rows:
        assert int(n_sub) == simulation.DOMAINS[name][1].N_SUB_STEPS
        assert (float(raw_mj), float(raw), float(env)) == (200.0 * int(n_sub), 200, 50)
        assert (ratio, spread) == ("0.25", "0.25-0.25")


def test_simulation_runs_tiny(capsys):
    simulation.main(["--steps", "5", "--repeats", "1"])
    assert len(capsys.readouterr().out.splitlines()) == 4


def _done(value):
    future = cf.Future()
    future.set_result(value)
    return future


def test_generate_shard_check():
    """Two sides that give the same output pass; one byte of one archive
    changed is refused, naming the shard, the policy and both sides."""
    job = generate.jobs(
        SimpleNamespace(domain="acrobot", instances=1, episodes=1, max_steps=5),
        "open-loop",
        1,
        first=3,
    )[0]
    want = generate.generate.run_shard(job)
    other = want._replace(data=want.data[:-1] + bytes([want.data[-1] ^ 1]))
    same = {side: lambda job: _done(want) for side in ("a", "b")}
    generate.check_same_shards([job], same)
    with pytest.raises(AssertionError, match=r"^shard 3 \(open-loop\): b and a differ"):
        generate.check_same_shards(
            [job], {"a": lambda job: _done(want), "b": lambda job: _done(other)}
        )


def test_generate_bookkeeping_and_tiny_run(tmp_path, capsys, monkeypatch):
    """The tiny run checks one open-loop shard in this process against the
    pool, before timing (the check itself runs, on the real pool), then prints
    the bookkeeping for --run-instances."""
    book = generate.bookkeeping(40, 16, 2, str(tmp_path))
    assert book["shards"] == 3  # 40 instances in shards of 16
    assert book["manifest_bytes"] > 0 and book["manifest"] > 0 < book["progress"]
    checked, check = [], generate.check_same_shards
    timed = generate.shard_rate

    def spy(batch, submits):
        checked.append(([(job.policy, job.instances) for job in batch], [*submits]))
        check(batch, submits)

    def after_check(batch, submit):
        assert checked, "timed before the check"
        return timed(batch, submit)

    monkeypatch.setattr(generate, "check_same_shards", spy)
    monkeypatch.setattr(generate, "shard_rate", after_check)
    generate.main(
        ["--instances", "1", "--episodes", "1", "--max-steps", "5",
         "--raw-steps", "10", "--repeats", "1", "--run-instances", "32",
         "--dir", str(tmp_path)]
    )  # fmt: skip
    assert checked == [([("open-loop", (2000,))], ["in process", "in the pool"])]
    out = capsys.readouterr().out
    # --run-instances 32 in shards of --instances 1
    assert "a run of 32 instances in 32 shards of 1" in out
    assert "  ratio " in out
