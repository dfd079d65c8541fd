"""Pictures of the simulated sand table: a bird's-eye map and one frame per camera.

    rmmdet snapshot --out docs/images [--seed 0] [--at-s 20]

The traffic runs lock-step for `at_s` simulated seconds; then every camera is captured (the same
renderer the sensor services use, with its ground-truth visible boxes drawn in) and a top-down map is
drawn: the road texture, lane directions, junctions with the paper's flow-count numbers, areas,
buildings, the vehicles at that instant, and every sensor with its field of view (cameras: horizontal
FOV out to `camera_fov_m`; radars: azimuth FOV out to `radar_fov_m`; lidars: a ring at `lidar_ring_m`,
they see 360 deg: `BirdsEyeSettings`, sim/config.py, scaled to the scene).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from shared.scene.scale import SiteScale, at_scale
from shared.scene.scene import Scene
from sim.config import BirdsEyeSettings, SimSettings
from sim.lockstep import LockstepSim
from sim.sensors.camera import CameraFrame
from sim.world import road_texture

SENSOR_BGR = {"camera": (255, 160, 0), "lidar": (0, 200, 255), "radar": (60, 60, 255)}
AREA_BGR = (255, 255, 255)
VEHICLE_OUTLINE_BGR = (0, 0, 0)
TEXT_BGR = (255, 255, 255)
LABEL_BGR = (0, 255, 0)
FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass(frozen=True)
class TablePixels:
    """World metres <-> bird's-eye pixels (row 0 = the table's max-y edge, as road_texture)."""

    x0_m: float
    y_top_m: float
    px_per_m: float

    @classmethod
    def of(cls, scene: Scene, px_per_m: float) -> TablePixels:
        t = scene.spec.table
        return cls(t.origin_m[0], t.origin_m[1] + t.size_y_m, px_per_m)

    def __call__(self, xy_m: np.ndarray) -> np.ndarray:
        xy = np.atleast_2d(np.asarray(xy_m, float))[:, :2]
        return np.column_stack([(xy[:, 0] - self.x0_m), (self.y_top_m - xy[:, 1])]) * self.px_per_m

    def point(self, xy_m: np.ndarray | tuple[float, ...]) -> tuple[int, int]:
        u, v = self(np.asarray(xy_m, float)[:2])[0]
        return round(u), round(v)


def _wedge(origin_xy: np.ndarray, yaw_rad: float, fov_rad: float, radius_m: float) -> np.ndarray:
    angles = yaw_rad + np.linspace(-fov_rad / 2, fov_rad / 2, 24)
    arc = origin_xy + radius_m * np.column_stack([np.cos(angles), np.sin(angles)])
    return np.vstack([origin_xy, arc])


def _text(img: np.ndarray, text: str, at: tuple[int, int], scale: float = 0.45, bgr=TEXT_BGR) -> None:
    cv2.putText(img, text, at, FONT, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, at, FONT, scale, bgr, 1, cv2.LINE_AA)


def birds_eye(
    scene: Scene,
    vehicles: list[tuple[str, float, float, float]] | None = None,
    drawing: BirdsEyeSettings | None = None,
) -> np.ndarray:
    """BGR top-down map; `vehicles` = (id, x_m, y_m, yaw_rad) to draw; `drawing` (default: the
    defaults) at the scene's scale."""
    draw = at_scale(drawing or BirdsEyeSettings(), SiteScale.of(scene.spec))
    px_per_m = draw.px_per_m
    px = TablePixels.of(scene, px_per_m)
    img = cv2.cvtColor(road_texture(scene, px_per_m=px_per_m), cv2.COLOR_RGB2BGR)
    deck = None if scene.spec.road is None else scene.spec.road.deck
    for lane in scene.spec.lanes:  # the viaduct deck (not in the ground texture) and lane directions
        pts = np.asarray(scene.lane_centreline(lane.id))
        on_deck = pts[:, 2] > deck.min_z_m if deck is not None else np.zeros(len(pts), bool)
        if deck is not None and on_deck.any():
            cv2.polylines(
                img,
                [px(pts[on_deck]).astype(np.int32)],
                False,
                (150, 158, 158),
                round(deck.width_m * px_per_m),
            )
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1))])
        for at in np.arange(draw.arrow_every_m / 2, s[-1], draw.arrow_every_m):
            i = int(np.searchsorted(s, at))
            j = min(i + 3, len(pts) - 1)
            if j > i:
                cv2.arrowedLine(
                    img, px.point(pts[i]), px.point(pts[j]), (255, 255, 255), 1, cv2.LINE_AA, 0, 0.6
                )
    for obj in scene.spec.static_objects:
        cx, cy = obj.position_m[:2]
        bgr = tuple(int(255 * c) for c in obj.rgba[2::-1])
        if obj.kind != "cylinder":  # a box, or a signal head's box housing
            rect = ((cx, cy), (obj.size_m[0], obj.size_m[1]), math.degrees(obj.yaw_rad))
            corners = cv2.boxPoints(rect)
            cv2.fillPoly(img, [px(corners).astype(np.int32)], bgr)
        else:
            cv2.circle(img, px.point((cx, cy)), max(2, round(obj.size_m[0] / 2 * px_per_m)), bgr, -1)
    for area in scene.spec.areas:
        poly = px(np.asarray(area.polygon_m)).astype(np.int32)
        cv2.polylines(img, [poly], True, AREA_BGR, 1, cv2.LINE_AA)
        u, v = poly.min(axis=0)
        _text(img, area.name, (int(u) + 4, int(v) + 16), 0.5)
    for junction in scene.spec.junctions:
        u, v = px.point(junction.position_m)
        cv2.circle(img, (u, v), 14, (0, 215, 255), -1, cv2.LINE_AA)
        cv2.putText(img, str(junction.number), (u - 6, v + 6), FONT, 0.6, (0, 0, 0), 2, cv2.LINE_AA)
    overlay = img.copy()
    for spec in scene.spec.sensors:
        T = np.asarray(scene.T_world_from_sensor(spec.id))
        origin = T[:2, 3]
        yaw = math.atan2(T[1, 0], T[0, 0])
        bgr = SENSOR_BGR[spec.kind]
        if spec.camera is not None:
            wedge = _wedge(origin, yaw, spec.camera.hfov_rad, draw.camera_fov_m)
        elif spec.radar is not None:
            wedge = _wedge(origin, yaw, spec.radar.hfov_rad, min(spec.radar.max_range_m, draw.radar_fov_m))
        else:
            wedge = None
            ring_px = round(draw.lidar_ring_m * px_per_m)
            cv2.circle(overlay, px.point(origin), ring_px, bgr, 2, cv2.LINE_AA)
        if wedge is not None:
            cv2.fillPoly(overlay, [px(wedge).astype(np.int32)], bgr, cv2.LINE_AA)
    img = cv2.addWeighted(overlay, 0.25, img, 0.75, 0)
    for spec in scene.spec.sensors:
        u, v = px.point(scene.T_world_from_sensor(spec.id)[:2, 3])
        cv2.circle(img, (u, v), 5, SENSOR_BGR[spec.kind], -1, cv2.LINE_AA)
        _text(img, spec.id, (u + 6, v - 4), 0.35)
    length, width = scene.spec.vehicle.length_m, scene.spec.vehicle.width_m
    for vid, x, y, yaw in vehicles or []:
        corners = cv2.boxPoints(((x, y), (length, width), math.degrees(yaw)))
        poly = px(corners).astype(np.int32)
        cv2.fillPoly(img, [poly], (40, 40, 220))
        cv2.polylines(img, [poly], True, VEHICLE_OUTLINE_BGR, 1, cv2.LINE_AA)
        _text(img, vid, px.point((x, y)), 0.35)
    legend = [("camera", "camera + FOV"), ("lidar", "lidar (ring)"), ("radar", "radar + FOV")]
    bottom = img.shape[0] - 20 * len(legend)
    for i, (kind, label) in enumerate(legend):
        cv2.circle(img, (14, bottom + 20 * i), 6, SENSOR_BGR[kind], -1, cv2.LINE_AA)
        _text(img, label, (26, bottom + 5 + 20 * i), 0.45)
    return img


