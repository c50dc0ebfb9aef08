"""Simulation settings shared by the tests that need a drone heard clearly while it flies."""

from __future__ import annotations

import dataclasses

from datamodules.simulate.acoustics import AudioConfig
from datamodules.simulate.ambient import AmbientConfig
from datamodules.simulate.simulator import SimulationConfig
from datamodules.simulate.trajectory import TrajectoryConfig

#: quiet air: 45 dB(A), no wind, no HVAC unit (no static source)
QUIET = AmbientConfig(level_dba=(45.0, 45.0), wind_speed=(0.0, 0.0), hvac=False)
#: always flying (no hover: the clock calibration needs the geometry to change)
FLYING = TrajectoryConfig(hover_probability=0.0, cruise_speed_median=3.0, cruise_speed_sigma=0.1)


def flying_m300(duration: float, ambient: AmbientConfig = QUIET, **audio) -> SimulationConfig:
    """A loud drone (an M300) flying for ``duration`` seconds, audio only; ``audio`` sets
    :class:`~datamodules.simulate.acoustics.AudioConfig` fields (clock offsets, drifts)."""
    return SimulationConfig(duration=duration, drone="m300", camera=False, lidar_sensors=(), trajectory=FLYING,
                            audio=dataclasses.replace(AudioConfig(), ambient=ambient, **audio))
