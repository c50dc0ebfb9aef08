"""Trajectory smoothing with predictive uncertainty: the paper's GP, the robust Student-t smoother, online forms.

Which smoother runs: :func:`make_smoother` builds one by preset name. ``robust`` (the default,
:data:`DEFAULT_PRESET`) is the Student-t state-space smoother that ignores outlier frames
(:class:`RobustSmoother`); ``paper`` (the AAUTE paper's RBF GP) and ``tuned`` (Matern-5/2 learned on real
tracks) are Gaussian-process smoothers (:class:`GPSmoother`). Every smoother returns a
:class:`SmoothedTrack` (mean and std of x, y, z at the query times). :class:`OnlineSmoother` and
:func:`smooth_online` run the robust model causally or at a fixed lag, one frame at a time.

The modules, leaves first (each imports only those above it):

* ``track``: :class:`SmoothedTrack`, the :class:`Smoother` protocol, input checks, track CSV files;
* ``matern``: the Matern-5/2 SDE in closed form (numpy and torch);
* ``kalman``: the Kalman/RTS engines on that SDE (torch parallel scans for gradients, blocked numpy);
* ``gp``: :class:`GPSmoother`, its presets, backends and marginal-likelihood fit;
* ``robust``: :class:`RobustSmoother`, its presets, variational inference and EM fit;
* ``online``: :class:`OnlineSmoother` and :func:`smooth_online`;
* ``calibration``: the coverage of the truth and the std calibration factor;
* ``factory``: :func:`make_smoother` and the helpers that smooth detections, batches and files.
"""

from zoo.smoothing.calibration import calibration_factor, coverage
from zoo.smoothing.factory import (
    DEFAULT_PRESET,
    make_smoother,
    measured_rows,
    smooth_detected,
    smooth_detected_track,
    smooth_predictions,
    smooth_track_file,
)
from zoo.smoothing.gp import (
    BACKENDS,
    KERNELS,
    LOCAL_TOLERANCE,
    PAPER_TIME_UNIT,
    PRESETS,
    GPHyperparameters,
    GPSmoother,
    fit_hyperparameters,
)
from zoo.smoothing.online import OnlineRow, OnlineSmoother, smooth_online
from zoo.smoothing.robust import (
    DOF_BOUNDS,
    OFFLINE,
    ROBUST_PRESETS,
    FitReport,
    RobustFit,
    RobustHyperparameters,
    RobustSmoother,
    fit_robust_hyperparameters,
)
from zoo.smoothing.track import (
    DETECTION_COLUMNS,
    SMOOTHED_COLUMNS,
    TRACK_COLUMNS,
    TRACK_KEYS,
    Hyperparameters,
    SmoothedTrack,
    Smoother,
    TrackFileError,
    TrackPart,
    read_track_csv,
    read_tracks_csv,
    write_smoothed_csv,
    write_smoothed_tracks,
)

__all__ = [
    "BACKENDS",
    "DEFAULT_PRESET",
    "DETECTION_COLUMNS",
    "DOF_BOUNDS",
    "KERNELS",
    "LOCAL_TOLERANCE",
    "OFFLINE",
    "PAPER_TIME_UNIT",
    "PRESETS",
    "ROBUST_PRESETS",
    "SMOOTHED_COLUMNS",
    "TRACK_COLUMNS",
    "TRACK_KEYS",
    "FitReport",
    "GPHyperparameters",
    "GPSmoother",
    "Hyperparameters",
    "OnlineRow",
    "OnlineSmoother",
    "RobustFit",
    "RobustHyperparameters",
    "RobustSmoother",
    "SmoothedTrack",
    "Smoother",
    "TrackFileError",
    "TrackPart",
    "calibration_factor",
    "coverage",
    "fit_hyperparameters",
    "fit_robust_hyperparameters",
    "make_smoother",
    "measured_rows",
    "read_track_csv",
    "read_tracks_csv",
    "smooth_detected",
    "smooth_detected_track",
    "smooth_online",
    "smooth_predictions",
    "smooth_track_file",
    "write_smoothed_csv",
    "write_smoothed_tracks",
]
