"""PointPillars configuration: grid, network, targets, post-processing, augmentation and training.

One `PointPillarsConfig` travels with a model (saved as JSON next to the checkpoint and the ONNX file),
so pillarisation, decoding and the network always agree. Units: metres, radians, seconds.

Defaults are sized for the 1:18 sand table (vehicles 0.33 x 0.22 x 0.21 m, agents see them within about
4 m): a 160 x 160 grid of 0.05 m pillars over x, y in [-4, 4) m, a head at stride 2 (0.1 m cells) that
regresses the sub-cell centre offset. See the package docstring for the measurements behind them. The
lengths are `Length` settings (shared/scene/scale.py): `at_scale` sizes the defaults for another scene
(the same 160 x 160 grid, its pillars and window the scene's car lengths), which is how a model to be
trained at another site starts (`rmmdet train lidar --scene`). A trained model's config is explicit.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.scene.scale import LENGTH, Length

# The backbone has two stride-2 stages; the neck brings both to stride 2, so the grid must divide by 4.
GRID_DIVISOR = 4
HEAD_STRIDE = 2


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class GridConfig(_Model):
    """Point-cloud range and pillar grid (agent frame: x east, y north, z up, z = 0 the table)."""

    x_min_m: Length = Field(-4.0, description="grid range x start (inclusive), metres")
    x_max_m: Length = Field(4.0, description="grid range x end (exclusive), metres")
    y_min_m: Length = Field(-4.0, description="grid range y start (inclusive), metres")
    y_max_m: Length = Field(4.0, description="grid range y end (exclusive), metres")
    z_min_m: Length = Field(-0.05, description="points below this height are dropped, metres")
    z_max_m: Length = Field(0.8, description="points at or above this height are dropped, metres")
    pillar_size_m: Length = Field(0.05, gt=0, description="square pillar edge (x and y), metres")
    max_points_per_pillar: int = Field(
        20, ge=1, description="points kept per pillar (the first ones in input order); the rest are dropped"
    )
    max_pillars: int = Field(
        16000, ge=1, description="non-empty pillars kept per frame (the most populated ones)"
    )

    @model_validator(mode="after")
    def _check(self) -> GridConfig:
        if self.x_max_m <= self.x_min_m or self.y_max_m <= self.y_min_m or self.z_max_m <= self.z_min_m:
            raise ValueError("grid ranges must have max > min")
        for name, extent in (("x", self.x_max_m - self.x_min_m), ("y", self.y_max_m - self.y_min_m)):
            cells = extent / self.pillar_size_m
            if abs(cells - round(cells)) > 1e-6 or round(cells) % GRID_DIVISOR:
                raise ValueError(
                    f"{name} extent {extent} m must be a multiple of {GRID_DIVISOR} pillars of "
                    f"{self.pillar_size_m} m"
                )
        return self

    @property
    def nx(self) -> int:
        """Pillars along x (grid columns)."""
        return round((self.x_max_m - self.x_min_m) / self.pillar_size_m)

    @property
    def ny(self) -> int:
        """Pillars along y (grid rows)."""
        return round((self.y_max_m - self.y_min_m) / self.pillar_size_m)

    @property
    def head_nx(self) -> int:
        return self.nx // HEAD_STRIDE

    @property
    def head_ny(self) -> int:
        return self.ny // HEAD_STRIDE

    @property
    def head_cell_m(self) -> float:
        """Edge of one head (output) cell, metres."""
        return self.pillar_size_m * HEAD_STRIDE


class NetConfig(_Model):
    """Network widths: PFN -> BEV canvas -> two stride-2 conv stages -> neck at stride 2 -> head."""

    pfn_channels: int = Field(32, ge=1, description="pillar feature width (BEV canvas channels)")
    stage_channels: tuple[int, int] = Field((48, 96), description="conv widths of the stride-2 and -4 stages")
    stage_layers: tuple[int, int] = Field((2, 3), description="3x3 convs after each stage's strided conv")
    neck_channels: int = Field(64, ge=1, description="channels of each upsampled stage in the neck")
    head_channels: int = Field(48, ge=1, description="width of the shared 3x3 conv of the head")
    bn_momentum: float = Field(0.01, gt=0, lt=1, description="BatchNorm momentum (PyTorch convention)")
    bn_eps: float = Field(1e-3, gt=0, description="BatchNorm epsilon")


class HeadConfig(_Model):
    """Centre heatmap and regression targets (CenterPoint-style, one class)."""

    heatmap_sigma_m: Length = Field(
        0.06, gt=0, description="std of the Gaussian drawn around each centre on the heatmap, metres"
    )
    regression_radius_m: Length = Field(
        0.11,
        ge=0,
        description="head cells whose centre lies within this distance of a box centre regress that box "
        "(>= one cell so the peak cell always has a target), metres",
    )
    ignore_radius_m: Length = Field(
        0.2, ge=0, description="heatmap loss is masked within this distance of an ignore box centre, metres"
    )
    mean_size_m: Annotated[tuple[float, float, float] | None, LENGTH] = Field(
        None,
        description="reference (dx, dy, dz), m; sizes are regressed as log(size / this). None: the median "
        "size of the training labels, fixed when training starts (a trained model keeps its own in its "
        "config)",
    )

    def mean_size(self) -> tuple[float, float, float]:
        """`mean_size_m`, which a trained or training model always has."""
        if self.mean_size_m is None:
            raise ValueError("head.mean_size_m is unset: training fixes it from its labels (with_mean_size)")
        return self.mean_size_m

    direction_offset_rad: float = Field(
        math.pi / 4,
        description="headings are split into axis (mod pi, from sin/cos of 2*yaw) + direction bit; the bit "
        "flips at this angle + pi/2 (diagonal, away from the table's axis-aligned roads)",
    )


class PostConfig(_Model):
    """Decoding and non-maximum suppression."""

    score_threshold: float = Field(0.3, ge=0, le=1, description="peaks below this score are dropped")
    pre_nms_top_k: int = Field(128, ge=1, description="highest-scoring peaks decoded before NMS")
    nms_iou_threshold: float = Field(
        0.1, ge=0, le=1, description="rotated BEV IoU above which the lower-scoring box is suppressed"
    )
    max_detections: int = Field(64, ge=1, description="boxes returned per frame at most")


class AugmentConfig(_Model):
    """Global augmentation of a training frame (points and boxes together)."""

    mirror_y_prob: float = Field(0.5, ge=0, le=1, description="probability of mirroring y -> -y")
    mirror_x_prob: float = Field(0.5, ge=0, le=1, description="probability of mirroring x -> -x")
    quarter_turns: bool = Field(
        True,
        description="rotate by a uniform multiple of 90 deg: with the flips, the 8 symmetries of the square "
        "grid, which map pillars onto pillars and keep the table's axis-aligned roads axis-aligned",
    )
    rotation_max_rad: float = Field(
        0.0,
        ge=0,
        description="extra uniform rotation about z in [-max, max] (any angle blurs the heading prior of "
        "axis-aligned roads)",
    )
    scale_min: float = Field(0.98, gt=0, description="uniform global scaling lower bound")
    scale_max: float = Field(1.02, gt=0, description="uniform global scaling upper bound")
    translation_std_m: Length = Field(0.05, ge=0, description="std of a global x, y shift, metres")


class TrainConfig(_Model):
    """Optimiser, schedule and loss weights."""

    epochs: int = Field(15, ge=1, description="passes over the training split")
    batch_size: int = Field(4, ge=1, description="frames per step")
    lr: float = Field(3e-3, gt=0, description="peak learning rate of the one-cycle schedule (AdamW)")
    weight_decay: float = Field(1e-2, ge=0, description="AdamW weight decay")
    warmup_fraction: float = Field(0.1, gt=0, lt=1, description="share of steps spent warming up")
    grad_clip_norm: float = Field(10.0, gt=0, description="gradient norm clip")
    heatmap_weight: float = Field(1.0, ge=0, description="focal heatmap loss weight")
    offset_weight: float = Field(2.0, ge=0, description="centre offset (head cells) L1 weight")
    z_weight: float = Field(
        1.0,
        ge=0,
        description="centre height squared-error weight (head cells); squared, not L1: the deck's few "
        "vehicles stayed at the table's median height under L1",
    )
    size_weight: float = Field(1.0, ge=0, description="log-size L1 weight")
    angle_weight: float = Field(1.0, ge=0, description="sin/cos(2 yaw) L1 weight")
    direction_weight: float = Field(0.2, ge=0, description="direction-bit BCE weight")
    focal_alpha: float = Field(2.0, gt=0, description="focal loss exponent on the prediction")
    focal_beta: float = Field(4.0, gt=0, description="focal loss exponent on (1 - Gaussian) for negatives")
    seed: int = Field(0, ge=0, description="seed of weights, shuffling and augmentation")
    num_threads: int = Field(
        1,
        ge=1,
        description="torch CPU threads (on the shared 2-core dev machine, 2 OpenMP threads ran a step "
        "8x slower than 1 when another job held a core)",
    )
    crop_size_m: Length = Field(
        4.0,
        ge=0,
        description="train on square windows of this edge (a multiple of 4 pillars; 0 = the whole grid), "
        "centred uniformly over the grid: the network is fully convolutional, and a 4 m window costs a "
        "quarter of the 8 m grid",
    )
    eval_every: int = Field(2, ge=1, description="validation AP every this many epochs (and the last)")


class PointPillarsConfig(_Model):
    grid: GridConfig = GridConfig()
    net: NetConfig = NetConfig()
    head: HeadConfig = HeadConfig()
    post: PostConfig = PostConfig()
    augment: AugmentConfig = AugmentConfig()
    train: TrainConfig = TrainConfig()

    def train_grid(self) -> GridConfig:
        """Grid of the training windows: `train.crop_size_m` centred on the origin (the dataset shifts
        each frame so a random window lands there), or the detection grid when cropping is off."""
        half = self.train.crop_size_m / 2
        if half == 0:
            return self.grid
        window = {"x_min_m": -half, "x_max_m": half, "y_min_m": -half, "y_max_m": half}
        return GridConfig.model_validate({**self.grid.model_dump(), **window})

    def save(self, path: Path) -> None:
        Path(path).write_text(json.dumps(self.model_dump(mode="json"), indent=2) + "\n")

    @classmethod
    def load(cls, path: Path) -> PointPillarsConfig:
        return cls.model_validate_json(Path(path).read_text())
