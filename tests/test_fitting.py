"""The fitting pipeline's fast steps against plain dense formulas: GP smoothing of
each instance's transitions onto the support points, and the training instances'
posterior weights."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from hipmdp import FitConfig, fit, fitting
from hipmdp import gibbs_dense as dense
from hipmdp.data import Transitions
from hipmdp.fitting import (
    MAX_MAGNITUDE,
    check_batch,
    posterior_weights,
    smooth_onto_support,
)
from hipmdp.gibbs import ChainResult, GibbsPriors, GibbsState
from hipmdp.gp import HyperSet, subsample


def _dense_gp_mean(X, y, Xs, ell, sf2, sn2):
    """k(X*, X) (K + σ²I)⁻¹ y with k = σ_f² exp(−½ Σ_j ((x_j − x'_j)/ℓ_j)²)."""

    def k(P, Q):
        r2 = (((P[:, None, :] - Q[None, :, :]) / ell) ** 2).sum(axis=-1)
        return sf2 * np.exp(-0.5 * r2)

    return k(Xs, X) @ np.linalg.solve(k(X, X) + sn2 * np.eye(len(X)), y)


def _batch(rng, B=3, A=2, D=3, n=40):
    S = rng.uniform(-1, 1, size=(B * n, D))
    return Transitions(
        S,
        rng.integers(0, A, size=B * n),
        S + 0.3 * np.sin(S) + 0.05 * rng.normal(size=S.shape),
        np.repeat(np.arange(B) * 2 + 1, n),  # ids 1, 3, 5: not positions
    )


def _hyper(rng, A=2, D=3):
    return HyperSet(
        lengthscales=rng.uniform(0.5, 2.0, size=(A, D, D)),
        signal_var=rng.uniform(0.1, 1.0, size=(A, D)),
        noise_var=rng.uniform(1e-3, 1e-2, size=(A, D)),
    )


def test_smoothing_matches_a_dense_solve_per_instance_action_and_dimension():
    rng = np.random.default_rng(0)
    data, hyper = _batch(rng), _hyper(rng)
    support = rng.uniform(-1, 1, size=(7, 3))
    for n_smooth in (1000, 8):  # every transition, then a subsample per cell
        Y = smooth_onto_support(
            data, support, hyper, n_smooth=n_smooth, rng=np.random.default_rng(1)
        )
        assert Y.shape == (2, 3, 3, 7)
        sub_rng = np.random.default_rng(1)  # the subsamples, drawn in the same order
        cut = 0
        for bi, b in enumerate(data.instance_ids):
            for a in range(2):
                cell = np.flatnonzero((data.instances == b) & (data.actions == a))
                idx = cell[subsample(len(cell), n_smooth, rng=sub_rng)]
                cut += len(idx) < len(cell)
                for d in range(3):
                    ref = _dense_gp_mean(
                        data.states[idx],
                        data.deltas[idx, d],
                        support,
                        hyper.lengthscales[a, d],
                        hyper.signal_var[a, d],
                        hyper.noise_var[a, d],
                    )
                    np.testing.assert_allclose(Y[a, d, bi], ref, rtol=1e-8, atol=1e-12)
        assert cut == (0 if n_smooth == 1000 else 6)  # subsampled every cell, or none


def test_posterior_weights_match_the_dense_w_posterior_mean():
    rng = np.random.default_rng(2)
    K, R, B, m = 4, 5, 6, 8
    z = rng.random((K, R)) < 0.6
    z[0] = True
    f = rng.normal(size=(K, R, m)) * z[:, :, None]
    Y = rng.normal(size=(R, B, m))
    noise = rng.uniform(0.05, 0.3, size=R)
    mu_w = rng.normal(size=K)
    W = posterior_weights(Y, f, z, noise, mu_w, 0.7)
    ref = dense.w_posterior(z, f, Y, noise, mu_w, 0.7)
    np.testing.assert_array_equal(W[0], 1.0)
    np.testing.assert_allclose(W[1:], ref.mean, rtol=1e-10, atol=1e-12)
    # f where z is off is not part of the model: the weights ignore it
    junk = np.where(z[:, :, None], f, rng.normal(size=f.shape))
    np.testing.assert_array_equal(posterior_weights(Y, junk, z, noise, mu_w, 0.7), W)


def test_data_at_the_magnitude_limit_fit_without_overflow():
    data = _batch(np.random.default_rng(0))
    scale = MAX_MAGNITUDE / np.abs(np.r_[data.states, data.next_states]).max()
    big = Transitions(
        data.states * scale, data.actions, data.next_states * scale, data.instances
    )
    config = FitConfig(n_support=20, n_sweeps=2, n_chains=1, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow warns before it shows
        model = fit(big, config, rng=np.random.default_rng(1))
    assert np.all(np.isfinite(model.f)) and np.all(np.isfinite(model.weights))


def test_fit_shows_a_bar_per_stage_when_asked(capsys):
    """Every stage that takes a while has a bar (the hyperparameters had none:
    seconds of silence before the first), and none without ``progress``; the
    bars change nothing."""
    data = _batch(np.random.default_rng(0))
    config = FitConfig(n_support=20, n_sweeps=2, n_chains=1)
    shown = fit(data, config, rng=np.random.default_rng(1))
    err = capsys.readouterr().err
    for stage in ("hyperparameters", "support points", "smoothing", "gibbs"):
        assert f"{stage}:" in err
    assert "hyperparameters: 100%" in err and "| 6/6 " in err  # A × D fits
    quiet = fit(
        data, dataclasses.replace(config, progress=False), rng=np.random.default_rng(1)
    )
    assert capsys.readouterr().err == ""
    np.testing.assert_array_equal(shown.f, quiet.f)
    np.testing.assert_array_equal(shown.hyper.lengthscales, quiet.hyper.lengthscales)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"n_smooth": 0}, "n_smooth: expected >= 1"),  # was Y = 0 everywhere
        ({"n_smooth": -1}, "n_smooth: expected >= 1"),
        ({"hyper": 1}, r"hyper: expected 2 actions .* got 1 and 3"),  # dropped a
        ({"support": np.zeros((7, 2))}, r"support: expected .* \(m, 3\)"),
        ({"support": np.full((7, 3), np.nan)}, "support: expected finite"),
        ({"rng": 1}, "rng: expected a numpy Generator"),
        ({"data": "empty cell"}, r"action 1 has no transitions in instances \[3\]"),
    ],
)
def test_smoothing_refuses_what_it_would_fill_with_zeros(change, match):
    rng = np.random.default_rng(0)
    data, hyper = _batch(rng), _hyper(rng)
    args = {"data": data, "support": rng.uniform(-1, 1, size=(7, 3)),
            "hyper": hyper, "n_smooth": 10,
            "rng": np.random.default_rng(1)}  # fmt: skip
    args |= change
    if change.get("hyper") == 1:
        args["hyper"] = HyperSet(
            hyper.lengthscales[:1], hyper.signal_var[:1], hyper.noise_var[:1]
        )
    if change.get("data") == "empty cell":
        keep = ~((data.instances == 3) & (data.actions == 1))
        args["data"] = Transitions(
            data.states[keep], data.actions[keep], data.next_states[keep],
            data.instances[keep],
        )  # fmt: skip
    with pytest.raises(ValueError, match=match):
        smooth_onto_support(
            args.pop("data"), args.pop("support"), args.pop("hyper"), **args
        )


