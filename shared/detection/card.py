"""Model cards: a YAML file beside an ONNX detector saying what the network expects and returns, so a
detector trained elsewhere (a YOLO-family export, an OpenPCDet PointPillars export) runs in the MEC
with no code change (issue 36; the paper's "any pair of 2D and 3D detectors as modules").

    kind: camera                      # camera | lidar
    model: yolov8n.onnx               # beside the card
    layout: yolov8                    # the output layout: CAMERA_LAYOUTS / LIDAR_LAYOUTS
    input: {width: 640, height: 640, tensor: nchw_float32, colour: rgb, scale: 0.00392156862745098,
            letterbox: centre, pad_value: 114}
    classes: {2: car, 5: car, 7: car} # model class index -> the project's class; others dropped
    num_classes: 80                   # the model's class count (checked against its output shape)
    post: {score_threshold: 0.25, nms_iou: 0.6, pre_nms_top_k: 1000, max_detections: 300}
    tiles: {image_width_px: 1920, image_height_px: 1200, whole_image: true,   # optional: large images
            bands: [{y0_px: 150, y1_px: 566, scale: 0.5, min_overlap_px: 200}]}

`load_card` validates a card (unknown fields, layouts, classes are errors); the detectors
(`shared.detection.camera.card_detector`, `shared.detection.lidar.openpcdet`) check it against the ONNX
graph's input and output shapes when they load, so a card that does not fit its model is a clear error
at start, never an empty output.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from shared.config import ConfigError, read_yaml
from shared.detection.interface import CLASS_NAMES
from shared.detection.precision import model_file

CARD_SUFFIXES = (".yaml", ".yml")
#: Camera output layouts (`shared.detection.camera.layouts`).
CAMERA_LAYOUTS = ("rmmdet", "yolov8", "yolov5", "yolox")
Placement = Literal["top_left", "centre"]
Rounding = Literal["floor", "nearest"]
#: Each camera layout's family pre-processing: where the resized image sits in the input and how its
#: size is rounded (`shared.detection.camera.geometry.resized_size`), read from each family's published
#: code: YOLOX `yolox/data/data_augment.py` `preproc` (top-left, `int(w * r)`: truncated); YOLOv5
#: `utils/augmentations.py` `letterbox` and Ultralytics `ultralytics/data/augment.py` `LetterBox`
#: (centred, `int(round(w * r))`, padding `round(d / 2 - 0.1)` before the image, which for a whole
#: number of pixels d is d // 2); the project's own models (top-left, rounded). A card's `input` may say
#: otherwise (an export with its own pre-processing); unset, it takes its layout's.
LAYOUT_LETTERBOX: dict[str, tuple[Placement, Rounding]] = {
    "rmmdet": ("top_left", "nearest"),
    "yolov8": ("centre", "nearest"),
    "yolov5": ("centre", "nearest"),
    "yolox": ("top_left", "floor"),
}
#: Lidar output layouts: the project's centre-heatmap PointPillars, OpenPCDet's anchor head and its
#: CenterHead (CenterPoint).
LIDAR_LAYOUTS = ("rmmdet_pointpillars", "openpcdet_anchor", "openpcdet_center")


class _Card(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraInput(_Card):
    """How an image becomes the network's input tensor: letterboxed (aspect kept) to width x height,
    colour order, dtype and layout, then `(value * scale - mean) / std` per channel (float tensors)."""

    width: int = Field(gt=0, description="network input width, px")
    height: int = Field(gt=0, description="network input height, px")
    tensor: Literal["nhwc_uint8", "nchw_float32"] = Field(
        description="nhwc_uint8: (B, H, W, 3) bytes as they are; nchw_float32: (B, 3, H, W) float32"
    )
    colour: Literal["rgb", "bgr"] = Field("rgb", description="channel order the network was trained on")
    scale: float = Field(1.0, gt=0, description="pixel values are multiplied by this (1/255: to [0, 1])")
    mean: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="subtracted after scaling")
    std: tuple[float, float, float] = Field((1.0, 1.0, 1.0), description="divided by after the mean")
    letterbox: Placement = Field(
        "top_left",
        description="where the resized image sits in the input (the rest is padding); unset in a card: "
        "its layout family's (LAYOUT_LETTERBOX)",
    )
    resize_rounding: Rounding = Field(
        "nearest",
        description="the resized image's size in input px: floor (YOLOX truncates) or nearest "
        "(Ultralytics, YOLOv5, the project); unset in a card: its layout family's (LAYOUT_LETTERBOX)",
    )
    pad_value: int = Field(114, ge=0, le=255, description="grey level of the padding")
    interpolation: Literal["linear", "area"] = Field("linear", description="downscaling filter")

    @model_validator(mode="after")
    def _check(self) -> CameraInput:
        if self.tensor == "nhwc_uint8" and (self.scale, self.mean, self.std) != (1.0, (0, 0, 0), (1, 1, 1)):
            raise ValueError("an nhwc_uint8 input takes the bytes as they are: no scale, mean or std")
        if any(s <= 0 for s in self.std):
            raise ValueError(f"std {self.std}: every channel's must be > 0")
        return self


class CameraPost(_Card):
    """Which decoded boxes are kept: score threshold, the best `pre_nms_top_k`, NMS per class."""

    score_threshold: float = Field(0.25, ge=0, le=1)
    nms_iou: float = Field(0.6, gt=0, le=1)
    pre_nms_top_k: int = Field(1000, gt=0)
    max_detections: int = Field(300, gt=0)


class YoloxGrid(_Card):
    """YOLOX's raw head output (exported without `--decode_in_inference`): boxes are offsets on the
    stride grids, decoded here."""

    strides: tuple[int, ...] = Field((8, 16, 32), description="the heads' strides, px, in output order")


class TileBand(_Card):
    """A horizontal band of the full image cut into overlapping tiles, each `scale` x its size in image
    px to the network's input: the band's rows `y0_px`..`y1_px` (full-image px), split into as few
    evenly spaced tiles as leave at least `min_overlap_px` (image px) between neighbours, across the
    whole image width and the band's height. A car cut by a tile's inner edge is dropped there and
    found whole in its neighbour, so the overlap should exceed the widest car the band shows."""

    y0_px: int = Field(ge=0, description="first row of the band, full-image px")
    y1_px: int = Field(gt=0, description="row after the band's last, full-image px")
    scale: float = Field(1.0, gt=0, le=4, description="network-input px per image px in these tiles")
    min_overlap_px: int = Field(
        128, ge=0, description="least overlap of neighbouring tiles, image px (strips have none)"
    )

    @model_validator(mode="after")
    def _check(self) -> TileBand:
        if self.y1_px <= self.y0_px:
            raise ValueError(f"band rows {self.y0_px}..{self.y1_px}: y1_px must be > y0_px")
        return self


class CameraTiles(_Card):
    """How a detector at its input size sees a large image (`shared.detection.camera.tiled`): tiles of
    road bands at a finer scale (far, small cars) and optionally the whole image letterboxed (near, large
    cars); detections go back to full-image px and are merged across tiles by NMS. Pixels are those of
    an `image_width_px` x `image_height_px` image; another size scales the layout with it."""

    image_width_px: int = Field(gt=0, description="the image size the layout is drawn for, px")
    image_height_px: int = Field(gt=0)
    bands: tuple[TileBand, ...] = Field((), description="tiled bands (none: the whole image only)")
    whole_image: bool = Field(True, description="also run the whole image letterboxed (near, large cars)")
    strips: bool = Field(
        False,
        description="each band in one network run, the image's full width at the band's scale (no tiles, "
        "no overlap); needs a model whose input height and width are free (e.g. 1536 x 288 for a band)",
    )
    whole_image_scale: float | None = Field(
        None,
        gt=0,
        le=1,
        description="with strips: the whole image at this scale, at its own aspect (none: letterboxed "
        "into the card's input)",
    )
    merge_iou: float = Field(0.5, gt=0, le=1, description="NMS IoU merging detections of different tiles")
    edge_px: float = Field(
        2.0, ge=0, description="a box within this of a tile edge inside the image is cut by it (dropped)"
    )

    @model_validator(mode="after")
    def _check(self) -> CameraTiles:
        if not self.bands and not self.whole_image:
            raise ValueError("no tiles: give bands, whole_image or both")
        if self.whole_image_scale is not None and not (self.strips and self.whole_image):
            raise ValueError("whole_image_scale is for a card with strips and whole_image")
        for band in self.bands:
            if band.y1_px > self.image_height_px:
                raise ValueError(f"band rows ..{band.y1_px} beyond the image's {self.image_height_px}")
        return self


class CameraCard(_Card):
    kind: Literal["camera"]
    model: str = Field(description="ONNX file, relative to the card")
    layout: Literal["rmmdet", "yolov8", "yolov5", "yolox"]
    input: CameraInput
    num_classes: int = Field(1, gt=0, description="the model's class count")
    classes: dict[int, str] = Field(description="model class index -> project class; others dropped")
    post: CameraPost = CameraPost()
    yolox: YoloxGrid | None = Field(None, description="layout yolox: the raw grid output to decode")
    tiles: CameraTiles | None = Field(
        None, description="large images in tiles (`shared.detection.camera.tiled`); none: letterboxed whole"
    )

    @model_validator(mode="before")
    @classmethod
    def _family_letterbox(cls, data: object) -> object:
        """An input's placement and rounding, where the card leaves them out, from its layout family."""
        if not isinstance(data, dict) or not isinstance(data.get("input"), dict):
            return data
        family = LAYOUT_LETTERBOX.get(data.get("layout"))  # type: ignore[arg-type]
        if family is None:
            return data  # an unknown layout: its own validation says so
        placement, rounding = family
        return {**data, "input": {"letterbox": placement, "resize_rounding": rounding, **data["input"]}}

    @model_validator(mode="after")
    def _check(self) -> CameraCard:
        _check_classes(self.classes, self.num_classes)
        if self.layout == "rmmdet" and self.num_classes != 1:
            raise ValueError("layout rmmdet has one class (its score column)")
        return self


