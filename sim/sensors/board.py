"""A calibration board rendered by any of the scene's cameras, over the static table: what a site's
calibration session photographs, so `rmmdet calibrate` is tested end to end in simulation.

The board is a textured quad (an OBJ with UVs: PyBullet's TinyRenderer maps textures onto meshes,
not onto its primitive boxes) in the board frame of `shared.calibration.solve.Board`: z = 0, x along
its columns, y along its rows, origin at the first inner corner; a white margin of one square around
the pattern. The square whose corner is the origin (x, y in [-square, 0]) is black, and the pattern
has one odd and one even number of squares, so a 180 deg turn swaps the colours: the detector orders
the corners from that square, and a view cannot be read upside down. Where the session puts the board
(distances, search grid, clearances) is `BoardSessionSettings` (sim/config.py), scaled to the scene.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np
import pybullet as pb
import yaml

from shared.calibration.solve import Board
from shared.geometry.camera import project_points
from shared.scene.scale import SiteScale, at_scale
from shared.scene.scene import Scene
from sim.config import BoardSessionSettings
from sim.sensors.camera import render
from sim.world import StaticWorld

PX_PER_SQUARE = 64
MARGIN_SQUARES = 1


def board_session(scene: Scene, session: BoardSessionSettings | None = None) -> BoardSessionSettings:
    """`session` (default: the defaults) at `scene`'s scale (idempotent)."""
    return at_scale(session or BoardSessionSettings(), SiteScale.of(scene.spec))


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
        x0, y0, x1, y1 = outline_extent(board)  # the quad, board frame
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
        parked = [0.0, 0.0, self.static.settings.parked_z_m]  # until `render` puts it somewhere
        self.body = pb.createMultiBody(0, -1, visual, parked, physicsClientId=cid)
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


def standing_on(
    scene: Scene,
    camera_id: str,
    board: Board,
    ahead_m: float,
    side_m: float = 0.0,
    surface_z_m: float = 0.0,
    session: BoardSessionSettings | None = None,
) -> np.ndarray:
    """A pose (world, 4x4) of `board` standing upright on the surface at height `surface_z_m` (the
    table, 0, or the viaduct's deck) `ahead_m` in front of the camera's foot along its heading and
    `side_m` to its left, its printed face turned to the camera's foot, its lowest row of squares the
    session's `table_clearance_m` above the surface: a surveyed target (every corner's world position
    known), as a site surveys one with a total station."""
    clearance_m = board_session(scene, session).table_clearance_m
    forward, left, foot = _heading(scene, camera_id)
    centre = foot + forward * ahead_m + left * side_m
    # board x across (to the camera's right), y up, z (printed face) towards the camera
    R = np.column_stack([-left, [0.0, 0.0, 1.0], -forward])
    width = (board.cols - 1) * board.square_m
    # the first inner corner: one square and the white margin above the bottom edge, at the left end
    lift = (1 + MARGIN_SQUARES) * board.square_m + clearance_m
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre + left * width / 2 + np.array([0.0, 0.0, surface_z_m + lift])
    return T