@pytest.mark.parametrize(
    ("name", "bad", "match"),
    [
        ("Y", np.zeros((5, 6, 1)), r"Y: expected shape \(5, 6, 8\)"),  # broadcast
        ("Y", np.zeros((5, 6)), r"Y: expected shape \(5, 'B', 8\)"),
        ("z", np.ones((4, 4), bool), r"z: expected shape \(4, 5\)"),
        ("noise", np.ones(4), r"noise: expected shape \(5,\)"),
        ("mu_w", np.zeros(3), r"mu_w: expected shape \(4,\)"),  # blamed F
    ],
)
def test_posterior_weights_refuse_mismatched_shapes(name, bad, match):
    K, R, B, m = 4, 5, 6, 8
    args = {"Y": np.zeros((R, B, m)), "f": np.zeros((K, R, m)),
            "z": np.ones((K, R), bool), "noise": np.ones(R),
            "mu_w": np.zeros(K)}  # fmt: skip
    args[name] = bad
    with pytest.raises(ValueError, match=match):
        posterior_weights(**args, sigma_w=0.7)


def test_check_batch_counts_distinct_states_for_the_support():
    """A batch holding each state twice has as many distinct states as once:
    n_support may equal that number, not exceed it."""
    data = _batch(np.random.default_rng(0))
    twice = Transitions.concatenate([data, data])
    n = len(data)  # 120 distinct states, 240 transitions
    check_batch(twice, FitConfig(n_support=n, n_candidates=n))
    with pytest.raises(ValueError, match=f"at most {n} \\(distinct states"):
        check_batch(twice, FitConfig(n_support=n + 1, n_candidates=n + 1))


def test_check_batch_warns_of_changes_too_small_for_the_hyperparameter_bounds():
    """Changes of mean square below 1e-12 fitted a useless model without a word:
    the bounds of the hyperparameter search stop following the data there. A
    dimension that never changes (mean square 0) is not warned of."""
    data = _batch(np.random.default_rng(0))
    config = FitConfig(n_support=10, n_candidates=10)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_batch(data, config)
        still = data.next_states.copy()
        still[:, 1] = data.states[:, 1]
        check_batch(Transitions(data.states, data.actions, still, data.instances),
                    config)  # fmt: skip
    tiny = Transitions(data.states * 1e-10, data.actions, data.next_states * 1e-10,
                       data.instances)  # fmt: skip
    with pytest.warns(RuntimeWarning, match=r"data.deltas: action 0, dimension 0 "
                      r"has mean squared change .* below 1e-12"):  # fmt: skip
        check_batch(tiny, config)