class PillarGrid(_Card):
    """OpenPCDet's point cloud range and pillar size (`POINT_CLOUD_RANGE`, `VOXEL_SIZE`), metres."""

    point_cloud_range_m: tuple[float, float, float, float, float, float] = Field(
        description="x_min, y_min, z_min, x_max, y_max, z_max in the cloud's frame"
    )
    voxel_size_m: tuple[float, float, float] = Field(description="pillar x, y size and the z extent")
    max_points_per_voxel: int = Field(32, gt=0)
    max_voxels: int = Field(16000, gt=0)


class Anchor(_Card):
    """One class's anchors (OpenPCDet `ANCHOR_GENERATOR_CONFIG`): size, rotations, bottom height."""

    class_name: str = Field(description="the model's class name (for messages)")
    size_m: tuple[float, float, float] = Field(description="dx, dy, dz")
    rotations_rad: tuple[float, ...] = Field((0.0, 1.5707963), min_length=1)
    bottom_height_m: float = 0.0


class LidarPost(_Card):
    score_threshold: float = Field(0.3, ge=0, le=1)
    nms_iou: float = Field(0.1, gt=0, le=1, description="rotated BEV IoU")
    pre_nms_top_k: int = Field(4096, gt=0)
    max_detections: int = Field(64, gt=0)


