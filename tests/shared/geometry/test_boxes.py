"""Known-answer tests for shared.geometry.boxes."""

from __future__ import annotations

import numpy as np
import pytest

from shared.geometry.boxes import (
    bev_corners,
    bev_intersection_area_matrix,
    bev_iou_matrix,
    box2d_centres,
    box3d_corners,
    iou2d_matrix,
    iou3d_matrix,
)

SQRT2 = np.sqrt(2.0)


# --- corners -----------------------------------------------------------------------------------------


def test_box3d_corners_order_axis_aligned() -> None:
    # Centre (1, 2, 3), length 4 along x, width 2, height 1.
    corners = box3d_corners([[1.0, 2.0, 3.0, 4.0, 2.0, 1.0, 0.0]])
    assert corners.shape == (1, 8, 3)
    expected_xy = [[3, 3], [3, 1], [-1, 1], [-1, 3]]  # front-left, front-right, rear-right, rear-left
    np.testing.assert_allclose(corners[0, :4, :2], expected_xy)
    np.testing.assert_allclose(corners[0, 4:, :2], expected_xy)
    np.testing.assert_allclose(corners[0, :4, 2], 2.5)
    np.testing.assert_allclose(corners[0, 4:, 2], 3.5)


def test_box3d_corners_heading_90() -> None:
    # Heading +90 deg: box-frame (+2, +1) (front-left) maps to world offset (-1, +2).
    corners = box3d_corners([[1.0, 2.0, 0.0, 4.0, 2.0, 1.0, np.pi / 2]])
    np.testing.assert_allclose(corners[0, :4, :2], [[0, 4], [2, 4], [2, 0], [0, 0]], atol=1e-12)


def test_bev_corners_accepts_3d_and_bev_boxes() -> None:
    boxes3d = np.array([[1.0, -2.0, 0.5, 3.0, 1.5, 1.0, 0.7], [0.0, 0.0, 0.0, 1.0, 1.0, 1.0, -2.0]])
    bev = boxes3d[:, [0, 1, 3, 4, 6]]
    np.testing.assert_allclose(bev_corners(boxes3d), bev_corners(bev))
    np.testing.assert_allclose(bev_corners(boxes3d), box3d_corners(boxes3d)[:, :4, :2])
    assert bev_corners(np.zeros((0, 5))).shape == (0, 4, 2)


# --- 2D IoU ------------------------------------------------------------------------------------------


def test_iou2d_known_answers() -> None:
    a = np.array([[0.0, 0.0, 2.0, 2.0]])
    b = np.array(
        [
            [0.0, 0.0, 2.0, 2.0],  # identical -> 1
            [5.0, 5.0, 6.0, 6.0],  # disjoint -> 0
            [2.0, 0.0, 4.0, 2.0],  # shares the edge x = 2 -> 0
            [1.0, 0.0, 3.0, 2.0],  # half overlap: inter 2, union 4 + 4 - 2 = 6 -> 1/3
            [1.0, 1.0, 3.0, 3.0],  # quarter overlap: inter 1, union 7 -> 1/7
            [0.5, 0.5, 1.0, 1.5],  # nested: 0.5 * 1 = 0.5 inside 4 -> 0.125
            [1.0, 1.0, 1.0, 1.5],  # zero width -> 0
        ]
    )
    np.testing.assert_allclose(iou2d_matrix(a, b), [[1.0, 0.0, 0.0, 1 / 3, 1 / 7, 0.125, 0.0]])


def test_iou2d_is_symmetric_matrix() -> None:
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 100, (6, 2))
    boxes = np.c_[xy, xy + rng.uniform(1, 30, (6, 2))]
    iou = iou2d_matrix(boxes, boxes[:4])
    assert iou.shape == (6, 4)
    np.testing.assert_allclose(iou[:4], iou[:4].T)
    np.testing.assert_allclose(np.diag(iou[:4]), 1.0)


def test_iou2d_degenerate_boxes_never_nan() -> None:
    point = np.array([[1.0, 1.0, 1.0, 1.0], [0.0, 0.0, 0.0, 5.0]])
    with np.errstate(all="raise"):
        iou = iou2d_matrix(point, point)
    np.testing.assert_array_equal(iou, np.zeros((2, 2)))


def test_iou2d_empty_inputs() -> None:
    assert iou2d_matrix(np.zeros((0, 4)), np.zeros((3, 4))).shape == (0, 3)
    assert iou2d_matrix(np.zeros((2, 4)), np.zeros((0, 4))).shape == (2, 0)


# --- rotated BEV IoU ---------------------------------------------------------------------------------


