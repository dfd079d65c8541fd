"""Train the camera detector from scratch on a generated dataset, then export it to ONNX.

    python -m training.camera.train --data DATASET_ROOT --out MODEL_DIR [--config JSON]
        [--epochs N] [--batch-size B] [--lr LR] [--max-minutes M] [--threads T] [--num-workers W]
        [--limit N] [--val-limit N] [--no-export]

Reads the `train` split (and `val`, if present, for a per-epoch validation loss and AP@0.5) of the
layout in `shared.datasets.layout`. Writes to MODEL_DIR: `model.pt` (EMA weights + config + training
record), `config.json` and, unless `--no-export`, `model.onnx` (see `export.py`).

Schedule: linear warm-up, then cosine decay of the AdamW learning rate over a progress that is the
larger of (step / total steps) and (elapsed / `max_minutes`): on a slow or busy machine the run
still completes its schedule (fewer epochs) and stops within the budget. Uses CUDA when available.
One log line per epoch.

Defaults (config.py): at most 12 epochs or 22 minutes after caching, 1 torch thread (bfloat16
autocast) + 1 augmentation worker: ~55 images/s on one core of this 2-core machine. On an idle
machine `--threads 2` trains ~1.6x faster; while another process keeps a core busy it is many times
slower (OpenMP threads wait on each other), hence the default.
"""

from __future__ import annotations

import argparse
import copy
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader
from tqdm import tqdm

from shared.config import with_overrides
from shared.datasets.sources import DEFAULT_SOURCE, DataSource
from shared.detection.camera.config import (
    CHECKPOINT_FILE,
    CONFIG_FILE,
    CameraDetectorConfig,
    PostprocessConfig,
)
from shared.detection.camera.geometry import Letterbox, postprocess
from shared.metrics.detection import CocoSummary, evaluate_coco
from training.camera.data import Batch, CameraDataset, assign_targets, collate
from training.camera.loss import detection_loss
from training.camera.net import CameraNet, count_macs, count_parameters, decode

log = logging.getLogger(__name__)

SECONDS_PER_MINUTE = 60.0
EVAL_BATCH = 64
EVAL_SCORE_THRESHOLD = 0.05  # AP needs the low-score tail of the precision-recall curve
EVAL_IOUS = (0.5,)
EMA_RAMP_STEPS = 10  # EMA decay ramps as (1 + n) / (ramp + n) over the first updates
LOSS_KEYS = ("loss", "score", "box")
SEED_MODULUS = 2**32


class ModelEMA:
    """Exponential moving average of a model's weights (buffers copied), the weights that are saved."""

    def __init__(self, model: CameraNet, decay: float) -> None:
        self.model: CameraNet = copy.deepcopy(model).eval()
        self.decay = decay
        self.updates = 0
        for p in self.model.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        d = min(self.decay, (1.0 + self.updates) / (EMA_RAMP_STEPS + self.updates))
        for ema_p, p in zip(self.model.parameters(), model.parameters(), strict=True):
            ema_p.mul_(d).add_(p.detach(), alpha=1.0 - d)
        for ema_b, b in zip(self.model.buffers(), model.buffers(), strict=True):
            ema_b.copy_(b)


def learning_rate(progress: float, step: int, cfg: CameraDetectorConfig) -> float:
    """Warm-up over `warmup_steps`, then cosine from `lr` to `lr * final_lr_fraction` as progress: 0 -> 1."""
    t = cfg.train
    final = t.lr * t.final_lr_fraction
    cosine = final + 0.5 * (t.lr - final) * (1.0 + math.cos(math.pi * min(progress, 1.0)))
    if step < t.warmup_steps:
        return cosine * (step + 1) / t.warmup_steps
    return cosine


def param_groups(model: nn.Module, weight_decay: float) -> list[dict[str, Any]]:
    """Weight decay on conv weights only (not on BatchNorm parameters and biases)."""
    decay = [p for p in model.parameters() if p.ndim > 1]
    no_decay = [p for p in model.parameters() if p.ndim <= 1]
    return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]


def forward(model: CameraNet, batch: Batch, cfg: CameraDetectorConfig, device: torch.device) -> torch.Tensor:
    """Raw output (B, 5, h, w) float32; bfloat16 autocast in training if configured (eval: float32)."""
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=cfg.train.bf16 and model.training):
        return model(batch.images.to(device, non_blocking=True)).float()


def batch_loss(
    raw: torch.Tensor, batch: Batch, cfg: CameraDetectorConfig, stride: int
) -> dict[str, torch.Tensor]:
    """Loss terms of a batch from the network's raw output."""
    labels, gt = assign_targets(batch, raw.shape[2], raw.shape[3], stride, cfg.assign)
    return detection_loss(raw, labels.to(raw.device), gt.to(raw.device), stride, cfg.loss)


def seed_worker(worker_id: int) -> None:
    """DataLoader worker init: an augmentation stream of its own (torch seeds each worker differently)."""
    info = torch.utils.data.get_worker_info()
    if info is not None and isinstance(info.dataset, CameraDataset):
        info.dataset.rng = np.random.default_rng(torch.initial_seed() % SEED_MODULUS)