class OpenPCDetHead(_Card):
    """OpenPCDet's AnchorHeadSingle as exported: class, box and direction maps (B, H, W, A x ...), box
    residuals by ResidualCoder, a direction classifier of `num_dir_bins` bins."""

    anchors: tuple[Anchor, ...] = Field(min_length=1)
    align_center: bool = False
    dir_offset_rad: float = 0.78539
    dir_limit_offset: float = 0.0
    num_dir_bins: int = Field(2, gt=0)
    point_features: Literal["xyzi", "augmented"] = Field(
        "xyzi",
        description="per point: x, y, z, intensity (the graph augments them), or OpenPCDet's PillarVFE "
        "10 (x, y, z, i, offsets from the pillar's mean and centre) done here",
    )
    inputs: tuple[str, str, str] = Field(
        ("voxels", "voxel_num_points", "voxel_coords"),
        description="input names: points per pillar, point counts, pillar coordinates (batch, z, y, x)",
    )
    outputs: tuple[str, str, str] = Field(("cls_preds", "box_preds", "dir_cls_preds"))


class CenterTask(_Card):
    """One of CenterHead's separate heads (a task): the model classes of its heatmap's channels, in
    order, and the names of its five output maps (NCHW)."""

    classes: tuple[int, ...] = Field(min_length=1, description="model class index of each heatmap channel")
    heatmap: str = Field(description="(1, classes, H, W) logits (`hm`)")
    center: str = Field(description="(1, 2, H, W) x, y offset within the cell, cells")
    center_z: str = Field(description="(1, 1, H, W) box centre height, m")
    dim: str = Field(description="(1, 3, H, W) log of dx, dy, dz")
    rot: str = Field(description="(1, 2, H, W) cos, sin of the heading")

    @property
    def outputs(self) -> tuple[str, str, str, str, str]:
        return (self.heatmap, self.center, self.center_z, self.dim, self.rot)


class OpenPCDetCenterHead(_Card):
    """OpenPCDet's CenterHead (CenterPoint) as exported: per task a heatmap and the box maps, decoded as
    its `centernet_utils.decode_bbox_from_heatmap` does; NMS per task as its post-processing does."""

    tasks: tuple[CenterTask, ...] = Field(min_length=1)
    feature_map_stride: int = Field(gt=0, description="pillars per feature-map cell (its FEATURE_MAP_STRIDE)")
    max_objects: int = Field(500, gt=0, description="cells kept per task before the threshold (its K)")
    post_center_limit_range_m: tuple[float, float, float, float, float, float] | None = Field(
        None, description="boxes centred outside this x, y, z range are dropped (its POST_CENTER_LIMIT_RANGE)"
    )
    point_features: Literal["xyzi", "augmented"] = Field("xyzi", description="as OpenPCDetHead's")
    inputs: tuple[str, str, str] = Field(("voxels", "voxel_num_points", "voxel_coords"))


