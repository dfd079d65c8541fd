"""PointPillars network (torch): pillar feature net, scatter to BEV, 2D backbone + neck, centre head.

    features (P, M, 7), num_points (P,), coords (P,) flat index b * ny * nx + row * nx + col
      -> PFN: Linear(7, C) + BN + ReLU on every point, masked max over the pillar's points -> (P, C)
      -> scatter into a zero canvas (B, C, ny, nx)
      -> stage 1: stride-2 conv + n1 convs (ny/2)    stage 2: stride-2 conv + n2 convs (ny/4)
      -> neck: 1x1 conv on stage 1, 2x2 transposed conv on stage 2, concatenated (stride 2)
      -> head: shared 3x3 conv, heatmap logits (B, 1, ny/2, nx/2), regression (B, 9, ny/2, nx/2)

`ExportModel` wraps it for ONNX (batch 1): sigmoid heatmap with non-peaks zeroed by a 3x3 max-pool.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F  # noqa: N812 (torch convention)
from torch import nn

from shared.detection.lidar.pointpillars.coding import NUM_REG_CHANNELS
from shared.detection.lidar.pointpillars.config import NetConfig, PointPillarsConfig
from shared.detection.lidar.pointpillars.pillars import NUM_POINT_FEATURES

HEATMAP_PRIOR = 0.01  # initial foreground probability of the heatmap (focal-loss bias init)
PEAK_KERNEL = 3  # local-maximum window of the peak extraction, head cells


def _bn2d(channels: int, cfg: NetConfig) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=cfg.bn_eps, momentum=cfg.bn_momentum)


def _conv_bn_relu(c_in: int, c_out: int, stride: int, cfg: NetConfig) -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), _bn2d(c_out, cfg), nn.ReLU(inplace=True)]


class PillarFeatureNet(nn.Module):
    """(P, M, 7) point features + (P,) counts -> (P, C) pillar features."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        self.linear = nn.Linear(NUM_POINT_FEATURES, cfg.pfn_channels, bias=False)
        self.norm = nn.BatchNorm1d(cfg.pfn_channels, eps=cfg.bn_eps, momentum=cfg.bn_momentum)

    def forward(self, features: torch.Tensor, num_points: torch.Tensor) -> torch.Tensor:
        P, M, _ = features.shape
        mask = torch.arange(M, device=features.device)[None, :] < num_points[:, None]  # (P, M)
        x = self.linear(features)  # (P, M, C)
        if self.training:
            # Batch statistics over real points only; padding rows would bias them towards zero.
            x = x.masked_scatter(mask[:, :, None], self.norm(x[mask]))
        else:
            x = self.norm(x.reshape(P * M, -1)).reshape(P, M, -1)
        x = F.relu(x) * mask[:, :, None].to(x.dtype)  # padding -> 0, below every ReLU output's max
        return x.max(dim=1).values


def scatter_to_bev(
    pillar_features: torch.Tensor, coords: torch.Tensor, batch_size: int, ny: int, nx: int
) -> torch.Tensor:
    """(P, C) features at flat indices (P,) (batch-major) -> (B, C, ny, nx) canvas, zeros elsewhere."""
    C = pillar_features.shape[1]
    canvas = pillar_features.new_zeros(batch_size * ny * nx, C)
    canvas = canvas.index_put((coords,), pillar_features, accumulate=False)
    return canvas.reshape(batch_size, ny, nx, C).permute(0, 3, 1, 2).contiguous()