@torch.no_grad()
def evaluate(
    model: CameraNet, dataset: CameraDataset, cfg: CameraDetectorConfig, device: torch.device
) -> tuple[dict[str, float], CocoSummary]:
    """Mean loss terms and COCO AP@0.5 (`shared.metrics`, in input pixels) of `model` on an
    un-augmented dataset."""
    model.eval()
    post = PostprocessConfig(**{**cfg.post.model_dump(), "score_threshold": EVAL_SCORE_THRESHOLD})
    identity = Letterbox(1.0, cfg.input.width, cfg.input.height)
    sums = dict.fromkeys(LOSS_KEYS, 0.0)
    dets: list[np.ndarray] = []
    n_batches = 0
    for start in range(0, len(dataset), EVAL_BATCH):
        batch = collate([dataset.sample(i) for i in range(start, min(start + EVAL_BATCH, len(dataset)))])
        raw = forward(model, batch, cfg, device)
        losses = batch_loss(raw, batch, cfg, model.stride)
        for k in LOSS_KEYS:
            sums[k] += float(losses[k])
        n_batches += 1
        cells = decode(raw, model.stride).cpu().numpy()
        dets += postprocess(cells, [identity] * len(cells), post)
    frames = list(zip(dets, dataset.boxes, dataset.ignore, strict=True))
    return {k: v / n_batches for k, v in sums.items()}, evaluate_coco(frames, EVAL_IOUS)


def save_checkpoint(
    out_dir: Path, model: CameraNet, cfg: CameraDetectorConfig, record: dict[str, Any]
) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / CHECKPOINT_FILE
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    torch.save({"state_dict": state, "config": cfg.model_dump(mode="json"), "record": record}, path)
    cfg.save(out_dir / CONFIG_FILE)
    return path


class Trainer:
    """One training run: data, model, EMA, optimiser and the step/time schedule."""

    def __init__(
        self,
        cfg: CameraDetectorConfig,
        data_root: Path,
        limit: int | None = None,
        val_limit: int | None = None,
        source: DataSource = DEFAULT_SOURCE,
    ) -> None:
        t = cfg.train
        self.cfg = cfg
        torch.manual_seed(t.seed)
        if t.threads:
            torch.set_num_threads(t.threads)
        self.device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        self.train_set = CameraDataset(data_root, "train", cfg, augment=True, limit=limit, source=source)
        self.val_set: CameraDataset | None = None
        try:
            self.val_set = CameraDataset(
                data_root, "val", cfg, augment=False, limit=val_limit or t.val_images, source=source
            )
        except FileNotFoundError:
            log.info("no val split: validation skipped")
        self.loader = DataLoader(
            self.train_set,
            batch_size=t.batch_size,
            shuffle=True,
            drop_last=len(self.train_set) >= t.batch_size,
            num_workers=t.num_workers,
            collate_fn=collate,
            generator=torch.Generator().manual_seed(t.seed),
            worker_init_fn=seed_worker,
            persistent_workers=t.num_workers > 0,
        )
        self.model = CameraNet(cfg).to(self.device)
        self.ema = ModelEMA(self.model, t.ema_decay) if t.ema_decay > 0 else None
        self.optimizer = torch.optim.AdamW(param_groups(self.model, t.weight_decay), lr=t.lr)
        self.total_steps = t.epochs * len(self.loader)
        self.budget_s = t.max_minutes * SECONDS_PER_MINUTE
        self.step = 0
        self.start = time.perf_counter()
        log.info(
            "model: %d parameters, %.3f GFLOPs at %dx%d, device %s, %d threads, bf16 %s",
            count_parameters(self.model),
            2 * count_macs(self.model, cfg.input.height, cfg.input.width) / 1e9,  # not ns: giga-operations
            cfg.input.width,
            cfg.input.height,
            self.device,
            torch.get_num_threads(),
            t.bf16,
        )

    @property
    def final_model(self) -> CameraNet:
        """The model that is evaluated and saved: the EMA if enabled."""
        return self.ema.model if self.ema is not None else self.model

    def progress(self) -> float:
        """Schedule position in [0, 1]: the larger of the step and the time fraction."""
        return max(self.step / self.total_steps, (time.perf_counter() - self.start) / self.budget_s)

    def train_step(self, batch: Batch, lr: float) -> dict[str, torch.Tensor]:
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        losses = batch_loss(
            forward(self.model, batch, self.cfg, self.device), batch, self.cfg, self.model.stride
        )
        self.optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.train.grad_clip)
        self.optimizer.step()
        if self.ema is not None:
            self.ema.update(self.model)
        self.step += 1
        return losses

    def train_epoch(self) -> dict[str, float]:
        """One pass (or until the budget ends): mean loss terms, images/s, last learning rate."""
        self.model.train()
        sums = dict.fromkeys(LOSS_KEYS, 0.0)
        n_steps, lr = 0, 0.0
        epoch_start = time.perf_counter()
        for batch in self.loader:
            progress = self.progress()
            if progress >= 1.0:
                break
            lr = learning_rate(progress, self.step, self.cfg)
            losses = self.train_step(batch, lr)
            for k in LOSS_KEYS:
                sums[k] += float(losses[k].detach())
            n_steps += 1
        seconds = time.perf_counter() - epoch_start
        means = {k: v / max(n_steps, 1) for k, v in sums.items()}
        return {
            **means,
            "steps": n_steps,
            "lr": lr,
            "images_per_s": n_steps * self.cfg.train.batch_size / seconds,
        }

    def run(self) -> list[dict[str, float]]:
        """Epochs until `epochs` or the time budget; one log line each. Returns the per-epoch record."""
        t = self.cfg.train
        history: list[dict[str, float]] = []
        # A progress bar on a terminal (tqdm disables itself when stderr is not one: logs stay clean).
        for epoch in tqdm(range(1, t.epochs + 1), desc="epochs", unit="epoch", disable=None):
            entry = {"epoch": epoch, **self.train_epoch()}
            if entry["steps"] == 0:
                break
            val_text = ""
            if self.val_set is not None:
                val_losses, ap = evaluate(self.final_model, self.val_set, self.cfg, self.device)
                recall = ap.per_threshold[EVAL_IOUS[0]].curve.recall
                max_recall = float(recall[-1]) if len(recall) else 0.0
                entry.update({f"val_{k}": v for k, v in val_losses.items()}, val_ap50=ap.ap50)
                val_text = f" | val loss {val_losses['loss']:.4f} AP50 {ap.ap50:.4f} recall {max_recall:.4f}"
            history.append(entry)
            log.info(
                "epoch %d/%d: loss %.4f (score %.4f, box %.4f), lr %.2e, %.0f img/s, %.0f s%s",
                epoch,
                t.epochs,
                entry["loss"],
                entry["score"],
                entry["box"],
                entry["lr"],
                entry["images_per_s"],
                time.perf_counter() - self.start,
                val_text,
            )
            if self.progress() >= 1.0 and epoch < t.epochs:
                log.info(
                    "time budget %.1f min reached after %d of %d steps",
                    t.max_minutes,
                    self.step,
                    self.total_steps,
                )
                break
        return history