def test_bev_iou_unit_square_vs_45_degrees() -> None:
    # Unit square vs the same square turned 45 deg about its centre. The turned square's vertices lie
    # sqrt(2)/2 from the centre, so each pokes h = (sqrt(2) - 1) / 2 past an edge of the first square and
    # is clipped off as a right isosceles triangle of height h and area h^2. The intersection is a regular
    # octagon of area 1 - 4 h^2 = 1 - (sqrt(2) - 1)^2 = 2 (sqrt(2) - 1) ~= 0.828427.
    # Union = 2 - 2 (sqrt(2) - 1) = 4 - 2 sqrt(2), so IoU = (sqrt(2) - 1) / (2 - sqrt(2)) = 1 / sqrt(2).
    square = np.array([[0.3, -0.2, 1.0, 1.0, 0.0]])
    turned = np.array([[0.3, -0.2, 1.0, 1.0, np.pi / 4]])
    np.testing.assert_allclose(bev_intersection_area_matrix(square, turned), [[2 * (SQRT2 - 1)]], atol=1e-12)
    np.testing.assert_allclose(bev_iou_matrix(square, turned), [[1 / SQRT2]], atol=1e-12)


def test_bev_iou_known_answers() -> None:
    a = np.array([[1.0, 2.0, 4.0, 2.0, 0.3]])
    b = np.array(
        [
            [1.0, 2.0, 4.0, 2.0, 0.3],  # identical -> 1
            [1.0, 2.0, 4.0, 2.0, 0.3 + np.pi],  # heading flipped, same footprint -> 1
            [1.0, 2.0, 2.0, 1.0, 0.3],  # nested, same centre and yaw: 2 / 8 -> 0.25
            [20.0, 2.0, 4.0, 2.0, 1.0],  # disjoint -> 0
            [1.0, 2.0, 0.0, 2.0, 0.3],  # zero length -> 0
        ]
    )
    np.testing.assert_allclose(bev_iou_matrix(a, b), [[1.0, 1.0, 0.25, 0.0, 0.0]], atol=1e-12)


def test_bev_iou_rotated_box_inside_axis_aligned_square() -> None:
    # 1 x 0.5 box at any yaw fully inside a 10 x 10 square: IoU = 0.5 / 100.
    big = np.array([[0.0, 0.0, 10.0, 10.0, 0.0]])
    small = np.array([[1.0, -1.0, 1.0, 0.5, 0.7], [-2.0, 3.0, 1.0, 0.5, -2.2]])
    np.testing.assert_allclose(bev_iou_matrix(big, small), [[0.005, 0.005]], atol=1e-12)


def test_bev_iou_cross_shape() -> None:
    # 2 x 1 box and the same box turned 90 deg: intersection is the central 1 x 1 square, union 2 + 2 - 1.
    a = np.array([[0.0, 0.0, 2.0, 1.0, 0.0]])
    b = np.array([[0.0, 0.0, 2.0, 1.0, np.pi / 2]])
    np.testing.assert_allclose(bev_iou_matrix(a, b), [[1 / 3]], atol=1e-12)


def test_bev_iou_touching_edges_is_zero() -> None:
    a = np.array([[0.0, 0.0, 2.0, 2.0, 0.0]])
    b = np.array([[2.0, 0.0, 2.0, 2.0, 0.0], [0.0, 2.0, 2.0, 2.0, np.pi / 2]])
    np.testing.assert_allclose(bev_iou_matrix(a, b), [[0.0, 0.0]], atol=1e-12)


def test_bev_iou_half_overlap_rotated_frame() -> None:
    # Two 2 x 2 squares offset by 1 m along their common heading of 30 deg: inter 2, union 6 -> 1/3.
    yaw = np.pi / 6
    a = np.array([[0.0, 0.0, 2.0, 2.0, yaw]])
    b = np.array([[np.cos(yaw), np.sin(yaw), 2.0, 2.0, yaw]])
    np.testing.assert_allclose(bev_iou_matrix(a, b), [[1 / 3]], atol=1e-12)


def test_bev_iou_accepts_3d_boxes_and_empty() -> None:
    shift = 0.5 * np.array([np.cos(0.4), np.sin(0.4)])
    boxes = np.array([[0.0, 0.0, 0.5, 2.0, 1.0, 1.0, 0.4], [*shift, -3.0, 2.0, 1.0, 1.0, 0.4]])
    iou = bev_iou_matrix(boxes, boxes)
    np.testing.assert_allclose(np.diag(iou), 1.0)
    # z is ignored in BEV: shifting 0.5 m along a 2 m length at the same yaw gives 1.5 / 2.5.
    np.testing.assert_allclose(iou[0, 1], 1.5 / 2.5, atol=1e-12)
    assert bev_iou_matrix(np.zeros((0, 7)), boxes).shape == (0, 2)
    assert bev_iou_matrix(boxes, np.zeros((0, 5))).shape == (2, 0)


# --- 3D IoU ------------------------------------------------------------------------------------------


