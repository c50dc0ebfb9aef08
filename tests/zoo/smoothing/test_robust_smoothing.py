"""The robust Student-t state-space smoother: exactness, outliers, causality, fitting, coverage, GPyTorch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from zoo.smoothing import (
    PRESETS,
    ROBUST_PRESETS,
    GPSmoother,
    OnlineSmoother,
    RobustHyperparameters,
    RobustSmoother,
    calibration_factor,
    coverage,
    fit_robust_hyperparameters,
    make_smoother,
    smooth_online,
)
from zoo.smoothing.gp import statespace_posterior
from zoo.smoothing.kalman import Batch, blocked_posterior, blocked_prior, scan_posterior
from zoo.smoothing.robust import infer

HP = RobustHyperparameters(lengthscale=(3.0, 4.0, 5.0), outputscale=(4.0, 9.0, 6.0), noise=(0.04, 0.09, 0.06), dof=3.0)


def smooth_truth(t: np.ndarray) -> np.ndarray:
    return np.stack([2 * np.sin(0.4 * t), 3 * np.cos(0.25 * t), 1.5 * np.sin(0.3 * t + 1)], axis=1)


def track_with_outliers(n: int = 300, seed: int = 0, noise: float = 0.25):
    """A smooth 10 Hz flight with Gaussian noise and every 23rd frame 8 m off in one direction."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1 + rng.uniform(-0.01, 0.01, n) + 1.69e9
    truth = smooth_truth(t - t[0])
    y = truth + rng.normal(0, noise, truth.shape)
    outliers = np.arange(11, n, 23)
    y[outliers] += np.array([0.0, 8.0, -6.0])
    return t, y, truth, outliers


def test_gaussian_weights_reproduce_the_exact_matern_state_space_smoother_and_tracks_restart():
    """The GP statespace backend (the blocked engine) equals the torch scans at unit weights, track by track."""
    rng = np.random.default_rng(1)
    n = 257  # odd, not a power of two: every branch of the scan
    t = np.cumsum(rng.uniform(0.05, 0.2, n))
    y = rng.normal(0, 1, (n, 3))
    hp = PRESETS["tuned"]
    mean, var = statespace_posterior(hp, t - t[0], y, t - t[0])
    robust = RobustHyperparameters(hp.lengthscale, hp.outputscale, hp.noise, dof=5.0)
    two = Batch(np.concatenate([t - t[0], t - t[0] + t[-1] + 3]), np.concatenate([y, y[::-1]]),
                np.ones(2 * n, dtype=bool), np.r_[True, np.zeros(n - 1, bool), True, np.zeros(n - 1, bool)])
    with torch.no_grad():
        m2, v2, _ = scan_posterior(two, np.ones(2 * n), *robust.arrays())
    np.testing.assert_allclose(m2[:n].numpy(), mean, atol=1e-9)
    np.testing.assert_allclose(v2[:n].numpy(), var, atol=1e-9)
    mean_r, var_r = statespace_posterior(hp, t - t[0], y[::-1], t - t[0])  # the second track alone
    np.testing.assert_allclose(m2[n:].numpy(), mean_r, atol=1e-9)
    np.testing.assert_allclose(v2[n:].numpy(), var_r, atol=1e-9)


