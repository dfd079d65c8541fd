"""Range checks per message type, run by the codec after parsing (NaN/Inf is checked generically).

Each check returns a short description of the first problem, or None.
"""

from __future__ import annotations

from collections.abc import Iterable

from google.protobuf.message import Message

from shared.bus.codec import register_count_cap, register_validator
from shared.bus.streams import limits
from shared.timebase import MAX_SIM_SPEED, NS_PER_S, tick_stamp_ns

#: Sanity bound for any coordinate on an 8 m x 10 m table (generous, catches unit mix-ups).
MAX_ABS_COORD_M = 1000.0
MAX_SPEED_MPS = 50.0


def _probability(name: str, value: float) -> str | None:
    return None if 0.0 <= value <= 1.0 else f"{name}={value} outside [0, 1]"


def _box3d(box: Message, where: str) -> str | None:
    size = box.size_m  # type: ignore[attr-defined]
    if min(size.x, size.y, size.z) < 0:
        return f"{where}: negative size"
    c = box.center_m  # type: ignore[attr-defined]
    if max(abs(c.x), abs(c.y), abs(c.z)) > MAX_ABS_COORD_M:
        return f"{where}: centre beyond {MAX_ABS_COORD_M} m"
    return None


def _covariance(values: Iterable[float], n: int, where: str) -> str | None:
    values = list(values)
    if not values:
        return None  # covariance is optional
    if len(values) != n * n:
        return f"{where}: covariance has {len(values)} values, expected {n * n}"
    if any(values[i * n + i] < 0 for i in range(n)):
        return f"{where}: negative variance"
    return None


def _first(problems: Iterable[str | None]) -> str | None:
    return next((p for p in problems if p), None)


def _max_objects_per_list() -> int:
    return limits().max_objects_per_list


# Lists capped at `limits.max_objects_per_list`; the codec checks them before anything iterates them.
for _type, _field in (
    ("rmmdet.v1.Detection2DArray", "detections"),
    ("rmmdet.v1.DetectedObjects", "objects"),
    ("rmmdet.v1.TrackedObjects", "objects"),
    ("rmmdet.v1.RadarScan", "targets"),
    ("rmmdet.v1.GroundTruth", "vehicles"),
):
    register_count_cap(_type, _field, _max_objects_per_list)


def _tick_rate(tick_hz: float) -> str | None:
    low, high = limits().min_tick_hz, limits().max_tick_hz
    return None if low <= tick_hz <= high else f"tick_hz={tick_hz} outside [{low}, {high}]"


def _tick_stamp(header: Message, tick_hz: float) -> str | None:
    """A sim message's stamp must be its tick's time in its run (`tick_stamp_ns`), within half a tick:
    a forged far-future tick cannot pass with a present stamp (nor the other way round)."""
    h = header
    expected_ns = tick_stamp_ns(h.epoch, h.tick, tick_hz)  # type: ignore[attr-defined]
    if abs(h.stamp.ToNanoseconds() - expected_ns) > NS_PER_S / (2 * tick_hz):  # type: ignore[attr-defined]
        return f"tick {h.tick} of epoch {h.epoch} is not stamped at its time"  # type: ignore[attr-defined]
    return None


@register_validator("rmmdet.v1.Header")
def _header(m: Message) -> str | None:
    for stamp in m.processing:  # type: ignore[attr-defined]
        if (
            stamp.HasField("start")
            and stamp.HasField("end")
            and stamp.end.ToNanoseconds() < stamp.start.ToNanoseconds()
        ):
            return f"processing stage {stamp.stage!r} ends before it starts"
    return None


@register_validator("rmmdet.v1.Detection2DArray")
def _detections_2d(m: Message) -> str | None:
    for i, d in enumerate(m.detections):  # type: ignore[attr-defined]
        if d.box.width_px < 0 or d.box.height_px < 0:
            return f"detections[{i}]: negative box size"
        problem = _probability(f"detections[{i}].score", d.score) or _first(
            _probability(f"detections[{i}].classification", h.probability) for h in d.classification
        )
        if problem:
            return problem
    return None