def test_new_features_chooses_the_samplers_new_feature_step(monkeypatch):
    """``FitConfig.new_features`` reaches the sampler as
    ``GibbsPriors.multiple_try`` ("paper": False, the default; "multiple_try":
    True); another value is refused, naming the field."""
    seen = []

    class Stop(Exception):
        pass

    def run_chains(data, priors, **kwargs):
        seen.append(priors)
        raise Stop

    monkeypatch.setattr(fitting, "run_chains", run_chains)
    data = _batch(np.random.default_rng(0))
    small = FitConfig(n_support=9, n_hyper=12, n_candidates=50, progress=False)
    for config in (small, dataclasses.replace(small, new_features="multiple_try")):
        with pytest.raises(Stop):
            fit(data, config, rng=np.random.default_rng(1))
    assert [priors.multiple_try for priors in seen] == [False, True]
    with pytest.raises(ValueError, match="FitConfig.new_features: expected one of"):
        FitConfig(new_features="exact")


def test_fit_hands_the_sampler_rows_a_d_and_takes_the_dense_weights(monkeypatch):
    """What `fit` gives the sampler and makes of its best sample, against plain
    formulas. Rows r = a·D + d: Y[r, b] the dense GP mean of all of instance b's
    action-a transitions (n_smooth, not n_hyper, covers each cell whole), K[r]
    the kernel of (a, d) at the support points, σ²[r] its noise; the config's
    priors and budgets. From a best sample with a feature on some rows only: z
    and f kept as sampled, and the weights the dense w-posterior mean under the
    sample's μ_w and σ_w (not σ_w0). The hyperparameters and the best sample are
    stand-ins: this checks the plumbing, not the fitting. With A = 2 ≠ D = 3, rows
    in d-major order or a transposed noise show."""
    seen = {}
    B, A, D = 3, 2, 3
    rng = np.random.default_rng(5)
    z = np.zeros((3, A * D), dtype=bool)
    z[0], z[1, [0, 3, 4]], z[2, 2] = True, True, True
    w = np.vstack([np.ones(B), rng.normal(size=(2, B))])
    mu_w = np.array([0.0, 0.7, -0.4])

    def run_chains(data, priors, **kwargs):
        seen.update(data=data, priors=priors, **kwargs)
        f = rng.normal(size=(3, A * D, data.Y.shape[2])) * z[:, :, None]
        seen["f"] = f
        best = GibbsState(z, w, f, mu_w)
        dummy = np.zeros((1, 1))
        return ChainResult(best, 0.0, 0.0, 0, 0, dummy, dummy, dummy.astype(int))

    def select_support(*args, **kwargs):
        seen["n_candidates"] = kwargs["n_candidates"]
        return real_select_support(*args, **kwargs)

    real_select_support = fitting.select_support
    hyper = _hyper(np.random.default_rng(2))  # as fitted, but well conditioned
    monkeypatch.setattr(fitting, "fit_hyper_set", lambda *args, **kwargs: hyper)
    monkeypatch.setattr(fitting, "run_chains", run_chains)
    monkeypatch.setattr(fitting, "select_support", select_support)
    data = _batch(np.random.default_rng(0), B=B, A=A, D=D)
    # n_smooth covers every (b, a) cell whole (16-24 transitions), n_hyper does not
    config = FitConfig(
        n_support=9, n_sweeps=5, n_chains=3, alpha=1.5, sigma_w=2.0, sigma_w0=3.0,
        n_w=7, n_hyper=12, n_candidates=50, n_smooth=1000, progress=False,
    )  # fmt: skip
    model = fit(data, config, rng=np.random.default_rng(1))
    g, h, S = seen["data"], model.hyper, model.support
    assert h is hyper
    assert seen["priors"] == GibbsPriors(1.5, 2.0, 3.0, 7)
    assert (seen["n_sweeps"], seen["n_chains"], seen["n_candidates"]) == (5, 3, 50)
    for a in range(A):
        for d in range(D):
            r = a * D + d
            assert g.noise[r] == h.noise_var[a, d]
            dist2 = (((S[:, None] - S[None]) / h.lengthscales[a, d]) ** 2).sum(-1)
            Kr = h.signal_var[a, d] * np.exp(-0.5 * dist2)
            np.testing.assert_allclose(g.K[r], Kr, rtol=1e-12, atol=1e-15)
            for bi, b in enumerate(data.instance_ids):
                cell = (data.instances == b) & (data.actions == a)
                want = _dense_gp_mean(
                    data.states[cell], data.deltas[cell, d], S,
                    h.lengthscales[a, d], h.signal_var[a, d], h.noise_var[a, d],
                )  # fmt: skip
                np.testing.assert_allclose(g.Y[r, bi], want, rtol=1e-8, atol=1e-12)
    np.testing.assert_array_equal(model.z.reshape(3, A * D), z)
    np.testing.assert_array_equal(model.f.reshape(3, A * D, -1), seen["f"])
    ref = dense.w_posterior(z, seen["f"], g.Y, g.noise, mu_w, 2.0)
    np.testing.assert_array_equal(model.weights[0], 1.0)
    np.testing.assert_allclose(model.weights[1:], ref.mean, rtol=1e-10)