@pytest.mark.parametrize("blocks", [None, 1, 4, 1000])
def test_the_blocked_numpy_posterior_equals_the_torch_scans(blocks):
    """Two tracks, unobserved steps, a repeated time and uneven weights: same means, variances, likelihood."""
    rng = np.random.default_rng(21)
    n = 301
    t = np.cumsum(rng.uniform(0.05, 0.15, n))
    t[40] = t[39]  # a step of length zero
    start = np.zeros(n, dtype=bool)
    start[[0, 170]] = True
    batch = Batch(t - t[0], rng.normal(0, 2, (n, 3)), rng.uniform(size=n) > 0.15, start)
    w = rng.uniform(0.02, 1.5, n)
    with torch.no_grad():
        mean, var, loglik = scan_posterior(batch, w, *HP.arrays())
    prior = blocked_prior(batch, *HP.arrays()[:2], blocks=blocks)
    noise = HP.arrays()[2][None, :] / np.where(batch.observed, w, 1.0)[:, None]
    mean_b, var_b, loglik_b = blocked_posterior(prior, noise)
    np.testing.assert_allclose(mean_b, mean.numpy(), atol=1e-10)
    np.testing.assert_allclose(var_b, var.numpy(), atol=1e-12)
    assert loglik_b == pytest.approx(float(loglik), rel=1e-12)
    with torch.no_grad():
        mf, Pf, _ = scan_posterior(batch, w, *HP.arrays(), smooth=False)
    mf_b, Pf_b, _ = blocked_posterior(prior, noise, smooth=False)
    np.testing.assert_allclose(mf_b, mf.numpy(), atol=1e-10)
    np.testing.assert_allclose(Pf_b, Pf.numpy(), atol=1e-10)


def test_variational_inference_gives_the_same_fit_with_either_engine():
    t, y, _, _ = track_with_outliers(400, seed=22)
    batch = Batch(t - t[0], y - y.mean(0), np.ones(len(t), bool), np.r_[True, np.zeros(len(t) - 1, bool)])
    blocked = infer(batch, HP, engine="blocked")
    scan = infer(batch, HP, engine="scan")
    assert blocked.iterations == scan.iterations
    np.testing.assert_allclose(blocked.mean, scan.mean, atol=1e-9)
    np.testing.assert_allclose(blocked.var, scan.var, atol=1e-12)
    np.testing.assert_allclose(blocked.weights, scan.weights, atol=1e-9)
    assert blocked.elbo == pytest.approx(scan.elbo, rel=1e-10)
    with pytest.raises(ValueError, match="engine"):
        infer(batch, HP, engine="nope")


def test_robust_smoother_ignores_outliers_and_the_gaussian_one_does_not():
    t, y, truth, outliers = track_with_outliers()
    robust = RobustSmoother(HP).smooth(t, y)
    gaussian = GPSmoother(None, kernel="matern52", lengthscale=HP.lengthscale, outputscale=HP.outputscale,
                          noise=HP.noise).smooth(t, y)
    err_r = np.linalg.norm(robust.mean - truth, axis=1)
    err_g = np.linalg.norm(gaussian.mean - truth, axis=1)
    assert err_r[outliers].max() < 0.4  # the 10 m frames leave no mark
    assert err_g[outliers].mean() > 3 * err_r[outliers].mean()
    assert err_r.mean() < 0.6 * err_g.mean()
    assert robust.weights[outliers].max() < 0.1  # one weight per frame, shared by the axes
    inliers = np.setdiff1d(np.arange(len(t)), outliers)
    assert np.median(robust.weights[inliers]) > 0.8


def test_query_times_order_and_absolute_time_do_not_change_the_result():
    t, y, _, _ = track_with_outliers(120)
    base = RobustSmoother(HP).smooth(t, y)
    perm = np.random.default_rng(3).permutation(len(t))
    shuffled = RobustSmoother(HP).smooth(t[perm] - 1.69e9, y[perm])
    np.testing.assert_allclose(shuffled.mean, base.mean[perm], atol=1e-8)
    between = 0.5 * (t[:-1] + t[1:])
    queried = RobustSmoother(HP).smooth(t, y, between)
    assert queried.mean.shape == (len(between), 3) and np.all(np.isfinite(queried.std))
    # a query midway between two frames lies between their smoothed values on a smooth track
    assert np.abs(queried.mean - 0.5 * (base.mean[:-1] + base.mean[1:])).max() < 0.05


def test_the_calibration_factor_scales_the_reported_std():
    t, y, _, _ = track_with_outliers(100)
    plain = RobustSmoother(HP).smooth(t, y)
    scaled = RobustSmoother(replace_scale(HP, ((0.0, 3.0), (np.inf, 2.0)))).smooth(t, y)
    np.testing.assert_allclose(scaled.std, 2.0 * plain.std)
    np.testing.assert_allclose(scaled.mean, plain.mean)
    assert replace_scale(HP, ((0.0, 3.0), (1.0, 2.0), (np.inf, 1.5))).scale_for(0.5) == pytest.approx(2.5)