@register_validator("rmmdet.v1.DetectedObjects")
def _detected(m: Message) -> str | None:
    for i, o in enumerate(m.objects):  # type: ignore[attr-defined]
        problem = (
            _probability(f"objects[{i}].existence_probability", o.existence_probability)
            or _box3d(o.box, f"objects[{i}].box")
            or _first(_probability(f"objects[{i}].classification", h.probability) for h in o.classification)
        )
        if problem:
            return problem
    return None


@register_validator("rmmdet.v1.TrackedObjects")
def _tracked(m: Message) -> str | None:
    seen: set[int] = set()
    for i, o in enumerate(m.objects):  # type: ignore[attr-defined]
        if o.track_id in seen:
            return f"objects[{i}]: duplicate track_id {o.track_id}"
        seen.add(o.track_id)
        v = o.velocity_mps
        problem = (
            _probability(f"objects[{i}].existence_probability", o.existence_probability)
            or _box3d(o.box, f"objects[{i}].box")
            or _covariance(o.position_covariance_m2, 3, f"objects[{i}].position")
            or _covariance(o.velocity_covariance_m2ps2, 3, f"objects[{i}].velocity")
            or (f"objects[{i}]: negative yaw variance" if o.yaw_variance_rad2 < 0 else None)
            or (
                f"objects[{i}]: speed beyond {MAX_SPEED_MPS} m/s"
                if max(abs(v.x), abs(v.y), abs(v.z)) > MAX_SPEED_MPS
                else None
            )
        )
        if problem:
            return problem
    for s in m.inputs:  # type: ignore[attr-defined]
        if s.age_s < 0 and s.age_s != -1:
            return f"input {s.sensor_id}: negative age"
    return None


@register_validator("rmmdet.v1.RadarScan")
def _radar(m: Message) -> str | None:
    for i, t in enumerate(m.targets):  # type: ignore[attr-defined]
        if t.range_m < 0:
            return f"targets[{i}]: negative range"
        if abs(t.range_rate_mps) > MAX_SPEED_MPS:
            return f"targets[{i}]: |range rate| beyond {MAX_SPEED_MPS} m/s"
    return None


@register_validator("rmmdet.v1.CalibrationSet")
def _calibration(m: Message) -> str | None:
    ids: set[str] = set()
    for s in m.sensors:  # type: ignore[attr-defined]
        if s.sensor_id in ids:
            return f"duplicate sensor_id {s.sensor_id}"
        ids.add(s.sensor_id)
        q = s.world_from_sensor.orientation
        norm2 = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w
        if abs(norm2 - 1.0) > 1e-6:
            return f"{s.sensor_id}: orientation is not a unit quaternion"
        if s.rate_hz < 0:
            return f"{s.sensor_id}: negative rate"
        if s.WhichOneof("model") == "camera":
            c = s.camera
            if c.width_px == 0 or c.height_px == 0 or c.fx_px <= 0 or c.fy_px <= 0:
                return f"{s.sensor_id}: invalid camera intrinsics"
    return None


@register_validator("rmmdet.v1.TrafficMap")
def _traffic(m: Message) -> str | None:
    g = m.grid  # type: ignore[attr-defined]
    cells = g.column_count * g.row_count
    if cells > limits().max_grid_cells:
        return f"grid of {g.column_count} x {g.row_count} cells, more than {limits().max_grid_cells}"
    for name in ("vehicle_count", "mean_speed_mps", "speed_samples"):
        n = len(getattr(g, name))
        if n not in (0, cells):
            return f"grid.{name} has {n} cells, expected {cells}"
    if cells and g.cell_size_m <= 0:
        return "grid.cell_size_m must be positive"
    for lane in m.lanes:  # type: ignore[attr-defined]
        if lane.density_veh_per_m < 0 or lane.mean_speed_mps < 0:
            return f"lane {lane.lane_id}: negative density or speed"
    return None


