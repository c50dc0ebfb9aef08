"""The Cramér–Rao lower bound of time-difference localisation: how well any method could do.

Signal model (a single stationary, Gaussian, wideband source; the delays are the only unknowns): microphone m
records ``g_m s(t - tau_m) + n_m(t)`` with ``tau_m = |x - p_m| / c`` for a source at ``x`` and microphones at
``p_m``; the noises are independent of each other and of the source. ``snr_m(f)`` is the ratio of the drone's
power spectral density at microphone m to that microphone's noise density. Observed for ``T`` seconds, the
DFT bins (spacing 1/T) are independent complex Gaussian vectors with covariance ``C(f) = N^(1/2) (I + b b^H)
N^(1/2)``, ``|b_m|^2 = snr_m(f)``, and the Whittle form of the Fisher information of the delay vector is

    J_tau = T * integral over the band of  2 (2 pi f)^2 / (1 + beta) * (beta diag(snr) - snr snr^T) df,
    beta = sum_m snr_m(f),

the multi-sensor result of Hahn & Tretter (1973, "Optimum processing for delay-vector estimation in passive
signal arrays", IEEE Trans. IT-19) in the form of Weiss & Weinstein (1983, "Fundamental limitations in passive
time delay estimation, Part I", IEEE Trans. ASSP-31). ``J_tau`` has the constant vector in its null space: an
absolute delay (the emission time) is not observable, only differences are. For two microphones it reduces to
the Knapp & Carter (1976, "The generalized correlation method for estimation of time delay", IEEE Trans.
ASSP-24, eq. 21) bound

    var(D) >= [ 2 T integral (2 pi f)^2 |gamma(f)|^2 / (1 - |gamma(f)|^2) df ]^-1,
    |gamma|^2 / (1 - |gamma|^2) = snr_1 snr_2 / (1 + snr_1 + snr_2),

which on a flat band [f1, f2] with equal SNR is ``3 (1 + 2 snr) / (8 pi^2 T snr^2 (f2^3 - f1^3))``.
The position bound follows by the chain rule: with ``G_mi = d tau_m / d x_i = (x - p_m)_i / (c |x - p_m|)``,
``J_x = G^T J_tau G`` and ``cov(x_hat) >= J_x^-1`` for any unbiased estimator; :func:`position_bound` reports
``sqrt(trace(J_x^-1))``, the bound on the RMS 3D position error (metres). With four microphones (three time
differences for three coordinates) there are positions where the time differences do not change along one
direction (the range, mostly): there ``J_x`` is singular and the bound infinite. Given ``prior_std``, the
bound is Van Trees's Bayesian one (Van Trees 1968, "Detection, Estimation, and Modulation Theory I", eq.
2.288; Gill & Levit 1995) for an isotropic Gaussian prior of that spread, ``(J_x + I / prior_std^2)^-1``,
which never exceeds what knowing only the flight region gives.

What the bound leaves out, all of which can only make real errors larger: it is local (below a threshold SNR,
or with ambiguous lags, estimators leave it; Ziv–Zakai bounds describe that regime), it takes the source as
still during the window and the spectra as known, and it models the direct path only (the simulator's SNR
counts the ground-reflected sound as the drone's, but its delays carry no information here). It needs
microphone positions and a clock shared by all microphones.
"""

from __future__ import annotations

import numpy as np

from datamodules.snr import SnrSpectrum
from zoo.nets.phase.steering import SPEED_OF_SOUND  # the phase nets' air (m/s), so the bound uses the same


