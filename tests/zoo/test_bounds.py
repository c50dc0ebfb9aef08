"""The localisation bound against closed forms and against a maximum-likelihood TDOA estimator."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from datamodules.snr import SnrSpectrum
from zoo.bounds import (
    delay_fisher,
    flat_band_tdoa_variance,
    knapp_carter_variance,
    position_bound,
    position_fisher,
    window_bounds,
)

C = 343.0


def _flat(snr: float, low: float, high: float, bin_hz: float = 1.0, mics: int = 2) -> tuple[np.ndarray, np.ndarray]:
    freqs = np.arange(0.0, high + bin_hz, bin_hz)
    snr_bins = np.where((freqs >= low) & (freqs <= high), snr, 0.0)
    return freqs, np.repeat(snr_bins[:, None], mics, axis=1)


def test_knapp_carter_matches_the_flat_band_closed_form():
    freqs, snr = _flat(2.0, 500.0, 4000.0, bin_hz=0.5)
    bound = knapp_carter_variance(snr[:, 0], snr[:, 1], freqs, 0.1, (500.0, 4000.0))
    assert bound == pytest.approx(flat_band_tdoa_variance(2.0, 500.0, 4000.0, 0.1), rel=2e-3)


def test_unequal_snrs_enter_as_the_coherence_ratio():
    """|gamma|^2 / (1 - |gamma|^2) = s1 s2 / (1 + s1 + s2) (Knapp and Carter 1976)."""
    freqs = np.array([1000.0, 1001.0])
    bound = knapp_carter_variance(np.array([3.0, 3.0]), np.array([0.5, 0.5]), freqs, 1.0)
    density = 2 * (2 * np.pi) ** 2 * (1000.0 ** 2 + 1001.0 ** 2) * 1.5 / 4.5
    assert bound == pytest.approx(1 / density, rel=1e-12)


def test_absolute_delay_is_unobservable():
    freqs, snr = _flat(1.0, 100.0, 2000.0, bin_hz=10.0, mics=4)
    fisher = delay_fisher(snr * np.array([1.0, 0.5, 2.0, 0.1]), freqs, 1.0)
    assert np.allclose(fisher @ np.ones(4), 0.0, atol=1e-6 * np.abs(fisher).max())


def test_two_microphones_in_the_far_field_give_the_bearing_bound():
    """Tangential position information = (d sin(theta) / (c R))^2 / var(D), the far-field bearing bound."""
    spacing, distance, theta = 1.0, 2000.0, np.radians(60.0)
    mics = np.array([[spacing / 2, 0.0, 0.0], [-spacing / 2, 0.0, 0.0]])
    source = distance * np.array([np.cos(theta), np.sin(theta), 0.0])
    freqs, snr = _flat(1.0, 200.0, 3000.0, bin_hz=5.0)
    fisher = position_fisher(source, mics, delay_fisher(snr, freqs, 0.5), C)
    tangent = np.array([-np.sin(theta), np.cos(theta), 0.0])
    expected = (spacing * np.sin(theta) / (C * distance)) ** 2 / knapp_carter_variance(snr[:, 0], snr[:, 1], freqs, 0.5)
    assert tangent @ fisher @ tangent == pytest.approx(expected, rel=1e-3)
    # one time difference cannot fix three coordinates; a prior of 50 m caps the two unseen ones near 50 m
    assert np.isinf(position_bound(source, mics, snr, freqs, 0.5, speed_of_sound=C))
    capped = position_bound(source, mics, snr, freqs, 0.5, speed_of_sound=C, prior_std=50.0)
    assert np.sqrt(2) * 50.0 < capped < np.sqrt(3) * 50.0


def test_the_bound_shrinks_with_snr_and_grows_with_range():
    mics = np.array([[1.5, 1.5, 0.2], [-1.5, 1.5, 0.7], [-1.5, -1.5, 1.2], [1.5, -1.5, 1.7]])
    freqs, snr = _flat(1.0, 100.0, 2000.0, bin_hz=25.0, mics=4)
    near, far = np.array([8.0, 5.0, 6.0]), np.array([32.0, 20.0, 24.0])
    bounds = position_bound(np.stack([near, far]), mics, np.stack([snr, snr]), freqs, 2.0, speed_of_sound=C)
    assert np.all(np.isfinite(bounds)) and bounds[1] > 4 * bounds[0]
    louder = position_bound(near, mics, 10 * snr, freqs, 2.0, speed_of_sound=C)
    assert louder < bounds[0] / 2


def test_window_bounds_average_the_frames_a_window_spans():
    mics = np.array([[1.5, 1.5, 0.2], [-1.5, 1.5, 0.7], [-1.5, -1.5, 1.2], [1.5, -1.5, 1.7]])
    db = np.full((4, 4, 81), -60.0)
    db[:, 2:, 4:41] = 10.0  # the drone is heard from the third second, 100-1000 Hz
    spectrum = SnrSpectrum(db)
    position = np.array([[10.0, 4.0, 5.0]] * 3)
    bounds = window_bounds(spectrum, mics, position, np.array([2.0, 3.0, 4.0]), 2.0, speed_of_sound=C)
    assert bounds[0] > 100 * bounds[2]  # silent window: next to no information
    assert bounds[1] == pytest.approx(bounds[2] * np.sqrt(2), rel=0.05)  # half the window: half the information


def _ml_tdoa(first: np.ndarray, second: np.ndarray, fs: float, band: tuple[float, float]) -> float:
    """Maximum-likelihood delay of ``second`` behind ``first`` for flat, equal spectra: the peak of the
    in-band cross-correlation, refined off the sample grid."""
    n = first.size
    freqs = np.fft.rfftfreq(n, 1 / fs)
    keep = (freqs >= band[0]) & (freqs <= band[1])
    cross = np.fft.rfft(first)[keep] * np.conj(np.fft.rfft(second)[keep])
    omega = 2 * np.pi * freqs[keep]

    def correlation(delay: float) -> float:
        return -float(np.real(np.sum(cross * np.exp(-1j * omega * delay))))

    padded = np.zeros(4 * n + 1, dtype=complex)  # 8x interpolated cross-correlation, then refined
    padded[np.flatnonzero(keep)] = np.conj(cross)  # its inverse transform peaks at the delay
    lags = np.fft.irfft(padded, 8 * n)
    step = 1 / (8 * fs)
    peak = int(np.argmax(lags))
    start = (peak if peak < lags.size // 2 else peak - lags.size) * step
    return float(minimize_scalar(correlation, bounds=(start - step, start + step),
                                 method="bounded", options={"xatol": 1e-12}).x)


def test_a_maximum_likelihood_estimator_reaches_the_bound_at_high_snr():
    fs, seconds, band, snr, delay = 8000.0, 0.25, (300.0, 1500.0), 10.0, 1.37e-3
    n = int(fs * seconds)
    freqs = np.fft.rfftfreq(n, 1 / fs)
    in_band = (freqs >= band[0]) & (freqs <= band[1])
    rng = np.random.default_rng(7)
    estimates = []
    for _ in range(300):
        # flat in-band source and noise spectra of ratio ``snr``: the bound's model, delays applied exactly
        source = (rng.standard_normal(freqs.size) + 1j * rng.standard_normal(freqs.size)) * in_band
        noise = (rng.standard_normal((2, freqs.size)) + 1j * rng.standard_normal((2, freqs.size))) * in_band
        noise /= np.sqrt(snr)
        first = np.fft.irfft(source + noise[0], n)
        second = np.fft.irfft(source * np.exp(-2j * np.pi * freqs * delay) + noise[1], n)
        estimates.append(_ml_tdoa(first, second, fs, band))
    errors = np.asarray(estimates) - delay
    snr_bins = np.where(in_band, snr, 0.0)
    bound = knapp_carter_variance(snr_bins, snr_bins, freqs, seconds, band)
    assert abs(errors.mean()) < 3 * np.sqrt(bound / errors.size)
    assert np.mean(errors ** 2) == pytest.approx(bound, rel=0.25)