def _heading(scene: Scene, camera_id: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The camera's heading on the table (unit), its left, and its foot (the point below it, z = 0)."""
    T_world_from_body = np.asarray(scene.T_world_from_sensor(camera_id))
    forward = T_world_from_body[:3, 0].copy()
    forward[2] = 0.0
    forward /= np.linalg.norm(forward)
    return (
        forward,
        np.array([-forward[1], forward[0], 0.0]),
        T_world_from_body[:3, 3] * np.array([1.0, 1.0, 0.0]),
    )


def outline_extent(board: Board) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) of the printed board in its own frame, m: the pattern and its white margin."""
    s, margin = board.square_m, MARGIN_SQUARES * board.square_m
    return -s - margin, -s - margin, board.cols * s + margin, board.rows * s + margin


def board_outline(board: Board, T_world_from_board: np.ndarray) -> np.ndarray:
    """(4, 3) world corners of the printed board (its white margin included)."""
    x0, y0, x1, y1 = outline_extent(board)
    corners = np.array([[x0, y0, 0, 1], [x1, y0, 0, 1], [x1, y1, 0, 1], [x0, y1, 0, 1]], float)
    return (T_world_from_board @ corners.T).T[:, :3]


SUPPORTS = ("table", "viaduct")  # what a board may stand on
ROWS = 3  # rows of placements at different distances
IMAGE_MARGIN_PX = 8


def standing_placements(
    scene: Scene,
    camera_id: str,
    board: Board,
    world: StaticWorld,
    session: BoardSessionSettings | None = None,
) -> list[np.ndarray]:
    """Board poses standing on the table or the deck where the camera sees the whole board: candidates
    on a grid ahead of the camera's foot (the session's `ahead_m`, `across_m` to either side,
    `step_m` apart; on the table 0.2-3 m, +-0.6 m, 5 cm), each on the surface under it, kept if that
    surface is level under the board's base (`flat_m`), the board's outline lies inside the image and
    no line of sight to its outline or inner corners is blocked; of those, up to `ROWS` rows from the
    nearest on (`row_gap_m` apart), three across each. The table's cameras get the table in
    front of them; the viaduct's mast cameras, whose lower view the deck fills, the deck. (Chosen
    against the cameras' pose errors: two rows at fixed fractions of the optical axis's reach put
    the mast cameras' boards behind the deck and cam_5's 1 cm off.)"""
    session = board_session(scene, session)
    forward, left, foot = _heading(scene, camera_id)
    camera = np.asarray(scene.T_world_from_sensor(camera_id))[:3, 3]
    K, dist = np.asarray(scene.K(camera_id)), scene.distortion(camera_id)
    T_opt = np.asarray(scene.T_optical_from_world(camera_id))
    spec = scene.sensor(camera_id).camera
    assert spec is not None
    size_px = np.array([spec.width_px, spec.height_px])
    x0, _, x1, _ = outline_extent(board)
    width = x1 - x0
    seen: list[tuple[float, float, np.ndarray]] = []
    step_m, across_m = session.step_m, session.across_m
    for ahead in np.arange(*session.ahead_m, step_m):
        # The last side within a fifth of a step of `across_m` is on the grid (floating-point steps).
        for side in np.arange(-across_m, across_m + step_m / 5, step_m):
            centre = foot + forward * ahead + left * side
            ends = [centre + left * k * width / 2 for k in (-1, 0, 1)]
            found = [surface_z(world, float(end[0]), float(end[1]), session) for end in ends]
            under = [z for z in found if z is not None]
            if len(under) < len(found) or np.ptp(under) > session.flat_m:
                continue
            T = standing_on(scene, camera_id, board, float(ahead), float(side), under[1], session)
            outline = board_outline(board, T)
            px, _ = project_points(outline, T_opt, K, dist)  # NaN behind the camera: not inside
            inside = np.all((px >= IMAGE_MARGIN_PX) & (px <= size_px - IMAGE_MARGIN_PX))
            points = np.vstack([outline, board_points(board, T)])
            if inside and all(clear_lines(world, camera, points, session)):
                seen.append((float(ahead), float(side), T))
    if not seen:
        return []
    # The nearest row seen and up to ROWS - 1 more, each the nearest `row_gap_m` beyond the one before
    # (near: large in the image; several depths: the pose's distance is not one plane's), each at its
    # leftmost, middle and rightmost.
    rows = sorted({a for a, _, _ in seen})
    chosen = [rows[0]]
    while len(chosen) < ROWS and (beyond := [r for r in rows if r >= chosen[-1] + session.row_gap_m]):
        chosen.append(beyond[0])
    picked: list[np.ndarray] = []
    for row in chosen:
        in_row = sorted(((side, T) for a, side, T in seen if a == row), key=lambda st: st[0])
        picked += [in_row[k][1] for k in dict.fromkeys([0, len(in_row) // 2, len(in_row) - 1])]
    return picked


def surface_z(
    world: StaticWorld, x: float, y: float, session: BoardSessionSettings | None = None
) -> float | None:
    """Height of the table or viaduct deck at (x, y), m; None where something else is on top or
    nothing is there (a ray down from the session's `survey_top_m` to its `survey_bottom_m`)."""
    session = board_session(world.scene, session)
    top, bottom = [x, y, session.survey_top_m], [x, y, session.survey_bottom_m]
    body, _, _, position, _ = pb.rayTest(top, bottom, physicsClientId=world.cid)[0]
    if body < 0 or world.body_kind.get(body) not in SUPPORTS:
        return None
    return float(position[2])


def board_points(board: Board, T_world_from_board: np.ndarray) -> np.ndarray:
    """(N, 3) world positions of the board's inner corners."""
    return board.object_points() @ T_world_from_board[:3, :3].T + T_world_from_board[:3, 3]


def clear_lines(
    world: StaticWorld, camera: np.ndarray, targets: np.ndarray, session: BoardSessionSettings | None = None
) -> list[bool]:
    """For each target point: nothing of the static world between it and the camera (the board is not
    in it); each line starts the session's `lens_clearance_m` out of the camera (its own mast is not in
    the way)."""
    clearance_m = board_session(world.scene, session).lens_clearance_m
    direction = (targets - camera) / np.linalg.norm(targets - camera, axis=1, keepdims=True)
    starts = camera + direction * clearance_m
    hits = pb.rayTestBatch(starts.tolist(), targets.tolist(), physicsClientId=world.cid)
    return [hit[0] < 0 for hit in hits]


def render_views(
    scene: Scene,
    camera_id: str,
    board: Board,
    out: Path,
    views: int,
    seed: int = 0,
    session: BoardSessionSettings | None = None,
) -> list[Path]:
    """`views` images of `board` in front of the camera (the session's `view_distance_m` away: 0.3-0.6 m
    on the table) as PNGs in `out`: a session's intrinsics photographs."""
    distance_m = board_session(scene, session).view_distance_m
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    with BoardRenderer(scene, camera_id, board) as renderer:
        rng = np.random.default_rng(seed)
        for k, T in enumerate(views_in_front(scene, camera_id, board, views, rng, distance_m)):
            paths.append(out / f"{camera_id}_view_{k:02d}.png")
            cv2.imwrite(str(paths[-1]), cv2.cvtColor(renderer.render(T), cv2.COLOR_RGB2BGR))
    return paths


def render_standing(
    scene: Scene,
    camera_id: str,
    board: Board,
    board_text: str,
    out: Path,
    session: BoardSessionSettings | None = None,
) -> Path:
    """The board standing on the table or deck at `standing_placements`, one PNG each in `out`, and the survey
    file naming each image with the board's surveyed pose (`board_text` as the survey's `board`)."""
    from shared.calibration.workflow import pose_spec

    out.mkdir(parents=True, exist_ok=True)
    placements = []
    with BoardRenderer(scene, camera_id, board) as renderer:
        placements_T = standing_placements(scene, camera_id, board, renderer.static, session)
        if not placements_T:
            raise ValueError(f"{camera_id} sees no place to stand the board")
        for k, T in enumerate(placements_T):
            name = f"{camera_id}_standing_{k:02d}.png"
            cv2.imwrite(str(out / name), cv2.cvtColor(renderer.render(T), cv2.COLOR_RGB2BGR))
            placements.append({"image": name, "pose": pose_spec(T).model_dump(exclude_none=True)})
    survey = out / "survey.yaml"
    survey.write_text(yaml.safe_dump({"board": board_text, "placements": placements}, sort_keys=False))
    return survey