def delay_fisher_density(snr: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """Fisher information of the delay vector per second of signal and per Hz (Hahn–Tretter).

    Args:
        snr: linear SNR, (..., bins, mics).
        freqs: Hz, (bins,).

    Returns:
        (..., bins, mics, mics): ``2 (2 pi f)^2 / (1 + beta) (beta diag(snr) - snr snr^T)``.
    """
    snr = np.clip(np.asarray(snr, dtype=np.float64), 0.0, None)
    beta = snr.sum(axis=-1, keepdims=True)
    omega2 = (2.0 * np.pi * np.asarray(freqs, dtype=np.float64)) ** 2
    scale = 2.0 * omega2[:, None] / (1.0 + beta)  # (..., bins, 1)
    outer = snr[..., :, None] * snr[..., None, :]
    diagonal = np.einsum("...m,mn->...mn", beta * snr, np.eye(snr.shape[-1]))
    return scale[..., None] * (diagonal - outer)


def band_mask(freqs: np.ndarray, band_hz: tuple[float, float] | None) -> np.ndarray:
    """Bins inside ``band_hz`` (inclusive), every bin when None."""
    freqs = np.asarray(freqs, dtype=np.float64)
    if band_hz is None:
        return np.ones(freqs.shape, dtype=bool)
    low, high = band_hz
    return (freqs >= low) & (freqs <= high)


def delay_fisher(snr: np.ndarray, freqs: np.ndarray, seconds: float, band_hz: tuple[float, float] | None = None
                 ) -> np.ndarray:
    """Fisher information of the delay vector (s^-2) from ``seconds`` of signal, summed over the band's bins.

    Args:
        snr: linear SNR on a uniform grid of bin centres, (..., bins, mics).
        freqs: bin centres (Hz), uniformly spaced.
        seconds: observation time T.
        band_hz: (low, high) Hz; None: every bin.

    Returns:
        (..., mics, mics).
    """
    freqs = np.asarray(freqs, dtype=np.float64)
    width = float(freqs[1] - freqs[0]) if freqs.size > 1 else 1.0
    keep = band_mask(freqs, band_hz)
    density = delay_fisher_density(np.asarray(snr)[..., keep, :], freqs[keep])
    return seconds * width * density.sum(axis=-3)


def knapp_carter_variance(snr_first: np.ndarray, snr_second: np.ndarray, freqs: np.ndarray, seconds: float,
                          band_hz: tuple[float, float] | None = None) -> float:
    """The Knapp–Carter (1976) bound on the variance (s^2) of a two-microphone time difference."""
    snr = np.stack([np.asarray(snr_first, float), np.asarray(snr_second, float)], axis=-1)
    fisher = delay_fisher(snr, freqs, seconds, band_hz)
    information = fisher[0, 0]  # d tau / d D = (1, 0) with tau_2 held as the reference
    return float(1.0 / information) if information > 0 else float("inf")


def flat_band_tdoa_variance(snr: float, low_hz: float, high_hz: float, seconds: float) -> float:
    """Closed form of the Knapp–Carter bound for equal, flat SNR on [low, high] Hz."""
    return 3.0 * (1.0 + 2.0 * snr) / (8.0 * np.pi ** 2 * seconds * snr ** 2 * (high_hz ** 3 - low_hz ** 3))


def delay_gradient(position: np.ndarray, mics: np.ndarray, speed_of_sound: float = SPEED_OF_SOUND) -> np.ndarray:
    """``d tau_m / d x``: unit vectors from each microphone to the source over c, (..., mics, 3)."""
    offset = np.asarray(position, dtype=np.float64)[..., None, :] - np.asarray(mics, dtype=np.float64)
    return offset / (speed_of_sound * np.linalg.norm(offset, axis=-1, keepdims=True))


def position_fisher(position: np.ndarray, mics: np.ndarray, delay_information: np.ndarray,
                    speed_of_sound: float = SPEED_OF_SOUND) -> np.ndarray:
    """``J_x = G^T J_tau G`` (m^-2), (..., 3, 3)."""
    gradient = delay_gradient(position, mics, speed_of_sound)
    return np.einsum("...mi,...mn,...nj->...ij", gradient, delay_information, gradient)


def position_bound(position: np.ndarray, mics: np.ndarray, snr: np.ndarray, freqs: np.ndarray, seconds: float,
                   band_hz: tuple[float, float] | None = None, speed_of_sound: float = SPEED_OF_SOUND,
                   prior_std: float | None = None) -> np.ndarray:
    """Bound on the RMS 3D position error (m), ``sqrt(trace(J_x^-1))``; inf where the geometry cannot localise.

    Args:
        position: true source positions, (..., 3) metres in the microphones' frame.
        mics: microphone positions, (mics, 3).
        snr: linear SNR per bin and microphone, (..., bins, mics).
        freqs: bin centres (Hz).
        seconds: window length T.
        band_hz: (low, high) Hz; None: every bin.
        speed_of_sound: m/s.
        prior_std: metres; given, the Bayesian bound for a Gaussian prior of this spread per axis.
    """
    information = position_fisher(position, mics, delay_fisher(snr, freqs, seconds, band_hz), speed_of_sound)
    if prior_std is not None:
        information = information + np.eye(3) / prior_std ** 2
    result = np.full(information.shape[:-2], np.inf)
    flat_info, flat_result = information.reshape(-1, 3, 3), result.reshape(-1)
    for index, matrix in enumerate(flat_info):
        eigen = np.linalg.eigvalsh(matrix)
        if eigen[0] > eigen[-1] * 1e-12 and eigen[0] > 0:
            flat_result[index] = float(np.sqrt(np.sum(1.0 / eigen)))
    return flat_result.reshape(result.shape)


def window_bounds(spectrum: SnrSpectrum, mics: np.ndarray, positions: np.ndarray, window_ends: np.ndarray,
                  seconds: float, band_hz: tuple[float, float] | None = None,
                  speed_of_sound: float = SPEED_OF_SOUND, prior_std: float | None = None) -> np.ndarray:
    """Per-window position bound (m) for windows ending at ``window_ends`` (seconds from the audio's start).

    The SNR of a window is the spectrum's average over the frames it overlaps; ``positions`` (windows x 3) are
    the true positions the windows are scored against.
    """
    snr = np.stack([spectrum.window_snr(end - seconds, end) for end in np.asarray(window_ends, float)])
    snr = np.moveaxis(snr, 1, 2)  # windows x bins x mics
    return position_bound(np.asarray(positions, float), mics, snr, spectrum.freqs, seconds, band_hz,
                          speed_of_sound, prior_std)