def train(
    cfg: CameraDetectorConfig,
    data_root: Path,
    out_dir: Path,
    limit: int | None = None,
    val_limit: int | None = None,
    source: DataSource = DEFAULT_SOURCE,
) -> tuple[CameraNet, dict[str, Any]]:
    """Train per `cfg`, save the EMA model to `out_dir`; returns it (eval mode, CPU) and the training record.

    `limit` / `val_limit`: use that many images of the split (evenly spaced) instead of all."""
    trainer = Trainer(cfg, data_root, limit, val_limit, source)
    history = trainer.run()
    model = trainer.final_model.eval()
    record: dict[str, Any] = {
        "steps": trainer.step,
        "seconds": time.perf_counter() - trainer.start,
        "train_images": len(trainer.train_set),
        "history": history,
    }
    path = save_checkpoint(out_dir, model, cfg, record)
    log.info("saved %s after %d steps, %.0f s", path, trainer.step, record["seconds"])
    return model.cpu(), record


TRAIN_OVERRIDES = ("epochs", "batch_size", "lr", "max_minutes", "threads", "num_workers", "seed")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, required=True, help="dataset root (shared.datasets.layout)")
    parser.add_argument("--out", type=Path, required=True, help="model directory to write")
    parser.add_argument("--config", type=Path, help="CameraDetectorConfig JSON to start from (else defaults)")
    parser.add_argument("--epochs", type=int, help="at most this many epochs")
    parser.add_argument("--batch-size", type=int)
    parser.add_argument("--lr", type=float, help="peak learning rate")
    parser.add_argument("--max-minutes", type=float, help="training time budget (after caching the images)")
    parser.add_argument("--threads", type=int, help="torch CPU threads")
    parser.add_argument("--num-workers", type=int, help="DataLoader worker processes")
    parser.add_argument("--seed", type=int)
    parser.add_argument("--limit", type=int, help="use N training images (evenly spaced) only")
    parser.add_argument("--val-limit", type=int, help="validate on N images (evenly spaced)")
    parser.add_argument("--no-export", action="store_true", help="skip the ONNX export")
    return parser


def config_from_args(args: argparse.Namespace) -> CameraDetectorConfig:
    """The `--config` file (or the defaults) with the training options given on the command line."""
    cfg = CameraDetectorConfig.load(args.config) if args.config else CameraDetectorConfig()
    overrides = {k: getattr(args, k) for k in TRAIN_OVERRIDES if getattr(args, k) is not None}
    return with_overrides(cfg, {"train": overrides})


def main(argv: list[str] | None = None) -> None:
    from shared.logging_setup import setup_logging

    args = build_parser().parse_args(argv)
    setup_logging("camera-train")
    cfg = config_from_args(args)
    model, _ = train(cfg, args.data, args.out, limit=args.limit, val_limit=args.val_limit)
    if not args.no_export:
        from training.camera.export import export_onnx

        export_onnx(model, cfg, args.out)


if __name__ == "__main__":
    main()
