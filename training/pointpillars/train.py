"""Train PointPillars from scratch on a generated dataset (OpenPCDet custom layout).

    python -m training.pointpillars.train --data DATASET_ROOT --out RUN_DIR \
        [--config CONFIG.json] [--epochs N] [--max-frames N] [--device cpu|cuda]

Writes RUN_DIR/config.json, RUN_DIR/last.pt, RUN_DIR/model.pt (best validation BEV AP@0.7, or the last
epoch without a validation split) and RUN_DIR/history.json (per-epoch losses, time, validation AP).
Checkpoints are {"state_dict", "config", "epoch", "val"}. Logs one line per epoch.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812 (torch convention)
from torch.utils.data import DataLoader
from tqdm import tqdm

from shared.config import with_overrides
from shared.detection.interface import CAR_CLASS_ID
from shared.detection.lidar.pointpillars.coding import (
    REG_COS2,
    REG_DIRECTION,
    REG_LOG_SIZE,
    REG_OFFSET_X,
    REG_OFFSET_Y,
    REG_SIN2,
    REG_Z,
    decode,
    rotated_nms,
)
from shared.detection.lidar.pointpillars.config import PointPillarsConfig, TrainConfig
from training.pointpillars.data import (
    Frame,
    PillarDataset,
    collate,
    grid_accuracy,
    read_split,
    with_mean_size,
)
from training.pointpillars.net import PointPillarsNet, count_parameters, peak_scores

log = logging.getLogger("pointpillars.train")

PROB_EPS = 1e-4  # sigmoid clamp of the focal loss
EVAL_BATCH = 8
CHECKPOINT_BEST = "model.pt"
CHECKPOINT_LAST = "last.pt"


# --- loss ---------------------------------------------------------------------------------------


def focal_loss(
    logits: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, cfg: TrainConfig
) -> torch.Tensor:
    """Penalty-reduced focal loss (CornerNet / CenterNet) on (B, 1, H, W); positives where target == 1."""
    pred = torch.sigmoid(logits).clamp(PROB_EPS, 1 - PROB_EPS)
    pos = (target == 1).to(pred.dtype)
    pos_loss = torch.log(pred) * (1 - pred) ** cfg.focal_alpha * pos
    neg_loss = torch.log(1 - pred) * pred**cfg.focal_alpha * (1 - target) ** cfg.focal_beta * (1 - pos)
    return -((pos_loss + neg_loss) * weight).sum() / pos.sum().clamp(min=1.0)


def detection_loss(
    heatmap: torch.Tensor, regression: torch.Tensor, batch: dict[str, torch.Tensor], cfg: TrainConfig
) -> tuple[torch.Tensor, dict[str, float]]:
    """Weighted sum of the focal heatmap loss and the masked regression losses (L1; squared error for z;
    BCE for the direction bit), each averaged over the assigned cells; the parts for logging."""
    mask = batch["regression_mask"]
    n = mask.sum().clamp(min=1.0)
    target = batch["regression"]

    def l1(channels: list[int] | slice) -> torch.Tensor:
        return ((regression[:, channels] - target[:, channels]).abs() * mask).sum() / n

    parts = {
        "heatmap": focal_loss(heatmap, batch["heatmap"], batch["heatmap_weight"], cfg),
        "offset": l1([REG_OFFSET_X, REG_OFFSET_Y]),
        "z": (((regression[:, REG_Z : REG_Z + 1] - target[:, REG_Z : REG_Z + 1]) ** 2) * mask).sum() / n,
        "size": l1(REG_LOG_SIZE),
        "angle": l1([REG_SIN2, REG_COS2]),
        "direction": (
            F.binary_cross_entropy_with_logits(
                regression[:, REG_DIRECTION : REG_DIRECTION + 1],
                target[:, REG_DIRECTION : REG_DIRECTION + 1],
                reduction="none",
            )
            * mask
        ).sum()
        / n,
    }
    weights = {
        "heatmap": cfg.heatmap_weight,
        "offset": cfg.offset_weight,
        "z": cfg.z_weight,
        "size": cfg.size_weight,
        "angle": cfg.angle_weight,
        "direction": cfg.direction_weight,
    }
    total = torch.stack([weights[k] * v for k, v in parts.items()]).sum()
    return total, {k: float(v.detach()) for k, v in parts.items()}


# --- evaluation ---------------------------------------------------------------------------------


@torch.inference_mode()
def predict(
    model: PointPillarsNet, frames: list[Frame], config: PointPillarsConfig, device: str
) -> list[np.ndarray]:
    """(M, 8) `[x, y, z, dx, dy, dz, yaw, score]` per frame with the torch model (same decode as ONNX)."""
    model.eval()
    data = PillarDataset(frames, config, train=False)
    cells = config.grid.nx * config.grid.ny
    out: list[np.ndarray] = []
    for start in range(0, len(frames), EVAL_BATCH):
        items = [data[i] for i in range(start, min(start + EVAL_BATCH, len(frames)))]
        batch = collate(items, cells)
        heatmap, regression = model(
            batch["features"].to(device),
            batch["num_points"].to(device),
            batch["coords"].to(device),
            len(items),
        )
        peaks = peak_scores(heatmap).cpu().numpy()
        regression = regression.cpu().numpy()
        for b in range(len(items)):
            boxes = decode(peaks[b, 0], regression[b], config.grid, config.head, config.post)
            keep = rotated_nms(boxes, config.post.nms_iou_threshold, config.post.max_detections)
            out.append(boxes[keep])
    return out


def evaluate(
    model: PointPillarsNet, frames: list[Frame], config: PointPillarsConfig, device: str
) -> dict[str, Any]:
    """Validation accuracy of the torch model (evaluation.accuracy: KITTI R40 BEV / 3D AP, centre error)."""
    dets = [
        np.column_stack([d, np.full(len(d), CAR_CLASS_ID, d.dtype)])
        for d in predict(model, frames, config, device)
    ]
    return grid_accuracy(dets, frames, config.grid)


# --- training -----------------------------------------------------------------------------------


def train(
    config: PointPillarsConfig,
    train_frames: list[Frame],
    val_frames: list[Frame],
    out_dir: Path | None,
    device: str = "cpu",
    max_steps: int | None = None,
) -> tuple[PointPillarsNet, list[dict[str, Any]]]:
    """Train from scratch; returns the model (last weights) and the per-epoch history.

    `max_steps` stops early (tests); checkpoints go to `out_dir` when given."""
    cfg = config.train
    torch.manual_seed(cfg.seed)
    model = PointPillarsNet(config).to(device)
    grid = config.train_grid()
    cells = grid.nx * grid.ny
    loader = DataLoader(
        PillarDataset(train_frames, config, train=True, seed=cfg.seed),
        batch_size=cfg.batch_size,
        shuffle=True,
        drop_last=len(train_frames) >= cfg.batch_size,
        collate_fn=functools.partial(collate, cells_per_frame=cells),
        generator=torch.Generator().manual_seed(cfg.seed),
    )
    total_steps = cfg.epochs * len(loader) if max_steps is None else min(max_steps, cfg.epochs * len(loader))
    optimiser = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    schedule = torch.optim.lr_scheduler.OneCycleLR(
        optimiser, max_lr=cfg.lr, total_steps=max(total_steps, 1), pct_start=cfg.warmup_fraction
    )
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        config.save(out_dir / "config.json")
    log.info(
        "training %d parameters on %d frames (%d val), grid %dx%d, windows %dx%d, %d steps, device %s",
        count_parameters(model),
        len(train_frames),
        len(val_frames),
        config.grid.nx,
        config.grid.ny,
        grid.nx,
        grid.ny,
        total_steps,
        device,
    )
    history: list[dict[str, Any]] = []
    best_ap = -1.0
    step = 0
    # A progress bar on a terminal (tqdm disables itself when stderr is not one: logs stay clean).
    for epoch in tqdm(range(1, cfg.epochs + 1), desc="epochs", unit="epoch", disable=None):
        model.train()
        t0 = time.perf_counter()
        sums: dict[str, float] = {}
        steps_in_epoch = 0
        for batch in loader:
            batch = {k: v.to(device) for k, v in batch.items()}
            heatmap, regression = model(
                batch["features"],
                batch["num_points"],
                batch["coords"],
                batch["heatmap"].shape[0],
                (grid.ny, grid.nx),
            )
            loss, parts = detection_loss(heatmap, regression, batch, cfg)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip_norm)
            optimiser.step()
            schedule.step()
            parts["loss"] = float(loss.detach())
            for k, v in parts.items():
                sums[k] = sums.get(k, 0.0) + v
            steps_in_epoch += 1
            step += 1
            if step >= total_steps:
                break
        record: dict[str, Any] = {k: v / max(steps_in_epoch, 1) for k, v in sums.items()}
        record.update(epoch=epoch, steps=steps_in_epoch, train_s=time.perf_counter() - t0)
        last = epoch == cfg.epochs or step >= total_steps
        if val_frames and (epoch % cfg.eval_every == 0 or last):
            t1 = time.perf_counter()
            record["val"] = evaluate(model, val_frames, config, device)
            record["val_s"] = time.perf_counter() - t1
        history.append(record)
        val = record.get("val")
        log.info(
            "epoch %d/%d loss %.4f (heatmap %.4f offset %.4f z %.4f size %.4f angle %.4f dir %.4f) %.0f s%s",
            epoch,
            cfg.epochs,
            record.get("loss", float("nan")),
            record.get("heatmap", float("nan")),
            record.get("offset", float("nan")),
            record.get("z", float("nan")),
            record.get("size", float("nan")),
            record.get("angle", float("nan")),
            record.get("direction", float("nan")),
            record["train_s"],
            f" | val BEV AP@0.7 {val['bev_ap_07']:.4f} AP@0.5 {val['bev_ap_05']:.4f} 3D AP@0.7 "
            f"{val['ap3d_07']:.4f} centre err {1000 * val['centre_error_m']:.1f} mm"
            if val
            else "",
        )
        if out_dir is not None:
            checkpoint = {
                "state_dict": model.state_dict(),
                "config": config.model_dump(mode="json"),
                "epoch": epoch,
                "val": val,
            }
            torch.save(checkpoint, out_dir / CHECKPOINT_LAST)
            ap = val["bev_ap_07"] if val else None
            if (ap is not None and ap > best_ap) or (not val_frames and last):
                best_ap = ap if ap is not None else best_ap
                torch.save(checkpoint, out_dir / CHECKPOINT_BEST)
            (out_dir / "history.json").write_text(json.dumps(history, indent=2) + "\n")
        if step >= total_steps:
            break
    return model, history


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, required=True, help="dataset root (shared/datasets/layout.py)")
    parser.add_argument(
        "--out", type=Path, required=True, help="run directory (checkpoints, config, history)"
    )
    parser.add_argument("--config", type=Path, help="PointPillarsConfig JSON (default: built-in defaults)")
    parser.add_argument("--epochs", type=int, help="override train.epochs")
    parser.add_argument("--max-frames", type=int, help="use at most this many training frames")
    parser.add_argument("--max-val-frames", type=int, help="validate on at most this many frames")
    parser.add_argument("--train-split", default="train")
    parser.add_argument("--val-split", default="val", help="validation split ('' to skip)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    config = PointPillarsConfig.load(args.config) if args.config else PointPillarsConfig()
    if args.epochs is not None:
        config = with_overrides(config, {"train": {"epochs": args.epochs}})
    torch.set_num_threads(config.train.num_threads)
    t0 = time.perf_counter()
    train_frames = read_split(args.data, args.train_split, args.max_frames)
    val_frames = read_split(args.data, args.val_split, args.max_val_frames) if args.val_split else []
    if not train_frames:
        raise SystemExit(f"no frames in split {args.train_split!r} under {args.data}")
    log.info(
        "read %d train + %d val frames in %.1f s",
        len(train_frames),
        len(val_frames),
        time.perf_counter() - t0,
    )
    train(with_mean_size(config, train_frames), train_frames, val_frames, args.out, args.device)


if __name__ == "__main__":
    main()
