"""Pascal VOC XML labels: one `annotation` per image with `object/bndbox` corners in 1-based,
inclusive pixel coordinates (xmin = x0 + 1, xmax = x1 for our exclusive x1).

Written with `xml.etree.ElementTree`; coordinates keep up to 10 significant digits, so integer pixel
boxes come back exactly and sub-pixel ones within 1e-6.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FLOAT_FORMAT = "%.10g"
CHANNELS = 3


@dataclass(frozen=True)
class VocAnnotation:
    filename: str
    width_px: int
    height_px: int
    boxes_px: np.ndarray  # (N, 4) x0, y0, x1, y1 (x1, y1 exclusive)
    names: list[str]
    difficult: list[bool]
    truncated: list[bool]


def to_xml(a: VocAnnotation) -> str:
    root = ET.Element("annotation")
    ET.SubElement(root, "filename").text = a.filename
    size = ET.SubElement(root, "size")
    for tag, count in (("width", a.width_px), ("height", a.height_px), ("depth", CHANNELS)):
        ET.SubElement(size, tag).text = str(count)
    for box, name, difficult, truncated in zip(a.boxes_px, a.names, a.difficult, a.truncated, strict=True):
        obj = ET.SubElement(root, "object")
        ET.SubElement(obj, "name").text = name
        ET.SubElement(obj, "pose").text = "Unspecified"
        ET.SubElement(obj, "truncated").text = str(int(truncated))
        ET.SubElement(obj, "difficult").text = str(int(difficult))
        bnd = ET.SubElement(obj, "bndbox")
        x0, y0, x1, y1 = (float(v) for v in box)
        for tag, value in (("xmin", x0 + 1), ("ymin", y0 + 1), ("xmax", x1), ("ymax", y1)):
            ET.SubElement(bnd, tag).text = FLOAT_FORMAT % value
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"


def from_xml(text: str) -> VocAnnotation:
    """Parse a VOC annotation; raises ValueError when a required element is missing."""
    root = ET.fromstring(text)

    def need(parent: ET.Element, tag: str) -> str:
        el = parent.find(tag)
        if el is None or el.text is None:
            raise ValueError(f"VOC annotation lacks <{tag}>")
        return el.text

    size = root.find("size")
    if size is None:
        raise ValueError("VOC annotation lacks <size>")
    boxes, names, difficult, truncated = [], [], [], []
    for obj in root.findall("object"):
        bnd = obj.find("bndbox")
        if bnd is None:
            raise ValueError("VOC object lacks <bndbox>")
        xmin, ymin, xmax, ymax = (float(need(bnd, t)) for t in ("xmin", "ymin", "xmax", "ymax"))
        boxes.append((xmin - 1, ymin - 1, xmax, ymax))
        names.append(need(obj, "name"))
        difficult.append(obj.findtext("difficult", "0") == "1")
        truncated.append(obj.findtext("truncated", "0") == "1")
    return VocAnnotation(
        filename=need(root, "filename"),
        width_px=int(need(size, "width")),
        height_px=int(need(size, "height")),
        boxes_px=np.asarray(boxes, float).reshape(-1, 4),
        names=names,
        difficult=difficult,
        truncated=truncated,
    )


def write_voc(path: Path, annotation: VocAnnotation) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(to_xml(annotation))


def read_voc(path: Path) -> VocAnnotation:
    return from_xml(path.read_text())


def voc_annotation(
    filename: str, width_px: int, height_px: int, boxes_px: np.ndarray, name: str, difficult: Sequence[bool]
) -> VocAnnotation:
    """Annotation of one image; a box touching the image border is marked truncated."""
    boxes = np.asarray(boxes_px, float).reshape(-1, 4)
    truncated = [bool(b[0] <= 0 or b[1] <= 0 or b[2] >= width_px or b[3] >= height_px) for b in boxes]
    return VocAnnotation(
        filename, width_px, height_px, boxes, [name] * len(boxes), list(difficult), truncated
    )
