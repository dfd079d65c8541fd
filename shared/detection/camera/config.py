"""Configuration of the camera detector: network, input, augmentation, training, post-processing.

One `CameraDetectorConfig` describes a model end to end; training writes it next to the checkpoint
(`config.json`) and the ONNX detector reads it back, so inference always pre- and post-processes the
way the model was trained. Plain pydantic models (no environment overrides): a config file is the
record of one trained model. Pixel values are in network-input pixels unless a name says otherwise.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.detection.card import LAYOUT_LETTERBOX, CameraCard, CameraInput, CameraPost, Rounding
from shared.detection.interface import CLASS_NAMES

CONFIG_FILE = "config.json"
CARD_FILE = "model.yaml"  # the export's model card (`CameraDetectorConfig.card`)
CHECKPOINT_FILE = "model.pt"
ONNX_FILE = "model.onnx"
ONNX_INPUT = "images"  # (B, H, W, 3) uint8 RGB, letterboxed to the input size
ONNX_OUTPUT = "detections"  # (B, N, 5) float32 [x0, y0, x1, y1, score], input pixels


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class InputConfig(_Model):
    """Network input: every image is letterboxed (aspect kept, padded) to width x height."""

    width: int = Field(448, gt=0, description="network input width, px (a multiple of the output stride)")
    height: int = Field(336, gt=0, description="network input height, px (a multiple of the output stride)")
    pad_value: int = Field(114, ge=0, le=255, description="grey level of the letterbox padding")
    interpolation: Literal["linear", "area"] = Field(
        "linear",
        description="downscaling filter: linear (0.2 ms for 640x480 -> 448x336) or area (antialiased, 1 ms)",
    )

    @property
    def resize_rounding(self) -> Rounding:
        """The project's models round the resized size (its card says so: layout rmmdet)."""
        return LAYOUT_LETTERBOX["rmmdet"][1]


class NetConfig(_Model):
    """Backbone (five stride-2 stages), top-down neck to stride 8, one shared head at stride 8."""

    widths: tuple[int, int, int, int, int] = Field(
        (16, 24, 48, 64, 96), description="channels of the stride 2, 4, 8, 16, 32 stages"
    )
    blocks: tuple[int, int, int, int, int] = Field(
        (0, 1, 1, 1, 1), description="residual blocks after the downsampling conv of each stage"
    )
    neck_width: int = Field(48, gt=0, description="channels of the neck and the head")
    head_convs: int = Field(2, ge=0, description="3x3 convs in the head before the prediction layer")
    prior_prob: float = Field(
        0.01, gt=0, lt=1, description="initial score of every cell (bias init of the score logit)"
    )

    @property
    def stride(self) -> int:
        """Output stride, px: the head runs on the stride-8 feature map."""
        return 8


class AugmentConfig(_Model):
    """Training augmentations, applied to the cached letterboxed image."""

    hflip_prob: float = Field(0.5, ge=0, le=1, description="probability of a horizontal flip")
    brightness: float = Field(0.25, ge=0, le=1, description="additive brightness shift, fraction of 255, +-")
    contrast: float = Field(0.25, ge=0, lt=1, description="contrast gain 1 +- this")
    saturation: float = Field(0.3, ge=0, lt=1, description="saturation gain 1 +- this")
    scale: float = Field(0.25, ge=0, lt=1, description="zoom factor 1 +- this (about the image centre)")
    translate: float = Field(0.1, ge=0, lt=1, description="shift, fraction of the input size, +-")
    affine_prob: float = Field(0.5, ge=0, le=1, description="probability of the scale/translate warp")
    min_kept_fraction: float = Field(
        0.4, ge=0, le=1, description="a box cut by the image edge keeping less of its area becomes ignored"
    )


class AssignConfig(_Model):
    """Which output cells learn a box (FCOS-style centre sampling, one scale)."""

    center_radius: float = Field(
        2.5, gt=0, description="positive cells lie within this many strides of a box centre (and in the box)"
    )
    min_box_px: float = Field(1.0, gt=0, description="boxes narrower or lower than this are ignored, px")


class LossConfig(_Model):
    """Quality focal loss on the score (target: IoU of the predicted box), GIoU loss on the box."""

    qfl_beta: float = Field(2.0, ge=0, description="quality focal loss modulating exponent")
    box_weight: float = Field(2.0, gt=0, description="weight of the GIoU loss against the score loss")


