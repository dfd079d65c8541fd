"""Camera detector training: labels, target assignment, loss, augmentation, and a tiny training run on
synthetic images (coloured rectangles) in the dataset layout."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from shared.datasets.layout import DatasetLayout  # noqa: E402
from shared.detection.camera.config import (  # noqa: E402
    CHECKPOINT_FILE,
    CONFIG_FILE,
    ONNX_FILE,
    AssignConfig,
    AugmentConfig,
    CameraDetectorConfig,
    InputConfig,
    NetConfig,
    TrainConfig,
)
from training.camera.data import (  # noqa: E402
    IGNORED,
    NEGATIVE,
    Augmenter,
    Batch,
    CameraDataset,
    Sample,
    assign_image,
    assign_targets,
)
from training.camera.loss import aligned_iou_giou, detection_loss  # noqa: E402
from training.camera.net import CameraNet, cell_centers, decode, load_checkpoint  # noqa: E402
from training.camera.train import (  # noqa: E402
    build_parser,
    config_from_args,
    learning_rate,
    train,
)

STRIDE = 8
GRID_W, GRID_H = 8, 6  # a 64 x 48 input
ASSIGN = AssignConfig(center_radius=2.5, min_box_px=1.0)
NONE = torch.zeros((0, 4))

TINY = CameraDetectorConfig(
    input=InputConfig(width=64, height=48),
    net=NetConfig(widths=(8, 8, 16, 16, 16), blocks=(0, 1, 1, 1, 1), neck_width=16, head_convs=1),
    train=TrainConfig(
        epochs=10, batch_size=8, lr=1e-2, warmup_steps=4, ema_decay=0.9, threads=1, max_minutes=2
    ),
)
SRC_W, SRC_H = 128, 96  # synthetic images, letterboxed at scale 0.5


def _centers() -> torch.Tensor:
    return cell_centers(GRID_H, GRID_W, STRIDE)


# --- labels ---------------------------------------------------------------------------------------------


# --- target assignment ----------------------------------------------------------------------------------


def test_assign_centre_region_of_a_box() -> None:
    # Box 8..40 x 8..40: cell centres 12, 20, 28, 36 on each axis lie inside and within 2.5 strides.
    target = assign_image(_centers(), torch.tensor([[8.0, 8.0, 40.0, 40.0]]), NONE, GRID_W, STRIDE, ASSIGN)
    grid = target.reshape(GRID_H, GRID_W)
    assert (grid[1:5, 1:5] == 0).all()
    assert (target == 0).sum() == 16
    assert (target == NEGATIVE).sum() == GRID_W * GRID_H - 16


def test_assign_centre_radius_limits_large_boxes() -> None:
    radius_1 = AssignConfig(center_radius=1.0)
    target = assign_image(_centers(), torch.tensor([[0.0, 0.0, 64.0, 48.0]]), NONE, GRID_W, STRIDE, radius_1)
    # Box centre (32, 24): only centres 28 and 36 (x) and 20 and 28 (y) are within 8 px.
    assert sorted(torch.nonzero(target.reshape(GRID_H, GRID_W) == 0).tolist()) == [
        [2, 3],
        [2, 4],
        [3, 3],
        [3, 4],
    ]


def test_assign_box_smaller_than_a_cell_gets_its_centre_cell() -> None:
    target = assign_image(_centers(), torch.tensor([[17.0, 9.0, 20.0, 11.0]]), NONE, GRID_W, STRIDE, ASSIGN)
    assert torch.nonzero(target == 0).flatten().tolist() == [1 * GRID_W + 2]


def test_assign_overlap_goes_to_the_smaller_box_and_ignore_regions() -> None:
    boxes = torch.tensor([[0.0, 0.0, 48.0, 48.0], [16.0, 16.0, 32.0, 32.0], [59.8, 0.0, 60.3, 40.0]])
    ignore = torch.tensor([[48.0, 40.0, 64.0, 48.0]])
    grid = assign_image(_centers(), boxes, ignore, GRID_W, STRIDE, ASSIGN).reshape(GRID_H, GRID_W)
    assert (grid[2:4, 2:4] == 1).all()  # inside both: the smaller box
    assert grid[1, 1] == 0  # centre (12, 12): 12 px from the big box's centre (24, 24)
    assert grid[0, 0] == NEGATIVE  # centre (4, 4): 20 px away, outside the 2.5-stride radius
    assert (grid[5, 6:] == IGNORED).all()  # ignore region
    assert (grid[:5, 7] == IGNORED).all()  # a box 0.5 px wide is ignored, never positive
    assert not (grid == 2).any()


def test_assign_targets_batch_shapes_and_boxes() -> None:
    batch = Batch(
        torch.zeros((2, 48, 64, 3), dtype=torch.uint8),
        [torch.tensor([[8.0, 8.0, 40.0, 40.0]]), NONE],
        [NONE, NONE],
    )
    labels, gt = assign_targets(batch, GRID_H, GRID_W, STRIDE, ASSIGN)
    assert labels.shape == (2, GRID_H * GRID_W) and gt.shape == (2, GRID_H * GRID_W, 4)
    assert (gt[0][labels[0] == 0] == torch.tensor([8.0, 8.0, 40.0, 40.0])).all()
    assert (labels[1] == NEGATIVE).all()


# --- decoding and loss ----------------------------------------------------------------------------------


def test_decode_known_answer() -> None:
    raw = torch.full((1, 5, 2, 3), -30.0)  # softplus(-30) ~ 0: zero-size boxes at the cell centres
    raw[0, 0, 1, 2] = 0.0  # score 0.5 at row 1, col 2
    raw[0, 1:, 1, 2] = torch.log(torch.expm1(torch.tensor([1.0, 2.0, 3.0, 4.0])))  # softplus = 1, 2, 3, 4
    dets = decode(raw, STRIDE)
    assert dets.shape == (1, 6, 5)
    # Cell (row 1, col 2): centre (20, 12); l, t, r, b = 8, 16, 24, 32 px.
    torch.testing.assert_close(dets[0, 5], torch.tensor([12.0, -4.0, 44.0, 44.0, 0.5]))
    torch.testing.assert_close(dets[0, 0, :4], torch.tensor([4.0, 4.0, 4.0, 4.0]))


def test_aligned_iou_giou_known_answers() -> None:
    a = torch.tensor([[0.0, 0.0, 2.0, 2.0], [0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 2.0, 1.0]])
    b = torch.tensor([[0.0, 0.0, 2.0, 2.0], [2.0, 0.0, 3.0, 1.0], [1.0, 0.0, 3.0, 1.0]])
    iou, giou = aligned_iou_giou(a, b)
    torch.testing.assert_close(iou, torch.tensor([1.0, 0.0, 1 / 3]), atol=1e-5, rtol=0)
    torch.testing.assert_close(giou, torch.tensor([1.0, -1 / 3, 1 / 3]), atol=1e-5, rtol=0)


def test_loss_ignores_ignored_cells_and_has_no_box_term_without_positives() -> None:
    raw = torch.zeros((1, 5, GRID_H, GRID_W))
    n = GRID_H * GRID_W
    all_ignored = detection_loss(raw, torch.full((1, n), IGNORED), torch.zeros(1, n, 4), STRIDE, TINY.loss)
    assert float(all_ignored["loss"]) == 0.0
    negatives = detection_loss(raw, torch.full((1, n), NEGATIVE), torch.zeros(1, n, 4), STRIDE, TINY.loss)
    assert float(negatives["score"]) > 0 and float(negatives["box"]) == 0.0


# --- augmentation ---------------------------------------------------------------------------------------


def _sample() -> Sample:
    image = np.zeros((48, 64, 3), np.uint8)
    image[8:24, 4:20] = 200
    return Sample(image, np.array([[4.0, 8.0, 20.0, 24.0]], np.float32), np.zeros((0, 4), np.float32))


def test_hflip_mirrors_image_and_boxes() -> None:
    aug = Augmenter(AugmentConfig(hflip_prob=1.0, affine_prob=0.0, brightness=0, contrast=0, saturation=0),
                    TINY.input, 1.0)  # fmt: skip
    out = aug(_sample(), np.random.default_rng(0))
    np.testing.assert_allclose(out.boxes, [[44, 8, 60, 24]])
    assert (out.image[8:24, 44:60] == 200).all() and out.image[8:24, 4:20].max() == 0


def test_affine_keeps_boxes_on_their_pixels() -> None:
    cfg = AugmentConfig(
        hflip_prob=0, affine_prob=1.0, scale=0.25, translate=0.1, brightness=0, contrast=0, saturation=0
    )
    aug = Augmenter(cfg, TINY.input, 1.0)
    rng = np.random.default_rng(3)
    for _ in range(10):
        out = aug(_sample(), rng)
        for x0, y0, x1, y1 in out.boxes:  # the bright square fills its (shrunk by 1 px) box
            inner = out.image[int(y0) + 1 : int(y1) - 1, int(x0) + 1 : int(x1) - 1]
            assert inner.size == 0 or inner.min() > 150


def test_affine_turns_mostly_cut_boxes_into_ignore() -> None:
    cfg = AugmentConfig(affine_prob=1.0, scale=0.0, translate=0.5, min_kept_fraction=0.99)
    aug = Augmenter(cfg, TINY.input, 1.0)
    outs = [aug(_sample(), np.random.default_rng(seed)) for seed in range(20)]
    assert any(len(o.ignore) == 1 and len(o.boxes) == 0 for o in outs)
    assert all(len(o.boxes) + len(o.ignore) <= 1 for o in outs)


def test_learning_rate_schedule() -> None:
    cfg = CameraDetectorConfig(train=TrainConfig(lr=1.0, warmup_steps=10, final_lr_fraction=0.1))
    assert learning_rate(0.0, 0, cfg) == pytest.approx(0.1)
    assert learning_rate(0.0, 10, cfg) == pytest.approx(1.0)
    assert learning_rate(0.5, 100, cfg) == pytest.approx(0.55)
    assert learning_rate(1.0, 100, cfg) == pytest.approx(0.1)


# --- end to end: a tiny dataset, a tiny training run ----------------------------------------------------


def write_synthetic_split(root: Path, split: str, n: int, seed: int) -> None:
    """Coloured rectangles (cars) on a two-tone background, in the dataset layout, with one ignore box."""
    layout = DatasetLayout(root)
    rng = np.random.default_rng(seed)
    for i in range(n):
        stem = f"s{seed:04d}_t{i:06d}_cam_1"
        img = np.empty((SRC_H, SRC_W, 3), np.uint8)
        img[: SRC_H // 2] = (200, 210, 220)
        img[SRC_H // 2 :] = (90, 140, 90)
        boxes = []
        for _ in range(rng.integers(1, 3)):
            w, h = rng.integers(16, 48), rng.integers(12, 36)
            x0, y0 = rng.integers(0, SRC_W - w), rng.integers(0, SRC_H - h)
            colour = tuple(int(c) for c in rng.integers(0, 120, 3))
            cv2.rectangle(img, (int(x0), int(y0)), (int(x0 + w - 1), int(y0 + h - 1)), colour, -1)
            boxes.append([float(x0), float(y0), float(x0 + w), float(y0 + h)])
        for path in (
            layout.camera_image(split, stem),
            layout.yolo_label(split, stem),
            layout.camera_meta(split, stem),
        ):
            path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(layout.camera_image(split, stem)), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        lines = []
        for x0, y0, x1, y1 in boxes:
            cx, cy = (x0 + x1) / 2 / SRC_W, (y0 + y1) / 2 / SRC_H
            lines.append(f"0 {cx} {cy} {(x1 - x0) / SRC_W} {(y1 - y0) / SRC_H}")
        layout.yolo_label(split, stem).write_text("\n".join(lines) + "\n")
        meta = {"boxes": boxes, "ignore": [[0.0, 0.0, 4.0, 4.0]], "vehicle_ids": [], "visible_px": []}
        layout.camera_meta(split, stem).write_text(json.dumps(meta))


@pytest.fixture(scope="module")
def synthetic_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("camera_ds")
    write_synthetic_split(root, "train", 32, seed=1)
    write_synthetic_split(root, "val", 8, seed=2)
    return root


def test_dataset_reads_the_layout_in_input_pixels(synthetic_root: Path) -> None:
    ds = CameraDataset(synthetic_root, "val", TINY, augment=False)
    assert len(ds) == 8
    s = ds[0]
    assert s.image.shape == (48, 64, 3) and s.image.dtype == np.uint8
    meta = json.loads(DatasetLayout(synthetic_root).camera_meta("val", ds.stems[0]).read_text())
    np.testing.assert_allclose(s.boxes, np.array(meta["boxes"]) * 0.5, atol=1e-4)
    np.testing.assert_allclose(s.ignore, [[0, 0, 2, 2]])


def test_dataset_limit_spreads_over_the_split(synthetic_root: Path) -> None:
    every = CameraDataset(synthetic_root, "val", TINY, augment=False)
    some = CameraDataset(synthetic_root, "val", TINY, augment=False, limit=3)
    assert some.stems == [every.stems[0], every.stems[4], every.stems[7]]


def test_tiny_training_lowers_the_loss_and_exports(synthetic_root: Path, tmp_path: Path) -> None:
    torch.set_num_threads(1)
    model, record = train(TINY, synthetic_root, tmp_path)
    history = record["history"]
    assert record["steps"] == TINY.train.epochs * 4  # 32 images, batches of 8
    assert history[-1]["loss"] < 0.75 * history[0]["loss"]
    assert history[-1]["box"] < history[0]["box"]
    assert 0.0 <= history[-1]["val_ap50"] <= 1.0
    assert (tmp_path / CHECKPOINT_FILE).exists() and (tmp_path / CONFIG_FILE).exists()
    loaded, cfg = load_checkpoint(tmp_path)
    assert cfg == TINY
    images = torch.zeros((1, 48, 64, 3), dtype=torch.uint8)
    with torch.no_grad():
        torch.testing.assert_close(loaded(images), model(images))

    from training.camera.export import export_onnx

    export_onnx(loaded, cfg, tmp_path)
    assert (tmp_path / ONNX_FILE).exists()
    assert isinstance(model, CameraNet)


def test_cli_options_override_the_config_file(tmp_path: Path) -> None:
    TINY.save(tmp_path / "cfg.json")
    argv = ["--data", "d", "--out", "o", "--config", str(tmp_path / "cfg.json")]
    argv += ["--epochs", "3", "--lr", "0.5"]
    cfg = config_from_args(build_parser().parse_args(argv))
    assert (cfg.train.epochs, cfg.train.lr, cfg.train.batch_size) == (3, 0.5, TINY.train.batch_size)
    assert cfg.net == TINY.net and cfg.input == TINY.input
    default = config_from_args(build_parser().parse_args(["--data", "d", "--out", "o"]))
    assert default == CameraDetectorConfig()
