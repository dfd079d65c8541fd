"""The camera detector network: a small anchor-free single-stage CNN (FCOS-like, one stride-8 level).

    images (B, H, W, 3) uint8 RGB, letterboxed to the input size
      -> backbone: five stride-2 stages of 3x3 conv + BN + ReLU (+ residual blocks), C3..C5 at 8/16/32
      -> neck: top-down path (1x1 laterals, nearest upsampling, 3x3 fuse convs) down to stride 8
      -> head: 3x3 convs, then one 1x1 conv with 5 outputs per cell:
         score logit and (l, t, r, b), the distances from the cell centre to the box sides
    raw (B, 5, H/8, W/8)

`decode` turns raw maps into (B, N, 5) rows `[x0, y0, x1, y1, score]` in network-input pixels, N =
(H/8) * (W/8) cells in row-major order; `ExportModel` is net + decode, the graph exported to ONNX,
so the runtime only thresholds, runs NMS and maps boxes back to the original image.

Default size (config.py): 448x336 input -> 56x42 cells of 8 px (11.4 px of a 640x480 image), widths
16/24/48/64/96, neck and head 48: 484k parameters, 0.53 GMACs (1.06 GFLOPs) per image.

Only training and export import this module (torch); inference uses onnxruntime.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as nnf

from shared.detection.camera.config import CHECKPOINT_FILE, CameraDetectorConfig, NetConfig

PIXEL_MEAN = 127.5  # uint8 -> roughly zero-mean, unit-range input
PIXEL_SCALE = 1.0 / 64.0
NUM_OUTPUTS = 5  # score logit, l, t, r, b
SCORE_CHANNEL = 0
BOX_CHANNELS = slice(1, 5)
STAGE_STRIDE = 2
NECK_LEVELS = 3  # C3, C4, C5 (strides 8, 16, 32)
PRED_INIT_STD = 0.01  # prediction layer starts near zero: every cell at the prior score, ~1.4 stride boxes


class ConvBNAct(nn.Sequential):
    """k x k conv (no bias) + BatchNorm + optional ReLU; 'same' padding, `stride` 1 or 2."""

    def __init__(self, c_in: int, c_out: int, k: int = 3, stride: int = 1, act: bool = True) -> None:
        layers: list[nn.Module] = [
            nn.Conv2d(c_in, c_out, k, stride, k // 2, bias=False),
            nn.BatchNorm2d(c_out),
        ]
        if act:
            layers.append(nn.ReLU(inplace=True))
        super().__init__(*layers)


class ResBlock(nn.Module):
    """Two 3x3 convs with an identity shortcut: relu(x + bn(conv(relu(bn(conv(x))))))."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.body = nn.Sequential(ConvBNAct(c, c), ConvBNAct(c, c, act=False))
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(x + self.body(x))