def replace_scale(hp: RobustHyperparameters, pairs) -> RobustHyperparameters:
    from dataclasses import replace

    return replace(hp, std_scale=pairs)


# ---------------------------------------------------------------------------------- causal and fixed lag


@pytest.mark.parametrize("lag", [0.0, 0.5])
def test_online_outputs_never_use_frames_beyond_their_lag(lag):
    t, y, _, _ = track_with_outliers(80, seed=4)
    cut = 50
    base = smooth_online(t, y, HP, lag=lag)
    perturbed = y.copy()
    perturbed[cut:] += np.random.default_rng(5).normal(0, 5, perturbed[cut:].shape)
    other = smooth_online(t, perturbed, HP, lag=lag)
    np.testing.assert_array_equal(base.timestamps, t)
    allowed = t + lag < t[cut]  # rows whose time plus the lag lies before the first changed frame
    np.testing.assert_array_equal(other.mean[allowed], base.mean[allowed])
    np.testing.assert_array_equal(other.std[allowed], base.std[allowed])
    assert not np.allclose(other.mean[cut:], base.mean[cut:])


def test_fixed_lag_uses_the_future_within_its_lag():
    t, y, truth, _ = track_with_outliers(200, seed=6, noise=0.4)
    causal = smooth_online(t, y, HP, lag=0.0)
    lagged = smooth_online(t, y, HP, lag=1.0)
    offline = RobustSmoother(HP).smooth(t, y)
    errors = [np.linalg.norm(s.mean - truth, axis=1).mean() for s in (causal, lagged, offline)]
    assert errors[0] > errors[1] > 0.9 * errors[2]
    row = 100  # a frame inside the lag changes the row, one just beyond it does not
    inside, beyond = y.copy(), y.copy()
    inside[row + 5] += 1.0
    beyond[np.flatnonzero(t > t[row] + 1.0)[0]] += 1.0
    assert not np.allclose(smooth_online(t, inside, HP, lag=1.0).mean[row], lagged.mean[row])
    np.testing.assert_array_equal(smooth_online(t, beyond, HP, lag=1.0).mean[row], lagged.mean[row])


def test_the_online_smoother_emits_each_frame_once_in_order_and_flush_finishes():
    t, y, _, _ = track_with_outliers(40, seed=7)
    online = OnlineSmoother(HP, lag=0.35)
    emitted = []
    for i in range(len(t)):
        rows = online.update(t[i], y[i])
        assert all(r.timestamp + 0.35 <= t[i] for r in rows)  # its lag has passed when a row comes out
        emitted += rows
    emitted += online.flush()
    assert [r.timestamp for r in emitted] == list(t)
    batch = smooth_online(t, y, HP, lag=0.35)
    np.testing.assert_array_equal(np.stack([r.mean for r in emitted]), batch.mean)
    with pytest.raises(ValueError, match="not after"):
        online.update(t[-1], y[-1])
    with pytest.raises(ValueError, match="finite"):
        online.update(t[-1] + 1, [np.nan, 0, 0])


def test_causal_mode_emits_at_once_with_bounded_window():
    t, y, _, _ = track_with_outliers(120, seed=8)
    online = OnlineSmoother(HP, lag=0.0, window=0.0)
    for i in range(len(t)):
        rows = online.update(t[i], y[i])
        assert [r.timestamp for r in rows] == [t[i]]
        assert len(online._frames) == 1  # nothing of the past is re-solved
    lagged = OnlineSmoother(HP, lag=0.5, window=0.0)
    for i in range(len(t)):
        lagged.update(t[i], y[i])
        assert len(lagged._frames) <= 8
    revised = OnlineSmoother(HP, lag=0.0, window=1.0)  # past weights revised, emitted rows final
    rows = [row for i in range(len(t)) for row in revised.update(t[i], y[i])]
    assert [r.timestamp for r in rows] == list(t) and len(revised._frames) <= 12
    default = OnlineSmoother(HP)  # a 5 s window: the work per frame stops growing once it is full
    sizes = [len(default._frames) for i in range(len(t)) if default.update(t[i], y[i]) is not None]
    assert max(sizes) <= 53 and sizes[-1] >= 48