class LidarCard(_Card):
    kind: Literal["lidar"]
    model: str
    layout: Literal["rmmdet_pointpillars", "openpcdet_anchor", "openpcdet_center"]
    classes: dict[int, str]
    num_classes: int = Field(1, gt=0)
    grid: PillarGrid | None = Field(None, description="layouts openpcdet_anchor and openpcdet_center")
    head: OpenPCDetHead | None = Field(None, description="layout openpcdet_anchor")
    center: OpenPCDetCenterHead | None = Field(None, description="layout openpcdet_center")
    post: LidarPost | None = Field(None, description="OpenPCDet layouts (default: LidarPost())")

    @model_validator(mode="after")
    def _check(self) -> LidarCard:
        _check_classes(self.classes, self.num_classes)
        if self.layout == "openpcdet_anchor":
            if self.grid is None or self.head is None or self.center is not None:
                raise ValueError("layout openpcdet_anchor needs `grid` and `head` (no `center`)")
            if len(self.head.anchors) != self.num_classes:
                raise ValueError(f"{len(self.head.anchors)} anchor classes for {self.num_classes} classes")
        elif self.layout == "openpcdet_center":
            if self.grid is None or self.center is None or self.head is not None:
                raise ValueError("layout openpcdet_center needs `grid` and `center` (no `head`)")
            scored = sorted(c for task in self.center.tasks for c in task.classes)
            if scored != list(range(self.num_classes)):
                raise ValueError(
                    f"the tasks' heatmaps score classes {scored}: each of the {self.num_classes} classes once"
                )
        elif (
            self.grid is not None or self.head is not None or self.center is not None or self.post is not None
        ):
            raise ValueError("layout rmmdet_pointpillars reads its grid, head and post from the model's JSON")
        return self

    @property
    def pillar_input(self) -> OpenPCDetHead | OpenPCDetCenterHead:
        """The OpenPCDet head whose pillar input (point features, input names) the graph takes."""
        head = self.head if self.head is not None else self.center
        if head is None:
            raise ValueError(f"layout {self.layout} takes no OpenPCDet pillars")
        return head

    @property
    def post_or_default(self) -> LidarPost:
        return self.post if self.post is not None else LidarPost()


ModelCard = Annotated[CameraCard | LidarCard, Field(discriminator="kind")]


class _CardFile(_Card):
    card: ModelCard


C = TypeVar("C", CameraCard, LidarCard)


def _check_classes(classes: dict[int, str], num_classes: int) -> None:
    if not classes:
        raise ValueError("no class maps to one of the project's: the detector would find nothing")
    for index, name in classes.items():
        if not 0 <= index < num_classes:
            raise ValueError(f"class index {index} outside the model's {num_classes} classes")
        if name not in CLASS_NAMES:
            raise ValueError(f"class {index} -> {name!r}: the project's classes are {CLASS_NAMES}")


def is_card(name: str | Path) -> bool:
    """Whether a detector name is a path to a card (rather than a registered name)."""
    return Path(name).suffix in CARD_SUFFIXES


def load_card(path: Path) -> CameraCard | LidarCard:
    """A validated card (ConfigError naming the file and the field)."""
    try:
        data = read_yaml(path)
        return _CardFile.model_validate({"card": data}).card
    except ValidationError as err:
        raise ConfigError(f"{path}: not a valid model card: {err}") from None


def save_card(path: Path, card: CameraCard | LidarCard, note: str) -> None:
    """Write `card` as YAML, `note` (who wrote it, from what) as its first comment line."""
    data = card.model_dump(mode="json", exclude_none=True)
    data["classes"] = {int(k): v for k, v in data["classes"].items()}  # JSON mode made them strings
    body = yaml.safe_dump(data, sort_keys=False, default_flow_style=None)
    path.write_text(f"# {note}\n{body}")


def load_card_and_model(card_path: Path, kind: type[C], precision: str = "fp32") -> tuple[C, Path]:
    """A card of `kind` (CameraCard, LidarCard) and its model file in `precision`
    (`shared.detection.precision`): ConfigError for an invalid card or one of the other kind,
    FileNotFoundError for a missing model."""
    card = load_card(card_path)
    if not isinstance(card, kind):
        raise ConfigError(
            f"{card_path}: a {card.kind} card, not a {kind.__name__.removesuffix('Card').lower()} detector's"
        )
    path = model_file(model_path(card_path, card), precision)
    if not path.is_file():
        raise FileNotFoundError(f"no {precision} model {path} for {card_path}")
    return card, path


def model_path(card_path: Path, card: CameraCard | LidarCard) -> Path:
    """The card's ONNX file (relative to the card); ConfigError if missing."""
    path = (card_path.parent / card.model).resolve()
    if not path.is_file():
        raise ConfigError(f"{card_path}: model {card.model} not found at {path}")
    return path
