"""A calibration board rendered by any of the scene's cameras, over the static table: what a site's
calibration session photographs, so `rmmdet calibrate` is tested end to end in simulation.

The board is a textured quad (an OBJ with UVs: PyBullet's TinyRenderer maps textures onto meshes,
not onto its primitive boxes) in the board frame of `shared.calibration.solve.Board`: z = 0, x along
its columns, y along its rows, origin at the first inner corner; a white margin of one square around
the pattern. The square whose corner is the origin (x, y in [-square, 0]) is black, and the pattern
has one odd and one even number of squares, so a 180 deg turn swaps the colours: the detector orders
the corners from that square, and a view cannot be read upside down.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np
import pybullet as pb
import yaml

from shared.calibration.solve import Board
from shared.scene.scene import Scene
from sim.sensors.camera import render
from sim.world import StaticWorld

PX_PER_SQUARE = 64
MARGIN_SQUARES = 1
TABLE_CLEARANCE_M = 0.001  # a board on the table lies this far above it (no z-fighting with the table)


def board_texture(board: Board) -> np.ndarray:
    """(H, W, 3) uint8 image of the board: (cols + 1) x (rows + 1) squares inside a white margin; the
    image's first row is the board's -y edge, its first column the -x edge."""
    if board.kind != "checkerboard":
        raise ValueError("the simulator renders checkerboards")
    nx, ny = board.cols + 1, board.rows + 1
    if (nx + ny) % 2 == 0:
        raise ValueError(
            f"{board.cols}x{board.rows} inner corners: one side must have an odd count of squares"
        )
    s, m = PX_PER_SQUARE, MARGIN_SQUARES * PX_PER_SQUARE
    img = np.full((ny * s + 2 * m, nx * s + 2 * m, 3), 255, np.uint8)
    for j in range(ny):
        for i in range(nx):
            if (i + j) % 2 == 0:  # square (0, 0), at the origin's -x -y side, is black
                img[m + j * s : m + (j + 1) * s, m + i * s : m + (i + 1) * s] = 0
    return img


class BoardRenderer:
    """Renders `board` at any world pose as camera `camera_id` of `scene` sees it (with the table)."""

    def __init__(self, scene: Scene, camera_id: str, board: Board) -> None:
        spec = scene.sensor(camera_id)
        if spec.camera is None:
            raise ValueError(f"{camera_id} is not a camera")
        self.scene, self.camera_id, self.board = scene, camera_id, board
        self.model = spec.camera
        self.static = StaticWorld(scene)
        self._dir = tempfile.TemporaryDirectory(prefix="rmmdet-board-")
        texture = Path(self._dir.name) / "board.png"
        cv2.imwrite(str(texture), cv2.cvtColor(board_texture(board), cv2.COLOR_RGB2BGR))
        s, margin = board.square_m, MARGIN_SQUARES * board.square_m
        x0, y0 = -s - margin, -s - margin  # the quad, board frame
        x1, y1 = board.cols * s + margin, board.rows * s + margin
        # UV v runs up the texture image (OpenGL): the image's first row, the -y edge, is v = 1
        # (tests/sim/test_board.py checks the detected corners against their projections).
        mesh = Path(self._dir.name) / "board.obj"
        mesh.write_text(
            f"v {x0} {y0} 0\nv {x1} {y0} 0\nv {x1} {y1} 0\nv {x0} {y1} 0\n"
            "vt 0 1\nvt 1 1\nvt 1 0\nvt 0 0\nvn 0 0 1\n"
            "f 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n"
        )
        cid = self.static.cid
        visual = pb.createVisualShape(pb.GEOM_MESH, fileName=str(mesh), physicsClientId=cid)
        self.body = pb.createMultiBody(0, -1, visual, [0.0, 0.0, -100.0], physicsClientId=cid)
        tex = pb.loadTexture(str(texture), physicsClientId=cid)
        pb.changeVisualShape(self.body, -1, textureUniqueId=tex, rgbaColor=[1, 1, 1, 1], physicsClientId=cid)

    def render(self, T_world_from_board: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB image with the board at `T_world_from_board` (4x4)."""
        from scipy.spatial.transform import Rotation

        cid = self.static.cid
        quat = Rotation.from_matrix(T_world_from_board[:3, :3]).as_quat()
        pb.resetBasePositionAndOrientation(
            self.body, T_world_from_board[:3, 3].tolist(), quat.tolist(), physicsClientId=cid
        )
        K = np.asarray(self.scene.K(self.camera_id))
        T = np.asarray(self.scene.T_optical_from_world(self.camera_id))
        full = (0, 0, self.model.width_px, self.model.height_px)
        rgb, _, _ = render(cid, T, K, full, self.model.near_m, self.model.far_m, segmentation=False)
        return np.ascontiguousarray(rgb)

    def close(self) -> None:
        self.static.close()
        self._dir.cleanup()

    def __enter__(self) -> BoardRenderer:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def views_in_front(
    scene: Scene,
    camera_id: str,
    board: Board,
    count: int,
    rng: np.random.Generator,
    distance_m: tuple[float, float],
) -> list[np.ndarray]:
    """`count` board poses (world, 4x4) in front of the camera, facing it within +-35 deg, at
    `distance_m` along its optical axis, centred near the axis: a calibration session's views."""
    from scipy.spatial.transform import Rotation

    T_world_from_optical = np.linalg.inv(np.asarray(scene.T_optical_from_world(camera_id)))
    centre_board = np.array(
        [(board.cols - 1) * board.square_m / 2, (board.rows - 1) * board.square_m / 2, 0.0]
    )
    poses = []
    for _ in range(count):
        d = rng.uniform(*distance_m)
        # in the optical frame: the board's normal points back at the camera (-z), tilted
        tilt = Rotation.from_euler("xyz", rng.uniform(-35, 35, 3) * np.array([1, 1, 0.3]), degrees=True)
        R_opt_board = tilt.as_matrix() @ np.diag([1.0, -1.0, -1.0])  # board z towards the camera
        offset = np.array([rng.uniform(-0.15, 0.15) * d, rng.uniform(-0.1, 0.1) * d, d])
        T_opt_board = np.eye(4)
        T_opt_board[:3, :3] = R_opt_board
        T_opt_board[:3, 3] = offset - R_opt_board @ centre_board
        poses.append(T_world_from_optical @ T_opt_board)
    return poses