def test_the_window_solve_is_the_exact_posterior_given_the_weights():
    """One variational iteration: the window's q(f) equals the Kalman smoother over every frame so far,
    with each committed frame's final weight and the window's weights from before the update."""
    t, y, _, _ = track_with_outliers(70, seed=14)
    online = OnlineSmoother(HP, lag=0.0, window=1.0, iterations=1)
    last_weight: dict[float, float] = {}
    for i in range(len(t)):
        used = dict(last_weight)
        online.update(t[i], y[i])
        last_weight.update({frame[0]: w for frame, w in zip(online._frames, online._weights, strict=True)})
    used[t[-1]] = 1.0
    weights = np.array([used[v] for v in t])
    batch = Batch(t - t[0], y - y[0], np.ones(len(t), bool), np.r_[True, np.zeros(len(t) - 1, bool)])
    noise = HP.arrays()[2][None, :] / weights[:, None]
    mean, var, _ = blocked_posterior(blocked_prior(batch, *HP.arrays()[:2]), noise)
    times, window_mean, window_var, _ = online._solution
    assert online._t is not None and len(times) < len(t)  # a committed state and a window after it
    window = np.searchsorted(t, times)
    np.testing.assert_allclose(window_mean, mean[window], atol=1e-8)
    np.testing.assert_allclose(window_var, var[window], atol=1e-10)


def test_a_frames_noise_scale_sets_how_far_it_pulls_the_estimate():
    """Scale 1 is the preset's noise exactly; a larger scale (a weaker measurement) pulls the estimate less."""
    t, y, _, _ = track_with_outliers(60, seed=15, noise=0.1)
    def last(scale: float | None, offset: float) -> object:
        smoother = OnlineSmoother(HP, lag=0.0)
        for i in range(len(t) - 1):
            smoother.update(t[i], y[i])
        frame = y[-1] + offset * np.array([1.0, -1.0, 1.0])  # the last frame moved off the track
        return (smoother.update(t[-1], frame) if scale is None else smoother.update(t[-1], frame, scale))[0]

    rows = [last(None, 0.3), last(1.0, 0.3), last(100.0, 0.3), last(0.01, 0.3)]
    np.testing.assert_array_equal(rows[0].mean, rows[1].mean)
    pull = [np.linalg.norm(r.mean - last(s, 0.0).mean) for r, s in zip(rows, (None, 1.0, 100.0, 0.01), strict=True)]
    assert pull[2] < 0.5 * pull[0] < pull[0] < pull[3]
    assert np.all(rows[2].std > rows[0].std)
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="noise_scale"):
            OnlineSmoother(HP).update(0.0, [0, 0, 0], bad)


def test_the_noise_scale_of_a_detection_score():
    from dataclasses import replace

    assert HP.noise_scale(3.0) == 1.0  # no score power: every frame has the preset's noise
    scored = replace(HP, score_power=4.0, score_reference=5.0)
    assert scored.noise_scale(5.0) == 1.0
    assert scored.noise_scale(2.5) == pytest.approx(16.0) and scored.noise_scale(10.0) == pytest.approx(1 / 16)
    assert scored.noise_scale(float("nan")) == 1.0  # a row without a score (phase_student)
    with pytest.raises(ValueError, match="score_power"):
        replace(HP, score_power=-1.0)
    with pytest.raises(ValueError, match="score_reference"):
        replace(HP, score_reference=0.0)


