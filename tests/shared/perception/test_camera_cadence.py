"""The MEC's camera work: with a lidar live the camera detector runs on every n-th frame only (on sim
ticks the frames `Scene.captures_on` names, the ones the MEC asks its cameras to capture), and a frame that
repeats its camera's previous one is neither decoded nor detected again."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from shared.detection.interface import DetectorInputError
from shared.paths import DEFAULT_SCENE
from shared.perception.config import MecSettings
from shared.perception.decode import FrameDecoder
from shared.perception.pipeline import AgentInputs, AgentPipeline
from shared.scene.scene import Scene
from tests.shared.perception.stubs import CountingCameras, NoCars

TICK_HZ = 60.0
TICKS_PER_FRAME = 6  # 10 Hz sensors


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


def pipeline(scene: Scene, cameras: CountingCameras) -> AgentPipeline:
    return AgentPipeline(scene, "agent1", MecSettings(), cameras=cameras, lidar=NoCars())


def frame(scene: Scene, tick: int, lidar: bool) -> AgentInputs:
    inputs = AgentInputs(stamp_ns=round(tick / TICK_HZ * 1e9), tick=tick)
    for cam in scene.sensors_of("agent1", "camera"):
        inputs.add("camera", cam.id, np.zeros((48, 64, 3), np.uint8))
    if lidar:
        for lid in scene.sensors_of("agent1", "lidar"):
            inputs.add("lidar", lid.id, np.zeros((0, 4), np.float32))
    return inputs


def test_on_sim_ticks_the_detector_runs_where_the_demanded_frames_fall(scene: Scene) -> None:
    cams = CountingCameras()
    pipe = pipeline(scene, cams)
    pipe.tick_hz = TICK_HZ
    n = MecSettings().detectors.camera_every_n_with_lidar
    assert n > 1
    ticks = [k * TICKS_PER_FRAME for k in range(1, 3 * n + 1)]  # starts off the cadence's phase
    ran = []
    for tick in ticks:
        before = len(cams.calls)
        pipe.process(frame(scene, tick, lidar=True))
        ran.append(cams.calls[-1] if len(cams.calls) > before else 0)
    # The 4 cameras are staggered: one image per frame on frames 0 .. 3 of each n, none on the rest.
    assert len(pipe.camera_ids) == 4 and n >= 5
    assert ran == [1 if (t // TICKS_PER_FRAME) % n < 4 else 0 for t in ticks]
    for k, camera in enumerate(pipe.camera_ids):
        assert pipe.cameras_due(True, (n + k) * TICKS_PER_FRAME) == {camera}
    assert all(pipe.cameras_due(True, (n + k) * TICKS_PER_FRAME) == frozenset() for k in range(4, n))


def test_without_a_lidar_every_frame_runs_the_detector(scene: Scene) -> None:
    cams = CountingCameras()
    pipe = pipeline(scene, cams)
    pipe.tick_hz = TICK_HZ
    for k in range(1, 6):
        pipe.process(frame(scene, k * TICKS_PER_FRAME, lidar=False))
    assert cams.calls == [4] * 5


def test_without_ticks_every_nth_processed_frame_runs_the_detector(scene: Scene) -> None:
    cams = CountingCameras()
    pipe = pipeline(scene, cams)  # real sensors: no tick rate
    n = MecSettings().detectors.camera_every_n_with_lidar
    for _ in range(2 * n):
        pipe.process(frame(scene, 0, lidar=True))
    assert len(cams.calls) == 2


def jpeg(value: int) -> CompressedImage:
    ok, buf = cv2.imencode(".jpg", np.full((48, 64, 3), value, np.uint8))
    assert ok
    return CompressedImage(format="jpeg", data=bytes(buf))


def test_a_repeated_camera_frame_is_decoded_once_and_its_boxes_reused(scene: Scene) -> None:
    decoder = FrameDecoder()
    first = decoder.decode("camera", "cam_11", jpeg(40))
    again = decoder.decode("camera", "cam_11", jpeg(40))
    assert again is first and not first.flags.writeable and decoder.repeats == 1
    other = decoder.decode("camera", "cam_12", jpeg(40))  # another camera: its own history
    changed = decoder.decode("camera", "cam_11", jpeg(200))
    assert other is not first and changed is not first and decoder.repeats == 1

    cams = CountingCameras()
    pipe = pipeline(scene, cams)
    assert set(pipe.detect_2d({"cam_11": first, "cam_12": other})) == {"cam_11", "cam_12"}
    assert set(pipe.detect_2d({"cam_11": again, "cam_12": other})) == {"cam_11", "cam_12"}
    pipe.detect_2d({"cam_11": changed})
    assert cams.calls == [2, 1]  # the repeat ran nothing; the changed frame ran alone
    assert pipe.counts["camera/repeated_frame"] == 2
    writable = np.zeros((48, 64, 3), np.uint8)  # not from a FrameDecoder: never taken as a repeat
    pipe.detect_2d({"cam_13": writable})
    pipe.detect_2d({"cam_13": writable})
    assert cams.calls == [2, 1, 1, 1]


def test_an_image_detected_on_arrival_is_not_detected_again_with_its_frame(scene: Scene) -> None:
    decoder = FrameDecoder()
    cams = CountingCameras()
    pipe = pipeline(scene, cams)
    first = decoder.image("cam_11", jpeg(40))
    assert pipe.detect_ahead("cam_11", first)
    other = decoder.image("cam_12", jpeg(90))
    assert set(pipe.detect_2d({"cam_11": first, "cam_12": other})) == {"cam_11", "cam_12"}
    assert cams.calls == [1, 1]  # cam_11 ahead; only cam_12 with the frame
    assert pipe.counts["camera/repeated_frame"] == 0  # ahead is not a repeat
    # The same bytes again: a repeat, neither detected ahead nor with the frame.
    again = decoder.image("cam_11", jpeg(40))
    assert again is first and not pipe.detect_ahead("cam_11", again)
    pipe.detect_2d({"cam_11": again})
    assert cams.calls == [1, 1] and pipe.counts["camera/repeated_frame"] == 1
    # Detected ahead on one image, joined with another (a newer frame): that one is detected.
    changed = decoder.image("cam_11", jpeg(200))
    assert pipe.detect_ahead("cam_11", changed)
    pipe.detect_2d({"cam_11": decoder.image("cam_11", jpeg(120))})
    assert cams.calls == [1, 1, 1, 1]
    assert not pipe.detect_ahead("cam_99", changed)  # not this agent's camera


class RejectingCameras(CountingCameras):
    def detect(self, images: list[np.ndarray]) -> list[np.ndarray]:
        super().detect(images)
        raise DetectorInputError("not an image")


def test_an_image_the_detector_rejects_ahead_is_left_for_its_frame(scene: Scene) -> None:
    cams = RejectingCameras()
    pipe = pipeline(scene, cams)
    image = FrameDecoder().image("cam_11", jpeg(40))
    assert not pipe.detect_ahead("cam_11", image)  # no exception out of the MEC's receive loop
    result = pipe.process(frame(scene, 0, lidar=False))
    assert result.counts["rejected/camera_input"] == 1 and len(cams.calls) == 2
