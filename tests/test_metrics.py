"""Metrics against hand-computed cases: pixels, empty masks, boxes, AP, aggregation."""

import math

import numpy as np
import pandas as pd
import pytest

from gdiff import metrics as M


def _rect(h, w, *rects):
    m = np.zeros((h, w), bool)
    for x0, y0, x1, y1 in rects:
        m[y0:y1, x0:x1] = True
    return m


def test_pixel_scores_hand_computed():
    gt = _rect(10, 10, (0, 0, 4, 4))  # 16 px
    pred = _rect(10, 10, (2, 0, 6, 4))  # 16 px, overlap 2x4 = 8
    s = M.pixel_scores(pred, gt)
    assert (s["TP"], s["FP"], s["FN"]) == (8, 8, 8)
    assert s["P"] == pytest.approx(0.5)
    assert s["R"] == pytest.approx(0.5)
    assert s["F1"] == pytest.approx(0.5)
    assert s["IoU"] == pytest.approx(8 / 24)


def test_pixel_scores_accept_255_masks_and_check_shape():
    gt = _rect(6, 6, (0, 0, 3, 3)).astype(np.uint8) * 255
    s = M.pixel_scores(gt, gt)
    assert s["P"] == s["R"] == s["F1"] == s["IoU"] == 1.0
    with pytest.raises(ValueError, match="shape"):
        M.pixel_scores(np.zeros((4, 4)), np.zeros((4, 5)))


def test_empty_prediction_nonempty_gt():
    gt = _rect(8, 8, (1, 1, 3, 3))
    s = M.pixel_scores(np.zeros_like(gt), gt)
    assert math.isnan(s["P"])
    assert s["R"] == 0 and s["F1"] == 0 and s["IoU"] == 0
    assert s["FN"] == 4


def test_empty_gt_nonempty_prediction():
    pred = _rect(8, 8, (1, 1, 3, 3))
    s = M.pixel_scores(pred, np.zeros_like(pred))
    assert math.isnan(s["R"])
    assert s["P"] == 0 and s["F1"] == 0 and s["IoU"] == 0


def test_both_empty_is_undefined():
    z = np.zeros((5, 5), bool)
    s = M.pixel_scores(z, z)
    assert all(math.isnan(s[k]) for k in ("P", "R", "F1", "IoU"))
    assert (s["TP"], s["FP"], s["FN"]) == (0, 0, 0)


def test_connected_regions_boxes_and_min_area():
    m = _rect(20, 20, (1, 2, 5, 4), (10, 10, 11, 11))  # 4x2 region and a single pixel
    r = M.connected_regions(m)
    assert sorted(map(tuple, r.boxes.tolist())) == [(1, 2, 5, 4), (10, 10, 11, 11)]
    r = M.connected_regions(m, min_area=2)
    assert r.boxes.tolist() == [[1, 2, 5, 4]]
    assert r.areas.tolist() == [8]
    # the dropped region is background in the label image
    assert r.labels[10, 10] == 0 and r.labels[2, 1] == 1
    # diagonal neighbours join with 8-connectivity but not with 4
    d = np.eye(4, dtype=bool)
    assert len(M.connected_regions(d).boxes) == 1
    assert len(M.connected_regions(d, connectivity=4).boxes) == 4


def test_box_iou_hand_computed():
    a = np.array([[0, 0, 4, 4]])
    b = np.array([[2, 0, 6, 4], [10, 10, 12, 12], [0, 0, 4, 4]])
    iou = M.box_iou(a, b)
    assert iou.shape == (1, 3)
    assert iou[0].tolist() == pytest.approx([8 / 24, 0.0, 1.0])


def test_match_boxes_greedy_by_score_one_gt_once():
    gt = np.array([[0, 0, 10, 10]])
    pred = np.array([[0, 0, 10, 9], [0, 0, 10, 10], [50, 50, 60, 60]])
    # the higher-scored prediction takes the only GT even though the other fits better
    matched, best = M.match_boxes(pred, np.array([0.9, 0.5, 0.8]), gt, 0.5)
    assert matched.tolist() == [True, False, False]
    assert best[0] == pytest.approx(0.9)
    assert best[1] == pytest.approx(1.0)  # its best overlap, though unmatched
    # IoU just below the threshold is not a match
    matched, _ = M.match_boxes(np.array([[0, 0, 10, 4]]), np.array([1.0]), gt, 0.5)
    assert not matched[0]