def test_the_std_factor_of_a_detection_score():
    from dataclasses import replace

    assert HP.std_score_factor(3.0) == 1.0  # no std score power: the std as the smoother gives it
    scored = replace(HP, std_score_power=1.5, score_reference=4.0)
    assert scored.std_score_factor(4.0) == 1.0
    assert scored.std_score_factor(16.0) == pytest.approx(8.0) and scored.std_score_factor(1.0) == pytest.approx(0.125)
    assert scored.std_score_factor(float("nan")) == 1.0 and scored.std_score_factor(0.0) == 1.0
    with pytest.raises(ValueError, match="std_score_power"):
        replace(HP, std_score_power=-0.5)


def test_predict_between_frames_is_the_exact_posterior_given_the_weights_and_noise_scales():
    """The interpolation at a time without a frame equals the Kalman smoother over every frame so far, with
    that time as an unobserved step, each frame at its last weight and its own noise scale."""
    t, y, _, _ = track_with_outliers(70, seed=16)
    scales = np.random.default_rng(17).uniform(0.2, 5.0, len(t))
    online = OnlineSmoother(HP, lag=0.5, window=1.0, iterations=2)
    last_weight: dict[float, float] = {}
    for i in range(len(t)):
        online.update(t[i], y[i], scales[i])
        last_weight.update({frame[0]: w for frame, w in zip(online._frames, online._weights, strict=True)})
    query = 0.5 * (t[-3] + t[-2])
    mean, std = online.predict(query)
    times = np.r_[t[:-2], query, t[-2:]]
    observed = np.r_[np.ones(len(t) - 2, bool), False, True, True]
    data = np.r_[y[:-2], np.zeros((1, 3)), y[-2:]] - y[0]
    noise = np.r_[scales[:-2], 1.0, scales[-2:]][:, None] * HP.arrays()[2][None, :]
    noise /= np.r_[[last_weight[v] for v in t[:-2]], 1.0, [last_weight[v] for v in t[-2:]]][:, None]
    batch = Batch(times - t[0], data, observed, np.r_[True, np.zeros(len(times) - 1, bool)])
    exact_mean, exact_var, _ = blocked_posterior(blocked_prior(batch, *HP.arrays()[:2]), noise)
    np.testing.assert_allclose(mean, exact_mean[len(t) - 2] + y[0], atol=1e-8)
    np.testing.assert_allclose(std, np.sqrt(exact_var[len(t) - 2]) * online.hold_scale, rtol=1e-6)
    with pytest.raises(ValueError, match="cannot predict"):
        OnlineSmoother(HP).predict(0.0)


# ------------------------------------------------------------------------------------------- fitting


def test_fitted_degrees_of_freedom_separate_gaussian_from_heavy_tailed_noise():
    rng = np.random.default_rng(9)
    t = np.arange(200) * 0.1
    truth = smooth_truth(t)
    gaussian = truth + rng.normal(0, 0.3, truth.shape)
    # a Student-t with 1.5 degrees of freedom, one scale per frame shared by the axes
    heavy = truth + 0.3 * rng.normal(0, 1, truth.shape) / np.sqrt(rng.gamma(0.75, 1 / 0.75, (len(t), 1)))
    start = RobustHyperparameters((3.0, 3.0, 3.0), (5.0, 5.0, 5.0), (0.1, 0.1, 0.1), dof=5.0)
    fit_g = fit_robust_hyperparameters([(t, gaussian)], start, rounds=5, m_iterations=3)
    fit_h = fit_robust_hyperparameters([(t, heavy)], start, rounds=5, m_iterations=3)
    assert fit_g.hyperparameters.dof > 20
    assert fit_h.hyperparameters.dof < 4
    assert fit_h.downweighted > 0.1 > fit_g.downweighted
    np.testing.assert_allclose(fit_g.hyperparameters.noise, 0.09, rtol=0.35)


def test_the_bound_increases_over_variational_iterations():
    t, y, _, _ = track_with_outliers(150, seed=10)
    batch = Batch(t - t[0], y - y.mean(0), np.ones(len(t), bool), np.r_[True, np.zeros(len(t) - 1, bool)])
    bounds = [infer(batch, HP, max_iterations=k, tolerance=0.0).elbo for k in (1, 2, 4, 8)]
    assert all(b2 >= b1 - 1e-6 for b1, b2 in zip(bounds, bounds[1:], strict=False))