def test_iou3d_known_answers() -> None:
    a = np.array([[0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0]])
    b = np.array(
        [
            [0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0],  # identical -> 1
            [0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0],  # half overlap in z: 0.5 / (2 - 0.5) -> 1/3
            [0.0, 0.0, 1.5, 1.0, 1.0, 1.0, 0.0],  # stacked, touching in z -> 0
            [0.0, 0.0, 5.0, 1.0, 1.0, 1.0, 0.0],  # far above -> 0
            [0.5, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0],  # half in x and half in z: 0.25 / 1.75 -> 1/7
            [0.0, 0.0, 0.5, 1.0, 1.0, 1.0, np.pi / 4],  # same z range: the BEV octagon, 1/sqrt(2)
            [0.0, 0.0, 0.5, 1.0, 1.0, 0.0, 0.0],  # zero height -> 0
        ]
    )
    np.testing.assert_allclose(
        iou3d_matrix(a, b), [[1.0, 1 / 3, 0.0, 0.0, 1 / 7, 1 / SQRT2, 0.0]], atol=1e-12
    )


def test_iou3d_nested() -> None:
    # 1 x 1 x 1 cube inside a 2 x 2 x 2 cube (rotated inner box): 1 / 8.
    outer = np.array([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]])
    inner = np.array([[0.1, -0.1, 0.2, 1.0, 1.0, 1.0, 0.3]])
    np.testing.assert_allclose(iou3d_matrix(outer, inner), [[0.125]], atol=1e-12)
    np.testing.assert_allclose(iou3d_matrix(inner, outer), [[0.125]], atol=1e-12)


def test_iou3d_empty_inputs() -> None:
    assert iou3d_matrix(np.zeros((0, 7)), np.zeros((4, 7))).shape == (0, 4)
    assert iou3d_matrix(np.zeros((4, 7)), np.zeros((0, 7))).shape == (4, 0)


# --- validation --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: iou2d_matrix(np.zeros((2, 3)), np.zeros((1, 4))), "shape"),
        (lambda: iou2d_matrix([[0, 0, 1, np.nan]], [[0, 0, 1, 1]]), "finite"),
        (lambda: iou2d_matrix([[2, 0, 1, 1]], [[0, 0, 1, 1]]), "x1 <= x2"),
        (lambda: bev_iou_matrix(np.zeros((2, 6)), np.zeros((1, 5))), "shape"),
        (lambda: bev_iou_matrix([[0, 0, 1, 1, np.inf]], [[0, 0, 1, 1, 0]]), "finite"),
        (lambda: bev_iou_matrix([[0, 0, -1, 1, 0]], [[0, 0, 1, 1, 0]]), "non-negative"),
        (lambda: iou3d_matrix(np.zeros((1, 5)), np.zeros((1, 7))), "shape"),
        (lambda: iou3d_matrix([[0, 0, 0, 1, 1, -1, 0]], np.zeros((1, 7))), "non-negative"),
        (lambda: box3d_corners([[0, 0, 0, 1, 1, 1, np.nan]]), "finite"),
        (lambda: box3d_corners([0, 0, 0, 1, 1, 1, 0]), "shape"),
    ],
)
def test_invalid_inputs_raise(call, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()


def test_box2d_centres_known_answer_and_extra_columns() -> None:
    boxes = np.array([[0.0, 0.0, 4.0, 2.0, 0.9, 0.0], [10.0, 20.0, 12.0, 30.0, 0.5, 0.0]])
    np.testing.assert_allclose(box2d_centres(boxes), [[2.0, 1.0], [11.0, 25.0]])
    np.testing.assert_allclose(box2d_centres([1.0, 1.0, 3.0, 5.0]), [[2.0, 3.0]])
    assert box2d_centres(np.zeros((0, 4))).shape == (0, 2)


def test_in_bev_boxes_takes_each_box_rotated_and_grown() -> None:
    from shared.geometry.boxes import in_bev_boxes

    # a 4 x 2 m box at (10, 0) turned 90 deg (4 m along y), a 2 x 2 m one at (0, 0); z and height unused
    boxes = np.array([[10.0, 0.0, 5.0, 4.0, 2.0, 1.5, np.pi / 2], [0.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0]])
    xy = np.array(
        [[10.0, 1.9], [10.9, 0.0], [11.1, 0.0], [10.0, 2.1], [1.0, 1.0], [1.05, 0.0], [np.nan, 0.0]]
    )
    assert in_bev_boxes(xy, boxes).tolist() == [True, True, False, False, True, False, False]
    # grown by 10 %: 4.4 x 2.2 m and 2.2 x 2.2 m
    assert in_bev_boxes(xy, boxes, growth=0.1).tolist() == [True, True, True, True, True, True, False]
    assert not in_bev_boxes(xy, np.zeros((0, 7))).any()