@register_validator("rmmdet.v1.RoutePlan")
def _route_plan(m: Message) -> str | None:
    if not m.vehicle_id or not m.plan_id:  # type: ignore[attr-defined]
        return "plan without vehicle_id or plan_id"
    if not 1 <= m.version <= limits().max_plan_version:  # type: ignore[attr-defined]
        return f"plan version {m.version} outside [1, {limits().max_plan_version}]"  # type: ignore[attr-defined]
    if len(m.signature) > 64 or len(m.key_id) > 64:  # type: ignore[attr-defined]
        return "oversized signature or key id"
    if not m.lane_ids:  # type: ignore[attr-defined]
        return "plan without lanes"
    return None


@register_validator("rmmdet.v1.RouteRequest")
def _route_request(m: Message) -> str | None:
    if not m.vehicle_id:  # type: ignore[attr-defined]
        return "request without vehicle_id"
    if m.lane_progress_m < 0:  # type: ignore[attr-defined]
        return "negative lane progress"
    if m.current_plan_version > limits().max_claimed_plan_version:  # type: ignore[attr-defined]
        return f"current_plan_version beyond {limits().max_claimed_plan_version}"
    return None


@register_validator("rmmdet.v1.GroundTruth")
def _ground_truth(m: Message) -> str | None:
    if problem := (
        _tick_rate(m.tick_hz)  # type: ignore[attr-defined]
        or _tick_stamp(m.header, m.tick_hz)  # type: ignore[attr-defined]
    ):
        return problem
    ids: set[str] = set()
    for v in m.vehicles:  # type: ignore[attr-defined]
        if v.vehicle_id in ids:
            return f"duplicate vehicle_id {v.vehicle_id}"
        ids.add(v.vehicle_id)
        problem = _box3d(v.box, f"vehicle {v.vehicle_id}")
        if problem:
            return problem
    return None


@register_validator("rmmdet.v1.SimClock")
def _sim_clock(m: Message) -> str | None:
    if m.real_time_factor < 0 or not 0 <= m.target_speed <= MAX_SIM_SPEED:  # type: ignore[attr-defined]
        return f"negative real-time factor, or target speed outside [0, {MAX_SIM_SPEED:g}]"
    if not m.step_s > 0:  # type: ignore[attr-defined]
        return "step_s must be > 0"
    tick_hz = 1.0 / m.step_s  # type: ignore[attr-defined]
    if (problem := _tick_rate(tick_hz)) or (problem := _tick_stamp(m.header, tick_hz)):  # type: ignore[attr-defined]
        return problem
    if m.sim_time.ToNanoseconds() != m.header.stamp.ToNanoseconds():  # type: ignore[attr-defined]
        return "sim_time differs from the header stamp"
    return None


MAX_EVERY_N = 1000  # a capture demand beyond this is a unit mix-up, not a cadence


@register_validator("rmmdet.v1.CaptureDemand")
def _capture_demand(m: Message) -> str | None:
    if not 1 <= m.every_n <= MAX_EVERY_N:  # type: ignore[attr-defined]
        return f"every_n={m.every_n} outside [1, {MAX_EVERY_N}]"  # type: ignore[attr-defined]
    if not m.valid_for_s > 0:  # type: ignore[attr-defined]
        return "valid_for_s must be > 0"
    return None


@register_validator("foxglove.CompressedImage")
def _compressed_image(m: Message) -> str | None:
    if m.format not in ("jpeg", "png", "webp"):  # type: ignore[attr-defined]
        return f"unsupported image format {m.format!r}"  # type: ignore[attr-defined]
    if not m.data:  # type: ignore[attr-defined]
        return "empty image"
    return None


@register_validator("foxglove.PointCloud")
def _point_cloud(m: Message) -> str | None:
    stride = m.point_stride  # type: ignore[attr-defined]
    n_bytes = len(m.data)  # type: ignore[attr-defined]
    if n_bytes and stride == 0:
        return "point_stride is 0"
    if stride and n_bytes % stride:
        return f"data length {n_bytes} is not a multiple of point_stride {stride}"
    for f in m.fields:  # type: ignore[attr-defined]
        if f.offset >= max(stride, 1):
            return f"field {f.name} offset {f.offset} beyond stride {stride}"
    return None