# ------------------------------------------------------------------------------------------- coverage


def test_coverage_and_calibration_factor():
    rng = np.random.default_rng(11)
    truth = rng.normal(0, 1, (20000, 3))
    mean = np.zeros_like(truth)
    std = np.full_like(truth, 0.5)  # twice too confident
    assert coverage(mean, std, truth) == pytest.approx(0.683, abs=0.01)
    assert coverage(mean, 2 * std, truth) == pytest.approx(0.954, abs=0.01)
    assert calibration_factor(mean, std, truth) == pytest.approx(1.96, abs=0.05)
    mean[0] = np.nan
    assert 0.6 < coverage(mean, std, truth) < 0.7
    with pytest.raises(ValueError, match="one shape"):
        coverage(mean, std[:5], truth)


# --------------------------------------------------------------------------------- defaults and GPyTorch


def test_make_smoother_defaults_to_robust_and_keeps_the_paper_gp_by_name():
    assert isinstance(make_smoother(), RobustSmoother)
    assert isinstance(make_smoother("paper"), GPSmoother)
    assert make_smoother("paper").hyperparameters == PRESETS["paper"]
    assert make_smoother("robust").hyperparameters == ROBUST_PRESETS["robust"]
    with pytest.raises(ValueError, match="unknown smoother preset"):
        make_smoother("nope")


@pytest.mark.slow
def test_agrees_with_gpytorch_student_t_variational_gp_on_a_short_track():
    """One axis, hyperparameters fixed: our mean-field scale mixture against GPyTorch's StudentTLikelihood
    with a full-rank variational GP (inducing points at the data). Different approximations of the
    same posterior: the means agree to a small fraction of the noise and both ignore the outliers."""
    import gpytorch

    rng = np.random.default_rng(12)
    n = 60
    t = np.arange(n) * 0.1
    truth = 2 * np.sin(0.8 * t)
    y = truth + rng.normal(0, 0.2, n)
    y[[15, 40]] += 6.0
    lengthscale, outputscale, noise, dof = 2.0, 4.0, 0.04, 4.0
    hp = RobustHyperparameters(lengthscale, outputscale, noise, dof)
    batch = Batch(t, y[:, None], np.ones(n, bool), np.r_[True, np.zeros(n - 1, bool)])
    ours = infer(batch, hp, axes=(np.array([lengthscale]), np.array([outputscale]), np.array([noise])),
                 max_iterations=200, tolerance=1e-8)

    torch.manual_seed(0)
    x = torch.as_tensor(t, dtype=torch.float64)[:, None]

    class Model(gpytorch.models.ApproximateGP):
        def __init__(self):
            distribution = gpytorch.variational.CholeskyVariationalDistribution(n)
            strategy = gpytorch.variational.VariationalStrategy(self, x, distribution,
                                                                 learn_inducing_locations=False)
            super().__init__(strategy)
            self.covar = gpytorch.kernels.ScaleKernel(gpytorch.kernels.MaternKernel(nu=2.5))

        def forward(self, inputs):
            return gpytorch.distributions.MultivariateNormal(torch.zeros(inputs.shape[0], dtype=inputs.dtype),
                                                             self.covar(inputs))

    model = Model().double()
    model.covar.base_kernel.lengthscale = torch.tensor(lengthscale, dtype=torch.float64)
    model.covar.outputscale = torch.tensor(outputscale, dtype=torch.float64)
    likelihood = gpytorch.likelihoods.StudentTLikelihood().double()
    likelihood.noise = torch.tensor(noise, dtype=torch.float64)
    likelihood.deg_free = torch.tensor(dof, dtype=torch.float64)
    variational = list(model.variational_strategy._variational_distribution.parameters())
    optimizer = torch.optim.Adam(variational, lr=0.1)
    objective = gpytorch.mlls.VariationalELBO(likelihood, model, num_data=n)
    target = torch.as_tensor(y, dtype=torch.float64)
    model.train()
    with gpytorch.settings.num_likelihood_samples(32):
        for _ in range(300):
            optimizer.zero_grad()
            loss = -objective(model(x), target)
            loss.backward()
            optimizer.step()
    model.eval()
    with torch.no_grad():
        theirs = model(x).mean.numpy()
    gaussian = GPSmoother(None, kernel="matern52", lengthscale=lengthscale, outputscale=outputscale,
                          noise=noise).smooth(t, np.stack([y, y, y], 1)).mean[:, 0]
    ours_mean = ours.mean[:, 0]
    assert np.abs(ours_mean - theirs).max() < 0.1  # noise std 0.2, outliers 6
    assert np.abs(ours_mean - truth)[[15, 40]].max() < 0.3
    assert np.abs(gaussian - truth)[[15, 40]].min() > 0.5  # the Gaussian GP is dragged by both