class TrainConfig(_Model):
    """Optimiser, schedule and data loading. The schedule also ends on the time budget."""

    epochs: int = Field(18, gt=0, description="passes over the training split (at most; see max_minutes)")
    batch_size: int = Field(32, gt=0, description="images per step")
    lr: float = Field(8e-3, gt=0, description="peak AdamW learning rate")
    weight_decay: float = Field(1e-4, ge=0, description="AdamW weight decay (not on norms and biases)")
    warmup_steps: int = Field(150, ge=0, description="linear learning-rate warm-up, steps")
    final_lr_fraction: float = Field(0.02, ge=0, le=1, description="cosine decay ends at lr x this")
    ema_decay: float = Field(0.998, ge=0, lt=1, description="decay of the weight EMA that is saved (0: off)")
    grad_clip: float = Field(10.0, gt=0, description="gradient-norm clip")
    max_minutes: float = Field(
        36.0, gt=0, description="wall-clock budget: the schedule follows max(step, time) progress, then stops"
    )
    num_workers: int = Field(
        1, ge=0, description="DataLoader worker processes: augmentation runs beside the network (RAM cache)"
    )
    threads: int = Field(
        1,
        ge=0,
        description="torch CPU threads (0: torch's default). 2 is ~1.7x faster on an idle 2-core machine, "
        "but many times slower while another process keeps a core busy",
    )
    bf16: bool = Field(
        True, description="bfloat16 autocast of the forward pass (about 2x faster on CPUs with AVX512-BF16)"
    )
    seed: int = Field(0, ge=0, description="seed of weights init, shuffling and augmentation")
    val_images: int = Field(
        600, ge=0, description="validation images evaluated after each epoch, evenly spaced (0: all)"
    )


class PostprocessConfig(_Model):
    """Score threshold and NMS of `OnnxCameraDetector`."""

    score_threshold: float = Field(
        0.05,
        ge=0,
        le=1,
        description="detections below this score are dropped (scores estimate the box IoU; low keeps "
        "AP: 0.3 costs ~1 point of AP@0.5)",
    )
    nms_iou: float = Field(
        0.6,
        gt=0,
        le=1,
        description="NMS IoU threshold (0.6 chosen on the validation split: cars queue and overlap)",
    )
    pre_nms_top_k: int = Field(
        1000,
        gt=0,
        description="best cells kept before NMS, per image: every car lights up ~10-20 cells, so 200 cut "
        "the weakest cars of dense scenes (validation AP@0.5 0.950 -> 0.967 at 1000)",
    )
    max_detections: int = Field(300, gt=0, description="detections kept after NMS, per image")


class CameraDetectorConfig(_Model):
    """Everything one trained camera detector needs, saved as `config.json` next to the model."""

    input: InputConfig = InputConfig()
    net: NetConfig = NetConfig()
    augment: AugmentConfig = AugmentConfig()
    assign: AssignConfig = AssignConfig()
    loss: LossConfig = LossConfig()
    train: TrainConfig = TrainConfig()
    post: PostprocessConfig = PostprocessConfig()

    @model_validator(mode="after")
    def _input_fits_stride(self) -> CameraDetectorConfig:
        stride = self.net.stride
        if self.input.width % stride or self.input.height % stride:
            size = f"{self.input.width}x{self.input.height}"
            raise ValueError(f"input {size} is not a multiple of the output stride {stride}")
        return self

    def save(self, path: Path) -> None:
        Path(path).write_text(self.model_dump_json(indent=2) + "\n")

    def card(self, model: str = ONNX_FILE) -> CameraCard:
        """The model card of this model's ONNX export (`model`, beside the card): NHWC uint8 RGB,
        top-left letterbox, boxes decoded in the graph (layout rmmdet), one class, car."""
        return CameraCard(
            kind="camera",
            model=model,
            layout="rmmdet",
            input=CameraInput(
                width=self.input.width,
                height=self.input.height,
                tensor="nhwc_uint8",
                colour="rgb",
                letterbox=LAYOUT_LETTERBOX["rmmdet"][0],
                resize_rounding=self.input.resize_rounding,
                pad_value=self.input.pad_value,
                interpolation=self.input.interpolation,
            ),
            num_classes=1,
            classes={0: CLASS_NAMES[0]},
            post=CameraPost(**self.post.model_dump()),
        )

    @classmethod
    def load(cls, path: Path) -> CameraDetectorConfig:
        return cls.model_validate(json.loads(Path(path).read_text()))
