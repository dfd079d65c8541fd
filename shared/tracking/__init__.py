"""Multi-object tracking of the edge (MEC) service: plain numpy modules, no bus inside.

Modules (import them directly; this package re-exports nothing)
---------------------------------------------------------------
- :mod:`shared.tracking.tracker`: `MultiObjectTracker` (one step per fused frame: predict, associate,
  update, lifecycle, heading) and its `TrackerConfig`.
- :mod:`shared.tracking.measurement`: the input (`Measurement`, `RangeRate`), its stacking and counted
  rejection, and the layout of the smoothed attributes.
- :mod:`shared.tracking.association`: gated global-nearest-neighbour assignment (Hungarian).
- :mod:`shared.tracking.kalman`: batched linear Kalman filter on [x, y, vx, vy] (constant-velocity or
  the paper's identity model) and the radar range-rate EKF update.
- :mod:`shared.tracking.track_table`: the tracks as columns, `TrackState`, the published `Track`.
- :mod:`shared.tracking.heading`: yaw from a mod-pi axis with its sign from heading or motion.
"""