# ------------------------------------------------------------------------------------------------ CLI


def write_track(path, t, y):
    import pandas as pd

    pd.DataFrame({"timestamp": t, "x": y[:, 0], "y": y[:, 1], "z": y[:, 2]}).to_csv(path, index=False)


def test_smooth_command_robust_offline_and_fixed_lag_print_diagnostics(tmp_path, capsys):
    import pandas as pd

    from zoo.cli import main

    t, y, truth, outliers = track_with_outliers(150, seed=13)
    src = tmp_path / "track.csv"
    write_track(src, t, y)
    assert main(["smooth", str(src), str(tmp_path / "off.csv")]) == 0  # robust is the default
    offline = capsys.readouterr().out
    assert "robust smoother (offline): degrees of freedom 1.24" in offline and "down-weighted" in offline
    assert main(["smooth", str(src), str(tmp_path / "lag.csv"), "--preset", "robust", "--lag", "1"]) == 0
    assert "lag 1 s" in capsys.readouterr().out
    for name in ("off.csv", "lag.csv"):
        out = pd.read_csv(tmp_path / name)
        assert list(out.columns) == ["timestamp", "x", "y", "z", "std_x", "std_y", "std_z"] and len(out) == len(t)
        error = np.linalg.norm(out[["x", "y", "z"]].to_numpy() - truth, axis=1)
        assert error[outliers].max() < 1.0
    assert main(["smooth", str(src), str(tmp_path / "never.csv"), "--preset", "paper", "--lag", "1"]) == 2
    assert not (tmp_path / "never.csv").exists()


@pytest.mark.parametrize("n", [1, 2, 3])
def test_tracks_of_one_to_three_frames(n):
    t = np.arange(n) * 0.1
    y = np.random.default_rng(n).normal(0, 1, (n, 3))
    offline = RobustSmoother().smooth(t, y)
    online = smooth_online(t, y, lag=1.0)
    for track in (offline, online):
        assert track.mean.shape == (n, 3) and np.all(np.isfinite(track.mean)) and np.all(np.isfinite(track.std))


def test_the_blocked_engine_reproduces_the_scan_engine_on_a_real_track(shared_data):
    """MMAUD V1 Mavic 3 with TAME's predictions, the shipped preset, 30 iterations: within 1e-6 m."""
    from zoo.smoothing import read_track_csv

    path = shared_data / "mmaud_v1_tame" / "Mavic3_pred.csv"
    if not path.is_file():
        pytest.skip(f"real MMAUD V1 / TAME track not found at {path}")
    t, y = read_track_csv(path)
    batch = Batch(t - t[0], y - y.mean(0), np.ones(len(t), bool), np.r_[True, np.zeros(len(t) - 1, bool)])
    hp = ROBUST_PRESETS["robust"]
    blocked, scan = infer(batch, hp, engine="blocked"), infer(batch, hp, engine="scan")
    assert blocked.iterations == scan.iterations == 30
    np.testing.assert_allclose(blocked.mean, scan.mean, atol=1e-6)
    np.testing.assert_allclose(np.sqrt(blocked.var), np.sqrt(scan.var), atol=1e-6)