def camera_picture(frame: CameraFrame, camera_id: str) -> np.ndarray:
    """BGR camera frame with its ground-truth visible boxes and the camera id."""
    img = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
    for vid, (u0, v0, u1, v1) in sorted(frame.visible_boxes.items()):
        cv2.rectangle(img, (u0, v0), (u1 - 1, v1 - 1), LABEL_BGR, 1)
        _text(img, vid, (u0, max(v0 - 3, 10)), 0.4, LABEL_BGR)
    _text(img, camera_id, (8, 20), 0.6)
    return img


def snapshot(scene: Scene, settings: SimSettings, at_s: float, out_dir: Path) -> list[Path]:
    """Run `at_s` simulated seconds, then write birds_eye.png and <camera>.png to `out_dir`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    cameras = [s.id for s in scene.sensors_of(kind="camera")]
    with LockstepSim(scene, settings, sensor_ids=cameras, labels=True) as sim:
        for _ in range(max(0, round(at_s * settings.tick_hz) - 1)):
            sim.traffic.step()
        sim.traffic.step()
        gt = sim.ground_truth()
        captures = sim.rig.capture(gt, specs=[scene.sensor(c) for c in cameras], labels=True)
    written = []
    vehicles = [(v.vehicle_id, v.box.center_m.x, v.box.center_m.y, v.box.yaw_rad) for v in gt.vehicles]
    path = out_dir / "birds_eye.png"
    cv2.imwrite(str(path), birds_eye(scene, vehicles))
    written.append(path)
    for c in captures:
        assert isinstance(c.data, CameraFrame)
        path = out_dir / f"{c.spec.id}.png"
        cv2.imwrite(str(path), camera_picture(c.data, c.spec.id))
        written.append(path)
    return written
