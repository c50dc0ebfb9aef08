"""Outdoor sound propagation physics: speed of sound, ISO 9613-1 absorption, A-weighting, ground.

Sources (tags as in ``docs/simulation_sources.md``): speed of sound and ISO 9613-1 air absorption,
section 2.1-2.2 [M/V, S25]; the A-weighting curve of IEC 61672-1 [M]; ground reflection as an
image source, hard surfaces Q ~ 0.95-1.0 and grass from the Delany-Bazley impedance with a flow
resistivity of 100-300 kPa s/m^2, section 2.4 [M].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

T0_KELVIN = 293.15
T01_KELVIN = 273.16  #: triple point of water (ISO 9613-1)
P_REF_KPA = 101.325
AIR_DENSITY = 1.16  #: kg/m^3 at 30 C, sea level [M]


def speed_of_sound(temperature_c: float) -> float:
    """Speed of sound in air (m/s): c = 331.3 sqrt(1 + T/273.15); 349.0 m/s at 30 C."""
    return 331.3 * float(np.sqrt(1.0 + temperature_c / 273.15))


def absorption_db_per_m(
    frequency: np.ndarray, temperature_c: float = 30.0, humidity_pct: float = 75.0, pressure_kpa: float = P_REF_KPA
) -> np.ndarray:
    """Pure-tone atmospheric absorption coefficient alpha(f) in dB/m (ISO 9613-1:1993, eq. 3-5).

    At 30 C and 75 % RH this gives 7.4 dB/km at 1 kHz and 58 dB/km at 8 kHz
    (``simulation_sources.md`` section 2.2 table).
    """
    f = np.asarray(frequency, dtype=np.float64)
    temp = temperature_c + 273.15
    p_rel = pressure_kpa / P_REF_KPA
    c_sat = -6.8346 * (T01_KELVIN / temp) ** 1.261 + 4.6151
    h = humidity_pct * 10.0**c_sat / p_rel  # molar concentration of water vapour (%)
    fr_o = p_rel * (24.0 + 4.04e4 * h * (0.02 + h) / (0.391 + h))
    t_rel = temp / T0_KELVIN
    fr_n = p_rel * t_rel**-0.5 * (9.0 + 280.0 * h * np.exp(-4.170 * (t_rel ** (-1 / 3) - 1)))
    relax = (temp / T0_KELVIN) ** -2.5 * (
        0.01275 * np.exp(-2239.1 / temp) / (fr_o + f**2 / fr_o) + 0.1068 * np.exp(-3352.0 / temp) / (fr_n + f**2 / fr_n)
    )
    return 8.686 * f**2 * (1.84e-11 / p_rel * (temp / T0_KELVIN) ** 0.5 + relax)


def a_weighting_db(frequency: np.ndarray) -> np.ndarray:
    """A-weighting gain in dB (IEC 61672-1 analytic form; 0 dB at 1 kHz, -inf at DC)."""
    f2 = np.asarray(frequency, dtype=np.float64) ** 2
    with np.errstate(divide="ignore"):
        ra = 12194.0**2 * f2**2 / (
            (f2 + 20.6**2) * np.sqrt((f2 + 107.7**2) * (f2 + 737.9**2)) * (f2 + 12194.0**2)
        )
        return 20.0 * np.log10(ra) + 2.0


@dataclass(frozen=True)
class GroundSurface:
    """Acoustic ground: a constant reflection factor (hard) or a Delany-Bazley porous surface."""

    name: str
    reflection_factor: float | None = None  #: hard surfaces: |R| independent of f and angle
    flow_resistivity: float | None = None  #: Pa s/m^2, porous surfaces (Delany-Bazley)

    def reflection_coefficient(self, frequency: np.ndarray, incidence_cos: np.ndarray | float) -> np.ndarray:
        """Plane-wave reflection coefficient R(f, theta) for a locally reacting surface.

        ``incidence_cos`` is cos of the angle from the surface normal. The phase convention is
        exp(+i omega t), which matches numpy's inverse FFT, so R multiplies STFT bins directly.
        """
        f = np.asarray(frequency, dtype=np.float64)
        cos_theta = np.asarray(incidence_cos, dtype=np.float64)
        if self.reflection_factor is not None:
            return np.full(np.broadcast(f, cos_theta).shape, self.reflection_factor, dtype=np.complex128)
        x = AIR_DENSITY * np.maximum(f, 1.0) / self.flow_resistivity
        z_rel = 1.0 + 0.0571 * x**-0.754 - 1j * 0.087 * x**-0.732  # normalised impedance Z/(rho c)
        return (z_rel * cos_theta - 1.0) / (z_rel * cos_theta + 1.0)


#: Concrete rooftop (the MMAUD V1 site) and asphalt: hard, Q = 0.95 (``simulation_sources.md`` 2.4 [M]).
CONCRETE = GroundSurface("concrete", reflection_factor=0.95)
ASPHALT = GroundSurface("asphalt", reflection_factor=0.95)
#: Grass: Delany-Bazley with sigma = 200 kPa s/m^2 (middle of 100-300, ``simulation_sources.md`` 2.4 [M]).
GRASS = GroundSurface("grass", flow_resistivity=2.0e5)
GROUNDS = {g.name: g for g in (CONCRETE, ASPHALT, GRASS)}


def level_to_pressure(spl_db: float) -> float:
    """RMS pressure (Pa) of a sound pressure level in dB re 20 uPa."""
    return 20e-6 * 10.0 ** (spl_db / 20.0)