def standing_on_table(
    scene: Scene, camera_id: str, board: Board, ahead_m: float, side_m: float = 0.0
) -> np.ndarray:
    """A pose (world, 4x4) of `board` standing upright on the table `ahead_m` in front of the camera's
    foot along its heading and `side_m` to its left, its printed face turned to the camera's foot, its
    lowest row of squares `TABLE_CLEARANCE_M` above the table: a surveyed target (every corner's
    world position known), as a site surveys one with a total station."""
    T_world_from_body = np.asarray(scene.T_world_from_sensor(camera_id))
    forward = T_world_from_body[:3, 0].copy()
    forward[2] = 0.0
    forward /= np.linalg.norm(forward)
    left = np.array([-forward[1], forward[0], 0.0])
    foot = T_world_from_body[:3, 3] * np.array([1.0, 1.0, 0.0])
    centre = foot + forward * ahead_m + left * side_m
    # board x across (to the camera's right), y up, z (printed face) towards the camera
    R = np.column_stack([-left, [0.0, 0.0, 1.0], -forward])
    width = (board.cols - 1) * board.square_m
    # the first inner corner: one square and the white margin above the bottom edge, at the left end
    lift = (1 + MARGIN_SQUARES) * board.square_m + TABLE_CLEARANCE_M
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre + left * width / 2 + np.array([0.0, 0.0, lift])
    return T


def standing_placements(scene: Scene, camera_id: str, board: Board) -> list[np.ndarray]:
    """Board poses standing on the table across the camera's lower view: two rows (0.45 and 0.6 of
    the distance at which its optical axis meets the table) by three across (centre, +-15 % of that
    distance to the sides), to be surveyed and photographed for the camera's pose."""
    T_world_from_body = np.asarray(scene.T_world_from_sensor(camera_id))
    height = T_world_from_body[2, 3]
    down = -T_world_from_body[2, 0]  # sine of the camera's pitch below the horizon
    axis_m = height / np.tan(np.arcsin(np.clip(down, 0.05, 0.99)))
    return [
        standing_on_table(scene, camera_id, board, axis_m * ahead, axis_m * side)
        for ahead in (0.45, 0.6)
        for side in (-0.15, 0.0, 0.15)
    ]


def render_views(
    scene: Scene, camera_id: str, board: Board, out: Path, views: int, seed: int = 0
) -> list[Path]:
    """`views` images of `board` in front of the camera (0.3-0.6 m away) as PNGs in `out`: a session's
    intrinsics photographs."""
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    with BoardRenderer(scene, camera_id, board) as renderer:
        for k, T in enumerate(
            views_in_front(scene, camera_id, board, views, np.random.default_rng(seed), (0.3, 0.6))
        ):
            paths.append(out / f"{camera_id}_view_{k:02d}.png")
            cv2.imwrite(str(paths[-1]), cv2.cvtColor(renderer.render(T), cv2.COLOR_RGB2BGR))
    return paths


def render_standing(scene: Scene, camera_id: str, board: Board, board_text: str, out: Path) -> Path:
    """The board standing on the table at `standing_placements`, one PNG each in `out`, and the survey
    file naming each image with the board's surveyed pose (`board_text` as the survey's `board`)."""
    from shared.calibration.workflow import pose_spec

    out.mkdir(parents=True, exist_ok=True)
    placements = []
    with BoardRenderer(scene, camera_id, board) as renderer:
        for k, T in enumerate(standing_placements(scene, camera_id, board)):
            name = f"{camera_id}_standing_{k:02d}.png"
            cv2.imwrite(str(out / name), cv2.cvtColor(renderer.render(T), cv2.COLOR_RGB2BGR))
            placements.append({"image": name, "pose": pose_spec(T).model_dump(exclude_none=True)})
    survey = out / "survey.yaml"
    survey.write_text(yaml.safe_dump({"board": board_text, "placements": placements}, sort_keys=False))
    return survey
