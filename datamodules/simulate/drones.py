"""The five MMAUD drone types: size, mass, rotors, acoustic and optical properties.

Sources (tags as in ``docs/simulation_sources.md``):
- sizes L x W x H and the "RCS" (= planform area L x W): MMAUD README, ``drone_charactics.png`` [V];
- masses, propeller diameters and blade counts: DJI specifications [M];
- hover rpm: Mavic 2 6150 and Phantom 4 6300 rpm from Heutschi et al. 2020 (via
  DroneSynthesis2DOA) [V]; Mavic 3, M300 and Avata scaled with n ~ sqrt(m) / D^2 from those [E];
- hover sound power LWA: Mavic 3 83 dB(A) from its EU C1 label [V]; the others estimated
  (Avata 80, Mavic 2 81, Phantom 4 84, M300 90 dB(A)) [E]; +-3 dB per flight;
- reflectivity at 905 nm: dark-grey DJI plastics 10-25 %, white Phantom 60-80 % [E].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DroneSpec:
    """Physical description of one drone type."""

    name: str
    size_m: tuple[float, float, float]  #: length, width, height (m)
    mass_kg: float
    rotors: int
    blades: int  #: blades per rotor
    prop_diameter_m: float
    hover_rpm: float
    lwa_db: float  #: A-weighted sound power at hover, dB re 1 pW
    reflectivity: float  #: diffuse reflectivity at 905 nm (0..1)
    class_id: int  #: MMAUD-V1 "Data-M" class index (TAME evaluate.py: 0 Mavic2 ... 4 M300)

    @property
    def hover_bpf_hz(self) -> float:
        """Blade-passing frequency at hover: blades x rpm / 60."""
        return self.blades * self.hover_rpm / 60.0

    @property
    def planform_area_m2(self) -> float:
        """Area seen from below (MMAUD's "RCS" column): length x width."""
        return self.size_m[0] * self.size_m[1]

    @property
    def side_area_m2(self) -> float:
        """Area seen side-on: max(length, width) x height."""
        return max(self.size_m[0], self.size_m[1]) * self.size_m[2]


DRONES: dict[str, DroneSpec] = {
    spec.name: spec
    for spec in (
        DroneSpec("mavic2", (0.322, 0.242, 0.084), 0.907, 4, 2, 0.221, 6150.0, 81.0, 0.15, 0),
        DroneSpec("mavic3", (0.283, 0.108, 0.348), 0.895, 4, 2, 0.239, 5250.0, 83.0, 0.15, 1),
        DroneSpec("phantom4", (0.350, 0.350, 0.198), 1.380, 4, 2, 0.239, 6300.0, 84.0, 0.70, 2),
        DroneSpec("avata", (0.180, 0.080, 0.180), 0.410, 4, 3, 0.074, 27000.0, 80.0, 0.12, 3),
        DroneSpec("m300", (0.810, 0.670, 0.430), 6.300, 4, 2, 0.533, 2800.0, 90.0, 0.20, 4),
    )
}


def drone_spec(name: str) -> DroneSpec:
    """Look a drone type up by name, with a clear error listing the known ones."""
    try:
        return DRONES[name]
    except KeyError:
        raise ValueError(f"unknown drone type {name!r}; known: {sorted(DRONES)}") from None


def rpm_for_thrust(spec: DroneSpec, acceleration: np.ndarray, gravity: float = 9.81) -> np.ndarray:
    """Mean rotor rpm needed for a body acceleration (N x 3, m/s^2, z up).

    Thrust balances gravity plus the acceleration, T = m |a + g z|, and rotor speed follows
    momentum theory, n ~ sqrt(T) (``simulation_sources.md`` section 1.2, "RPM change with manoeuvre").
    """
    acceleration = np.asarray(acceleration, dtype=np.float64)
    total = acceleration + np.array([0.0, 0.0, gravity])
    thrust_ratio = np.linalg.norm(total, axis=-1) / gravity
    return spec.hover_rpm * np.sqrt(np.maximum(thrust_ratio, 0.05))