class Backbone(nn.Module):
    """(B, C, ny, nx) -> (B, 2 * neck, ny/2, nx/2)."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        c1, c2 = cfg.stage_channels
        n1, n2 = cfg.stage_layers
        self.out_channels = 2 * cfg.neck_channels
        self.stage1 = nn.Sequential(
            *_conv_bn_relu(cfg.pfn_channels, c1, 2, cfg),
            *[m for _ in range(n1) for m in _conv_bn_relu(c1, c1, 1, cfg)],
        )
        self.stage2 = nn.Sequential(
            *_conv_bn_relu(c1, c2, 2, cfg), *[m for _ in range(n2) for m in _conv_bn_relu(c2, c2, 1, cfg)]
        )
        self.lateral1 = nn.Sequential(
            nn.Conv2d(c1, cfg.neck_channels, 1, bias=False),
            _bn2d(cfg.neck_channels, cfg),
            nn.ReLU(inplace=True),
        )
        self.up2 = nn.Sequential(
            nn.ConvTranspose2d(c2, cfg.neck_channels, 2, 2, bias=False),
            _bn2d(cfg.neck_channels, cfg),
            nn.ReLU(inplace=True),
        )

    def forward(self, bev: torch.Tensor) -> torch.Tensor:
        s1 = self.stage1(bev)
        s2 = self.stage2(s1)
        return torch.cat([self.lateral1(s1), self.up2(s2)], dim=1)


class CenterHead(nn.Module):
    """(B, C, H, W) -> heatmap logits (B, 1, H, W), regression (B, NUM_REG_CHANNELS, H, W)."""

    def __init__(self, c_in: int, cfg: NetConfig) -> None:
        super().__init__()
        self.shared = nn.Sequential(*_conv_bn_relu(c_in, cfg.head_channels, 1, cfg))
        self.heatmap = nn.Conv2d(cfg.head_channels, 1, 1)
        self.regression = nn.Conv2d(cfg.head_channels, NUM_REG_CHANNELS, 1)
        nn.init.constant_(self.heatmap.get_parameter("bias"), -math.log((1 - HEATMAP_PRIOR) / HEATMAP_PRIOR))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.shared(x)
        return self.heatmap(x), self.regression(x)


class PointPillarsNet(nn.Module):
    def __init__(self, config: PointPillarsConfig) -> None:
        super().__init__()
        self.ny, self.nx = config.grid.ny, config.grid.nx
        self.pfn = PillarFeatureNet(config.net)
        self.backbone = Backbone(config.net)
        self.head = CenterHead(self.backbone.out_channels, config.net)

    def forward(
        self,
        features: torch.Tensor,
        num_points: torch.Tensor,
        coords: torch.Tensor,
        batch_size: int = 1,
        grid_shape: tuple[int, int] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """features (P, M, 7) float32, num_points (P,) int64, coords (P,) int64 flat batch-major index
        into `batch_size` canvases of `grid_shape` (ny, nx) (default: the config's grid; training
        windows differ)."""
        ny, nx = grid_shape if grid_shape is not None else (self.ny, self.nx)
        bev = scatter_to_bev(self.pfn(features, num_points), coords, batch_size, ny, nx)
        return self.head(self.backbone(bev))


def peak_scores(heatmap_logits: torch.Tensor) -> torch.Tensor:
    """Sigmoid scores (B, 1, H, W) with every cell that is not a 3x3 local maximum set to 0."""
    scores = torch.sigmoid(heatmap_logits)
    pooled = F.max_pool2d(scores, PEAK_KERNEL, stride=1, padding=PEAK_KERNEL // 2)
    return scores * (pooled == scores).to(scores.dtype)


class ExportModel(nn.Module):
    """Batch-1 graph for ONNX: (features, num_points, coords) -> (peak scores (1, 1, H, W), regression)."""

    def __init__(self, net: PointPillarsNet) -> None:
        super().__init__()
        self.net = net

    def forward(
        self, features: torch.Tensor, num_points: torch.Tensor, coords: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        heatmap, regression = self.net(features, num_points, coords, 1)
        return peak_scores(heatmap), regression


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def load_checkpoint(path: Path, device: str = "cpu") -> tuple[PointPillarsNet, PointPillarsConfig]:
    checkpoint = torch.load(path, map_location=device, weights_only=True)
    config = PointPillarsConfig.model_validate(checkpoint["config"])
    model = PointPillarsNet(config).to(device)
    model.load_state_dict(checkpoint["state_dict"])
    return model.eval(), config