class Backbone(nn.Module):
    """Five stages, each a stride-2 3x3 conv then `blocks[i]` residual blocks; returns C3, C4, C5."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        stages = []
        c_in = 3
        for c_out, n_blocks in zip(cfg.widths, cfg.blocks, strict=True):
            layers: list[nn.Module] = [ConvBNAct(c_in, c_out, stride=STAGE_STRIDE)]
            layers += [ResBlock(c_out) for _ in range(n_blocks)]
            stages.append(nn.Sequential(*layers))
            c_in = c_out
        self.stages = nn.ModuleList(stages)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        return feats[-NECK_LEVELS:]


class Neck(nn.Module):
    """Top-down fusion: P5 = lat(C5); P4 = fuse(up(P5) + lat(C4)); P3 = fuse(up(P4) + lat(C3))."""

    def __init__(self, in_widths: tuple[int, ...], width: int) -> None:
        super().__init__()
        self.laterals = nn.ModuleList(ConvBNAct(c, width, k=1) for c in in_widths)
        self.fuse = nn.ModuleList(ConvBNAct(width, width) for _ in in_widths[:-1])

    def forward(self, feats: list[torch.Tensor]) -> torch.Tensor:
        p = self.laterals[-1](feats[-1])
        for i in range(len(feats) - 2, -1, -1):
            lateral = self.laterals[i](feats[i])
            # Odd sizes (336 / 32 = 10.5 -> 11): upsample to the lateral's exact size.
            up = nnf.interpolate(p, size=lateral.shape[-2:], mode="nearest")
            p = self.fuse[i](up + lateral)
        return p


class CameraNet(nn.Module):
    """Backbone + neck + head. `forward`: (B, H, W, 3) uint8 -> raw (B, 5, H/8, W/8) float32."""

    def __init__(self, cfg: CameraDetectorConfig) -> None:
        super().__init__()
        net = cfg.net
        self.stride = net.stride
        self.backbone = Backbone(net)
        self.neck = Neck(net.widths[-NECK_LEVELS:], net.neck_width)
        self.head = nn.Sequential(*(ConvBNAct(net.neck_width, net.neck_width) for _ in range(net.head_convs)))
        self.pred = nn.Conv2d(net.neck_width, NUM_OUTPUTS, 1)
        nn.init.normal_(self.pred.weight, std=PRED_INIT_STD)
        bias = torch.zeros(NUM_OUTPUTS)
        bias[SCORE_CHANNEL] = -math.log((1.0 - net.prior_prob) / net.prior_prob)
        self.pred.bias = nn.Parameter(bias)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = (images.permute(0, 3, 1, 2).float() - PIXEL_MEAN) * PIXEL_SCALE
        return self.pred(self.head(self.neck(self.backbone(x))))


def cell_centers(h: int, w: int, stride: int, device: torch.device | None = None) -> torch.Tensor:
    """(h * w, 2) centres (x, y) of the output cells, input px, row-major: ((j + 0.5) s, (i + 0.5) s)."""
    ys = (torch.arange(h, device=device, dtype=torch.float32) + 0.5) * stride
    xs = (torch.arange(w, device=device, dtype=torch.float32) + 0.5) * stride
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=1)


def split_raw(raw: torch.Tensor, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """raw (B, 5, h, w) -> score logits (B, N) and boxes (B, N, 4) `[x0, y0, x1, y1]` in input pixels.

    Distances are softplus(raw) * stride (positive, ~linear for large boxes)."""
    h, w = raw.shape[2:]
    flat = raw.flatten(2).transpose(1, 2)  # (B, N, 5)
    ltrb = nnf.softplus(flat[..., BOX_CHANNELS]) * stride
    centers = cell_centers(h, w, stride, raw.device)
    xy = centers.unsqueeze(0)
    boxes = torch.cat([xy - ltrb[..., :2], xy + ltrb[..., 2:]], dim=-1)
    return flat[..., SCORE_CHANNEL], boxes


def decode(raw: torch.Tensor, stride: int) -> torch.Tensor:
    """raw (B, 5, h, w) -> (B, h * w, 5) rows `[x0, y0, x1, y1, score]`, input pixels, score in [0, 1]."""
    logits, boxes = split_raw(raw, stride)
    return torch.cat([boxes, torch.sigmoid(logits).unsqueeze(-1)], dim=-1)


class ExportModel(nn.Module):
    """Net + decode: (B, H, W, 3) uint8 -> (B, N, 5) float32, the graph that goes to ONNX."""

    def __init__(self, net: CameraNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return decode(self.net(images), self.net.stride)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def count_macs(model: CameraNet, height: int, width: int) -> int:
    """Multiply-accumulates of the convolutions of one (height x width) forward pass."""
    macs = 0

    def hook(module: nn.Module, _inputs: tuple[torch.Tensor, ...], output: torch.Tensor) -> None:
        nonlocal macs
        assert isinstance(module, nn.Conv2d)
        k_h, k_w = module.kernel_size
        per_output = module.in_channels // module.groups * k_h * k_w
        macs += int(output.numel() // output.shape[0]) * per_output

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    try:
        was_training = model.training
        model.eval()
        with torch.no_grad():
            model(torch.zeros(1, height, width, 3, dtype=torch.uint8))
        model.train(was_training)
    finally:
        for h in handles:
            h.remove()
    return macs


def load_checkpoint(model_dir: Path) -> tuple[CameraNet, CameraDetectorConfig]:
    """The model of `model_dir/model.pt` in eval mode, on the CPU, and its config."""
    ckpt = torch.load(Path(model_dir) / CHECKPOINT_FILE, map_location="cpu", weights_only=True)
    cfg = CameraDetectorConfig.model_validate(ckpt["config"])
    model = CameraNet(cfg)
    model.load_state_dict(ckpt["state_dict"])
    return model.eval(), cfg