def test_average_precision_hand_computed():
    # ranked: TP, FP, TP with 3 GT -> precision 1, 1/2, 2/3 at recall 1/3, 1/3, 2/3
    ap = M.average_precision(np.array([0.9, 0.8, 0.7]), np.array([True, False, True]), 3)
    # envelope: p=1 up to r=1/3, p=2/3 from 1/3 to 2/3
    assert ap == pytest.approx(1 / 3 * 1 + 1 / 3 * 2 / 3)
    assert M.average_precision(np.array([]), np.array([], bool), 2) == 0.0
    assert math.isnan(M.average_precision(np.array([0.5]), np.array([False]), 0))
    assert M.average_precision(np.array([0.3, 0.9]), np.array([True, True]), 2) == 1.0


def test_box_scores_rank_by_probability_else_area():
    gt = _rect(40, 40, (0, 0, 10, 10))
    # a large false region and a small region matching the GT box
    pred = _rect(40, 40, (0, 0, 10, 10), (20, 20, 40, 40))
    by_area, boxes = M.box_scores(pred, gt)
    # by area the false region ranks first: precision 0 then 1/2 at recall 1 -> AP 0.5
    assert by_area["box_AP"] == pytest.approx(0.5)
    assert (by_area["box_TP"], by_area["box_FP"], by_area["box_FN"]) == (1, 1, 0)
    assert by_area["box_P"] == 0.5 and by_area["box_R"] == 1.0
    assert by_area["box_F1"] == pytest.approx(2 / 3)
    prob = np.where(_rect(40, 40, (0, 0, 10, 10)), 0.9, 0.6)
    by_prob, boxes = M.box_scores(pred, gt, prob)
    assert by_prob["box_AP"] == pytest.approx(1.0)
    pb = boxes[boxes["kind"] == "pred"].sort_values("score")
    assert pb["score"].tolist() == pytest.approx([0.6, 0.9])
    assert (boxes["kind"] == "gt").sum() == 1


def test_box_scores_empty_cases():
    z = np.zeros((16, 16), bool)
    gt = _rect(16, 16, (2, 2, 8, 8))
    s, boxes = M.box_scores(z, gt)
    assert (s["box_TP"], s["box_FP"], s["box_FN"]) == (0, 0, 1)
    assert math.isnan(s["box_P"]) and s["box_R"] == 0 and s["box_AP"] == 0
    s, boxes = M.box_scores(gt, z)
    assert s["box_FP"] == 1 and math.isnan(s["box_R"]) and math.isnan(s["box_AP"])
    s, boxes = M.box_scores(z, z)
    assert len(boxes) == 0 and math.isnan(s["box_F1"])


def test_aggregate_mean_ignores_nan_and_pooled_uses_counts():
    gt1 = _rect(10, 10, (0, 0, 4, 4))
    v1, b1 = M.score_view(gt1, gt1)  # perfect
    z = np.zeros((10, 10), bool)
    v2, b2 = M.score_view(_rect(10, 10, (6, 6, 8, 8)), z)  # false alarm, empty GT
    v3, b3 = M.score_view(z, z)  # nothing anywhere
    rows = []
    for name, v in (("a", v1), ("b", v2), ("c", v3)):
        rows.append({"scene": "s", "method": "m", "view": name, **v})
    df = pd.DataFrame(rows)
    boxes = pd.concat([b.assign(scene="s", method="m", view=n)
                       for n, b in (("a", b1), ("b", b2), ("c", b3))], ignore_index=True)
    agg = M.aggregate(df, boxes).iloc[0]
    assert agg["n_views"] == 3
    # recall: view a = 1, view b undefined, view c undefined -> mean 1 over 1 view
    assert agg["R_mean"] == 1.0 and agg["n_R"] == 1
    # precision: a = 1, b = 0 -> 0.5
    assert agg["P_mean"] == 0.5 and agg["n_P"] == 2
    # pooled: TP 16, FP 4, FN 0
    assert (agg["TP"], agg["FP"], agg["FN"]) == (16, 4, 0)
    assert agg["P_pooled"] == pytest.approx(16 / 20)
    assert agg["IoU_pooled"] == pytest.approx(16 / 20)
    assert agg["F1_pooled"] == pytest.approx(32 / 36)
    # boxes pooled: the true box (area 16) outranks the false one (area 4) -> AP 1
    assert agg["box_AP_pooled"] == pytest.approx(1.0)
    assert agg["box_P_pooled"] == 0.5
    # the same after a CSV round trip (matched read back as text/bool)
    agg2 = M.aggregate(df, boxes.astype({"matched": str})).iloc[0]
    assert agg2["box_AP_pooled"] == pytest.approx(1.0)


