"""Multi-object tracking of the edge (MEC) service: plain numpy modules, no bus inside.

Modules
-------
- :mod:`shared.tracking.kalman`: batched linear Kalman filter on [x, y, vx, vy] (constant-velocity or the
  paper's identity model) and the radar range-rate EKF update.
- :mod:`shared.tracking.tracker`: `MultiObjectTracker` (gated Hungarian association, M-of-N confirmation,
  coasting, heading from mod-pi yaw and motion) and its `TrackerConfig`.
"""

from shared.tracking.kalman import (
    POSITION_H,
    KalmanUpdate,
    MotionKind,
    MotionModel,
    predict,
    process_noise,
    range_rate_jacobian,
    transition_matrix,
    update,
    update_range_rate,
)
from shared.tracking.tracker import (
    MODALITIES,
    Measurement,
    MultiObjectTracker,
    RangeRate,
    Track,
    TrackerConfig,
    TrackState,
)

__all__ = [
    "MODALITIES",
    "POSITION_H",
    "KalmanUpdate",
    "Measurement",
    "MotionKind",
    "MotionModel",
    "MultiObjectTracker",
    "RangeRate",
    "Track",
    "TrackState",
    "TrackerConfig",
    "predict",
    "process_noise",
    "range_rate_jacobian",
    "transition_matrix",
    "update",
    "update_range_rate",
]