def test_object_recall_half_of_each_object():
    h, w = 20, 30
    before = _rect(h, w, (0, 0, 4, 4))  # object A (16 px), seen before only
    after = _rect(h, w, (10, 10, 20, 14), (24, 0, 28, 2))  # B (40 px) and C (8 px) after
    objects = M.object_regions([before, after])
    assert sorted(int(o.sum()) for o in objects) == [8, 16, 40]
    pred = np.zeros((h, w), bool)
    pred[0:2, 0:4] = True  # exactly half of A: found
    pred[10:14, 10:14] = True  # 16 of 40 px of B: missed
    s = M.object_scores(pred, objects)
    assert (s["obj_N"], s["obj_found"]) == (3, 1) and s["obj_R"] == pytest.approx(1 / 3)
    pred[0:2, 24:28] = True  # all of C
    assert M.object_scores(pred, objects)["obj_found"] == 2
    # the fraction is an option; small regions are dropped like boxes
    assert M.object_scores(pred, objects, found_fraction=0.6)["obj_found"] == 1
    assert len(M.object_regions([before, after], min_area=10)) == 2
    s = M.object_scores(pred, [])
    assert s["obj_N"] == 0 and math.isnan(s["obj_R"])
    # pooled over views: found / objects
    df = pd.DataFrame([{"scene": "s", "method": "m", "view": "a", "TP": 1, "FP": 0, "FN": 0,
                        "obj_N": 3, "obj_found": 1, "obj_R": 1 / 3},
                       {"scene": "s", "method": "m", "view": "b", "TP": 1, "FP": 0, "FN": 0,
                        "obj_N": 1, "obj_found": 1, "obj_R": 1.0}])
    agg = M.aggregate(df).iloc[0]
    assert agg["obj_R_pooled"] == pytest.approx(2 / 4)
    assert agg["obj_R_mean"] == pytest.approx((1 / 3 + 1) / 2)


def test_gt_box_scores_core_and_far_fraction():
    h, w = 100, 100
    boxes = [[10, 10, 30, 50]]  # core: x 15..25, y 20..40 (200 px)
    pred = np.zeros((h, w), bool)
    pred[20:40, 15:20] = True  # half the core
    s = M.gt_box_scores(pred, boxes, margin=5)
    assert (s["gtbox_N"], s["gtbox_found"], s["far_FP"]) == (1, 1, 0)
    pred[:] = False
    pred[0:10, 0:10] = True  # a ring around the box but not its core: missed, near
    pred[90:100, 90:100] = True  # far away: 100 px
    s = M.gt_box_scores(pred, boxes, margin=10)
    assert s["gtbox_found"] == 0 and s["gtbox_R"] == 0.0
    assert s["far_FP"] == 100 and s["far_frac"] == pytest.approx(100 / (h * w))
    # with a small margin the top-left block is far, too (pixels 0..4 are > 5 px off the box)
    assert M.gt_box_scores(pred, boxes, margin=5)["far_FP"] == 100 + 100 - 25
    # fractional boxes, a box reaching over the border, no boxes
    s = M.gt_box_scores(np.ones((h, w), bool), [[80.4, -5, 110, 20.6]], margin=0)
    assert s["gtbox_found"] == 1
    s = M.gt_box_scores(pred, np.zeros((0, 4)))
    assert s["gtbox_N"] == 0 and math.isnan(s["gtbox_R"]) and s["far_FP"] == 200


def test_gt_box_cores_per_box():
    boxes = [[10, 10, 30, 50], [60, 60, 80, 80], [200, 200, 220, 220]]  # the last off the map
    pred = np.zeros((100, 100), bool)
    pred[20:30, 15:25] = True  # half of box 1's core (x 15..25, y 20..40)
    pred[65:75, 65:69] = True  # 4 of box 2's 10 core columns (x 65..75, y 65..75)
    frac, found = M.gt_box_cores(pred, boxes)
    assert frac[:2] == pytest.approx([0.5, 0.4]) and math.isnan(frac[2])
    assert list(found) == [True, False, False]
    # the found flags are those gt_box_scores counts, also at another core and fraction
    for core, ff in ((0.5, 0.5), (0.8, 0.3), (1.0, 0.1)):
        frac, found = M.gt_box_cores(pred, boxes, core, ff)
        assert M.gt_box_scores(pred, boxes, core, ff)["gtbox_found"] == found.sum()
    assert M.gt_box_cores(pred, np.zeros((0, 4)))[0].shape == (0,)
