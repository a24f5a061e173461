"""SAM ONNX backend: tiny exported models end to end, mask-generator semantics, file errors."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("onnx")

import tiny_sam  # noqa: E402
from gdiff.errors import ConfigError, ModelFileError  # noqa: E402
from gdiff.segment import SegmentOptions, make_segmenter  # noqa: E402
from gdiff.segment.sam_masks import (box_nms, crop_boxes, mask_boxes, near_crop_edge,  # noqa: E402
                                     point_grid, remove_small_regions, stability_score)
from gdiff.segment.sam_onnx import SamOnnxSegmenter, SamOptions, lowres_to_image  # noqa: E402

BG = (0.2, 0.3, 0.5)
N_SIDE = 8  # 8 x 8 prompts; on 160 x 120 they sit at x = 10, 30, ..., y = 7.5, 22.5, ...


def scene(islands: bool = False):
    """160 x 120 test image: two rectangles and a disc on a flat background, + GT masks.

    Object edges lie at least 4 px from every prompt of the 8 x 8 grid, so each prompt falls
    clearly inside one segment. ``islands`` adds a 10 x 10 red island away from the red box and
    a 10 x 10 background-coloured hole in the green box.
    """
    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    gt = {"red": (xx >= 20) & (xx < 60) & (yy >= 15) & (yy < 60),
          "green": (xx >= 80) & (xx < 140) & (yy >= 15) & (yy < 45),
          "yellow": (xx - 100) ** 2 + (yy - 90) ** 2 < 17 ** 2}
    img = np.empty((h, w, 3), np.float32)
    img[:] = BG
    colours = {"red": (0.9, 0.1, 0.1), "green": (0.1, 0.8, 0.2), "yellow": (0.9, 0.9, 0.1)}
    for name, m in gt.items():
        img[m] = colours[name]
    if islands:
        island = (xx >= 50) & (xx < 60) & (yy >= 100) & (yy < 110)
        hole = (xx >= 102) & (xx < 112) & (yy >= 25) & (yy < 35)
        img[island] = colours["red"]
        img[hole] = BG
        gt["island"], gt["hole"] = island, hole
    gt["background"] = ~(gt["red"] | gt["green"] | gt["yellow"])
    return img, gt


def iou(a, b):
    return np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1)


def centroid(m):
    ys, xs = np.nonzero(m)
    return np.array([xs.mean(), ys.mean()])


def assert_found(masks, gt_mask, what="", centre=True):
    """Some mask covers the object: IoU > 0.8 (the oracle's 16-px embedding cells blur edges by
    about half a cell, ~1 px here) and the same centroid within 0.25 px (the blur is symmetric,
    so any error in undoing the resize/padding would show as a shift)."""
    best = max(masks, key=lambda m: iou(m, gt_mask))
    assert iou(best, gt_mask) > 0.8, (what, iou(best, gt_mask))
    shift = np.abs(centroid(best) - centroid(gt_mask)).max()
    assert not centre or shift < 0.25, (what, shift)


class CallCounter:
    """Wraps an onnxruntime session and counts run() calls and prompts fed."""

    def __init__(self, session):
        self.session, self.calls, self.shapes = session, 0, []

    def run(self, names, feeds):
        self.calls += 1
        self.shapes.append({k: v.shape for k, v in feeds.items()})
        return self.session.run(names, feeds)

    def __getattr__(self, name):
        return getattr(self.session, name)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("sam_models")
    pairs = {
        "sam": tiny_sam.model_pair(root / "a", "sam"),
        "sam_hwc": tiny_sam.model_pair(root / "b", "sam_hwc"),
        "efficientsam": tiny_sam.model_pair(root / "c", "efficientsam"),
        "sam_batched": tiny_sam.model_pair(root / "d", "sam", batched=True),
        "sam_masks_only": tiny_sam.model_pair(root / "e", "sam", low_res=False),
        "sam_single": tiny_sam.model_pair(root / "h", "sam_hwc", single_mask=True),
        "random": tiny_sam.model_pair(root / "f", "sam", kind="random", batched=True, seed=3),
        "random_esam": tiny_sam.model_pair(root / "g", "efficientsam", kind="random",
                                           batched=True, seed=4),
    }
    pairs["root"] = root
    return pairs


def test_tiny_models_are_tiny_and_shaped_like_the_exports(models):
    import onnxruntime as ort

    enc, dec = models["sam"]
    assert enc.stat().st_size < 20_000 and dec.stat().st_size < 20_000
    d = ort.InferenceSession(str(dec), providers=["CPUExecutionProvider"])
    assert [i.name for i in d.get_inputs()] == ["image_embeddings", "point_coords",
                                                "point_labels", "mask_input",
                                                "has_mask_input", "orig_im_size"]
    assert [o.name for o in d.get_outputs()] == ["masks", "iou_predictions", "low_res_masks"]
    assert d.get_inputs()[1].shape == [1, "num_points", 2]


# ---- end to end with the oracle models ------------------------------------------------------

@pytest.mark.parametrize("variant", ["sam", "sam_hwc", "efficientsam", "sam_batched",
                                     "sam_masks_only", "sam_single"])
def test_oracle_segments_come_out_where_the_objects_are(models, variant):
    img, gt = scene()
    seg = SamOnnxSegmenter(*models[variant], points_per_side=N_SIDE)
    inst = seg.segment(img)
    assert len(inst) == 4, [i.area for i in inst]
    for name in ("red", "green", "yellow", "background"):
        assert_found([i.mask for i in inst], gt[name], (variant, name), name != "background")
    for i in inst:
        assert i.mask.shape == img.shape[:2] and i.mask.dtype == bool
    scores = [i.score for i in inst]
    assert scores == sorted(scores, reverse=True)
    # instances never overlap
    assert np.max(np.sum([i.mask for i in inst], axis=0)) == 1


def test_portrait_image_maps_masks_back_through_resize_and_padding(models):
    img, gt = scene()
    img = np.ascontiguousarray(img.transpose(1, 0, 2))  # 120 wide, 160 high
    seg = SamOnnxSegmenter(*models["sam"], points_per_side=N_SIDE)
    inst = seg.segment(img)
    assert len(inst) == 4
    for name in ("red", "green", "yellow"):
        assert_found([i.mask for i in inst], gt[name].T, name)


@pytest.mark.parametrize("h, w", [(90, 200), (1100, 1500), (160, 120)])
def test_lowres_to_image_undoes_padding_and_resize_exactly(h, w):
    # low-res logits equal to a linear function of the S-frame position: bilinear resampling
    # must give that function's value at each original pixel centre (up- and downscaling,
    # landscape and portrait)
    s, lres = 1024, 256
    scale = s / max(h, w)
    rh, rw = int(h * scale + 0.5), int(w * scale + 0.5)
    c = (np.arange(lres) + 0.5) * (s / lres)  # low-res pixel centres in S-frame units
    low = (0.3 * c[None, :] - 0.7 * c[:, None])[None].astype(np.float32)
    out = lowres_to_image(low, (rh, rw), s, (h, w))[0]
    xs = (np.arange(w) + 0.5) * rw / w
    ys = (np.arange(h) + 0.5) * rh / h
    expect = 0.3 * xs[None, :] - 0.7 * ys[:, None]
    assert out.shape == (h, w)
    inside = ((ys >= c[0]) & (ys <= c[-1]))[:, None] & ((xs >= c[0]) & (xs <= c[-1]))[None, :]
    assert inside.mean() > 0.98
    np.testing.assert_allclose(out[inside], expect[inside], atol=1e-2)


# ---- mechanics: prompts, filters, NMS, batching, crops ------------------------------------

def test_grid_prompts_and_filters_count_as_expected(models):
    img, _ = scene()
    seg = SamOnnxSegmenter(*models["sam"], points_per_side=N_SIDE)
    seg.model.decoder = CallCounter(seg.model.decoder)
    seg.model.encoder = CallCounter(seg.model.encoder)
    props = seg.generate(img)
    n = N_SIDE ** 2
    assert seg.model.encoder.calls == 1  # the embedding is computed once per image
    assert seg.model.decoder.calls == n  # static batch dimension: one prompt per call
    # each call: the prompt and SAM's padding point
    assert all(sh["point_coords"] == (1, 2, 2) for sh in seg.model.decoder.shapes)
    st = seg.last_stats
    assert st["prompts"] == n
    assert st["candidates"] == 3 * n  # SAM's 3 multimask outputs (token 0 dropped)
    assert st["after_iou"] == 2 * n  # token 3 (IoU 0.70) is below 0.88
    assert 0 < st["after_stability"] <= n  # token 2 is never stable
    assert all(p.predicted_iou == pytest.approx(0.97) for p in props)
    assert all(p.stability_score >= 0.95 for p in props)

    # nothing passes: no proposals, no instances
    none = SamOnnxSegmenter(*models["sam"], points_per_side=4, pred_iou_thresh=0.99)
    assert none.segment(img) == [] and none.last_stats["after_iou"] == 0
    # an offset beyond every logit: no mask is stable
    unstable = SamOnnxSegmenter(*models["sam"], points_per_side=4,
                                stability_score_offset=100.0, stability_score_thresh=0.5)
    assert unstable.generate(img) == [] and unstable.last_stats["after_stability"] == 0

    # a --return-single-mask export gives one mask per prompt
    single = SamOnnxSegmenter(*models["sam_single"], points_per_side=N_SIDE)
    single.generate(img)
    assert single.last_stats["candidates"] == n

    # lower thresholds let more through
    loose = SamOnnxSegmenter(*models["sam"], points_per_side=N_SIDE, pred_iou_thresh=0.6,
                             stability_score_thresh=0.0)
    loose.generate(img)
    assert loose.last_stats["after_iou"] == 3 * n
    assert loose.last_stats["after_stability"] == 3 * n


def test_nms_removes_duplicate_masks(models):
    img, gt = scene()
    seg = SamOnnxSegmenter(*models["sam"], points_per_side=N_SIDE)
    props = seg.generate(img)
    assert len(props) == 4
    # without NMS every prompt inside an object gives its own copy of the object's mask
    off = SamOnnxSegmenter(*models["sam"], points_per_side=N_SIDE, box_nms_thresh=1.0)
    dup = off.generate(img)
    assert len(dup) == off.last_stats["after_stability"] > 3 * len(props)
    inside_red = sum(gt["red"][int(p.point[1]), int(p.point[0])] for p in dup)
    copies_of_red = sum(iou(p.mask, gt["red"]) > 0.8 for p in dup)
    assert copies_of_red == inside_red > 1


def test_batched_decoder_takes_points_per_batch_prompts_per_call(models):
    img, _ = scene()
    seg = SamOnnxSegmenter(*models["sam_batched"], points_per_side=N_SIDE, points_per_batch=16)
    seg.model.decoder = CallCounter(seg.model.decoder)
    batched = seg.generate(img)
    assert seg.model.decoder.calls == N_SIDE ** 2 // 16
    assert seg.model.decoder.shapes[0]["point_coords"] == (16, 2, 2)
    single = SamOnnxSegmenter(*models["sam"], points_per_side=N_SIDE).generate(img)
    assert len(batched) == len(single)
    for a, b in zip(batched, single):
        assert np.array_equal(a.mask, b.mask)


def test_crop_layers_encode_each_crop_once_and_keep_one_mask_per_object(models):
    img, gt = scene()
    seg = SamOnnxSegmenter(*models["sam_batched"], points_per_side=N_SIDE, crop_n_layers=1,
                           crop_n_points_downscale_factor=2)
    seg.model.encoder = CallCounter(seg.model.encoder)
    inst = seg.segment(img)
    assert seg.model.encoder.calls == 5  # the image + 2 x 2 crops
    assert seg.last_stats["prompts"] == N_SIDE ** 2 + 4 * (N_SIDE // 2) ** 2
    assert len(inst) == 4
    for name in ("red", "green", "yellow", "background"):
        assert_found([i.mask for i in inst], gt[name], name, name != "background")


def test_small_islands_and_holes_are_removed(models):
    img, gt = scene(islands=True)

    def proposal_at(props, x, y):
        return next(p for p in props if p.mask[y, x] and p.point is not None and
                    p.mask[int(p.point[1]), int(p.point[0])])

    raw = SamOnnxSegmenter(*models["sam"], points_per_side=N_SIDE).generate(img)
    red, green = proposal_at(raw, 40, 30), proposal_at(raw, 85, 20)
    assert red.mask[gt["island"]].mean() > 0.5  # same colour: the raw mask has the island
    assert green.mask[gt["hole"]].mean() < 0.5  # and the green mask has a hole

    clean = SamOnnxSegmenter(*models["sam"], points_per_side=N_SIDE,
                             min_mask_region_area=150).generate(img)
    red, green = proposal_at(clean, 40, 30), proposal_at(clean, 85, 20)
    assert not red.mask[gt["island"]].any()
    assert green.mask[gt["hole"]].all()
    assert iou(red.mask, gt["red"]) > 0.8


def test_alpha_and_min_region_area(models):
    img, gt = scene()
    alpha = np.ones(img.shape[:2], np.float32)
    alpha[:, :70] = 0.1  # left part: nothing rendered
    seg = SamOnnxSegmenter(*models["sam"], points_per_side=N_SIDE, min_region_area=500)
    inst = seg.segment(img, depth=np.ones(img.shape[:2], np.float32), alpha=alpha)
    covered = np.any([i.mask for i in inst], axis=0)
    assert not covered[:, :70].any()
    assert all(i.area >= 500 for i in inst)
    # the red box lies in the cut-away part; the others survive
    assert not any(iou(i.mask, gt["red"]) > 0.5 for i in inst)
    assert_found([i.mask for i in inst], gt["green"])


# ---- random-weight models ------------------------------------------------------------------

@pytest.mark.parametrize("variant", ["random", "random_esam"])
def test_random_models_end_to_end(models, variant):
    img, _ = scene()
    n_side, thr_iou, thr_stab = 16, 0.88, 0.95
    # no filters, no NMS: every non-empty candidate comes out with its IoU and stability
    raw = SamOnnxSegmenter(*models[variant], points_per_side=n_side, points_per_batch=128,
                           pred_iou_thresh=0.0, stability_score_thresh=0.0, box_nms_thresh=1.0)
    raw.model.decoder = CallCounter(raw.model.decoder)
    everything = raw.generate(img)
    assert raw.last_stats["prompts"] == n_side ** 2
    assert raw.model.decoder.calls == n_side ** 2 // 128
    assert raw.last_stats["candidates"] == 3 * n_side ** 2
    assert len(everything) == raw.last_stats["after_edge"]
    passing = [p for p in everything
               if p.predicted_iou > thr_iou and p.stability_score >= thr_stab]
    assert 0 < len(passing) < len(everything)  # the random heads give a spread of values

    seg = SamOnnxSegmenter(*models[variant], points_per_side=n_side, points_per_batch=128,
                           pred_iou_thresh=thr_iou, stability_score_thresh=thr_stab,
                           min_region_area=1)
    inst = seg.segment(img)
    st = seg.last_stats
    assert st["after_iou"] == sum(p.predicted_iou > thr_iou for p in everything)
    assert st["after_stability"] == len(passing)
    assert 0 < st["after_nms"] < len(passing)
    assert 0 < len(inst) <= st["proposals"]
    assert all(i.mask.shape == img.shape[:2] for i in inst)
    assert np.max(np.sum([i.mask for i in inst], axis=0)) == 1
    scores = [i.score for i in inst]
    assert scores == sorted(scores, reverse=True)


# ---- configuration and model-file errors ---------------------------------------------------

def test_factory_builds_the_backend_from_the_segment_section(models):
    enc, dec = models["sam"]
    opts = SegmentOptions(backend="sam", sam_encoder=str(enc), sam_decoder=str(dec),
                          points_per_side=N_SIDE, min_region_area=10)
    seg = make_segmenter(opts)
    assert isinstance(seg, SamOnnxSegmenter)
    assert seg.options.points_per_side == N_SIDE and seg.options.min_region_area == 10
    assert seg.options.pred_iou_thresh == opts.pred_iou_thresh
    img, gt = scene()
    assert_found([i.mask for i in seg.segment(img)], gt["yellow"])


def test_bad_option_values_are_config_errors(models):
    with pytest.raises(ConfigError, match="segment.pred_iou_thresh"):
        SamOptions(pred_iou_thresh=1.5)
    with pytest.raises(ConfigError, match="points_per_side"):
        SamOnnxSegmenter(*models["sam"], points_per_side=0)
    with pytest.raises(ConfigError, match="unexpected keyword"):
        SamOnnxSegmenter(*models["sam"], points_per_sid=8)


def test_missing_file_is_a_model_file_error(models, tmp_path):
    enc, dec = models["sam"]
    with pytest.raises(ModelFileError, match=r"nope\.onnx.*not found.*segment\.sam_encoder"):
        SamOnnxSegmenter(tmp_path / "nope.onnx", dec)
    with pytest.raises(ModelFileError, match=r"segment\.sam_decoder' is not set"):
        SamOnnxSegmenter(enc, None)


def test_non_onnx_file_is_a_model_file_error(models, tmp_path):
    enc, _ = models["sam"]
    junk = tmp_path / "decoder.onnx"
    junk.write_text("this is not a protobuf")
    with pytest.raises(ModelFileError, match=r"decoder\.onnx: not a loadable ONNX model"):
        SamOnnxSegmenter(enc, junk)


def test_wrong_signatures_are_model_file_errors(models, tmp_path):
    enc, dec = models["sam"]
    other = tiny_sam.unrelated_model(tmp_path / "other.onnx")
    with pytest.raises(ModelFileError) as e:
        SamOnnxSegmenter(enc, other)
    msg = str(e.value)
    assert "other.onnx" in msg and "point_coords" in msg and "batched_point_coords" in msg
    with pytest.raises(ModelFileError, match="swap"):
        SamOnnxSegmenter(dec, enc)
    combined = tiny_sam.unrelated_model(tmp_path / "esam_combined.onnx", "batched_images")
    with pytest.raises(ModelFileError, match="combined model"):
        SamOnnxSegmenter(enc, combined)
    with pytest.raises(ModelFileError, match="SAM 2"):
        SamOnnxSegmenter(enc, tiny_sam.sam2_like_decoder(tmp_path / "sam2.onnx"))
    with pytest.raises(ModelFileError, match=r"other\.onnx: a SAM image encoder has one input|"
                                             r"other\.onnx: image-encoder input"):
        SamOnnxSegmenter(other, dec)
    # encoder and decoder from different models: 3-channel embedding, 8-channel decoder
    rand_dec = models["random"][1]
    with pytest.raises(ModelFileError, match="same model"):
        SamOnnxSegmenter(enc, rand_dec)
    # an EfficientSAM encoder cannot feed a SAM decoder (and the reverse)
    esam_enc, esam_dec = models["efficientsam"]
    with pytest.raises(ModelFileError, match="does not fit"):
        SamOnnxSegmenter(tiny_sam.sam_encoder(tmp_path / "hwc.onnx", "hwc"), esam_dec)
    with pytest.raises(ModelFileError, match="EfficientSAM encoder"):
        SamOnnxSegmenter(esam_enc, dec)


# ---- mask-generator helpers ----------------------------------------------------------------

def test_point_grid_and_crop_boxes():
    g = point_grid(4)
    assert g.shape == (16, 2)
    np.testing.assert_allclose(np.unique(g[:, 0]), [0.125, 0.375, 0.625, 0.875])
    assert tuple(g[1]) == (0.375, 0.125)  # x varies fastest
    boxes, layers = crop_boxes(120, 160, 1, 512 / 1500)
    assert boxes[0] == (0, 0, 160, 120) and layers == [0, 1, 1, 1, 1]
    for x0, y0, x1, y1 in boxes[1:]:
        assert 0 <= x0 < x1 <= 160 and 0 <= y0 < y1 <= 120
        assert x1 - x0 > 80 and y1 - y0 > 60  # tiles overlap
    assert max(b[2] for b in boxes[1:]) == 160 and max(b[3] for b in boxes[1:]) == 120


def test_stability_boxes_nms_and_edges():
    lg = np.full((2, 10, 10), -5.0, np.float32)
    lg[0, 2:6, 2:6] = 5.0  # sharp: stable
    lg[1, 2:6, 2:6] = 5.0
    lg[1, 6:8, 2:6] = 0.5  # a soft rim: between the -1 and +1 thresholds
    s = stability_score(lg, 0.0, 1.0)
    assert s[0] == 1.0 and s[1] == pytest.approx(16 / 24)
    b = mask_boxes(lg > 0)
    assert b.tolist() == [[2, 2, 6, 6], [2, 2, 6, 8]]
    assert mask_boxes(np.zeros((1, 4, 4), bool)).tolist() == [[0, 0, 0, 0]]
    assert stability_score(np.zeros((0, 4, 4)), 0.0, 1.0).shape == (0,)
    boxes = np.array([[0, 0, 10, 10], [1, 0, 10, 10], [20, 20, 30, 30], [0, 0, 10, 9]])
    keep = box_nms(boxes, np.array([0.5, 0.9, 0.1, 0.0]), 0.7)
    assert keep.tolist() == [1, 2]
    assert box_nms(boxes, np.array([0.5, 0.9, 0.1, 0.0]), 1.0).tolist() == [1, 0, 2, 3]
    near = near_crop_edge(np.array([[50, 10, 79, 40], [0, 0, 30, 30]]), (0, 0, 80, 60),
                          (0, 0, 160, 120))
    assert near.tolist() == [True, False]


def test_remove_small_regions():
    m = np.zeros((30, 30), bool)
    m[2:20, 2:20] = True
    m[8:10, 8:10] = False  # 4-pixel hole
    m[25:27, 25:27] = True  # 4-pixel island
    filled, changed = remove_small_regions(m, 10, "holes")
    assert changed and filled[8:10, 8:10].all() and filled[25, 25]
    cleaned, changed = remove_small_regions(m, 10, "islands")
    assert changed and not cleaned[25:27, 25:27].any() and cleaned[2, 2]
    same, changed = remove_small_regions(m, 3, "islands")
    assert not changed and np.array_equal(same, m)
    tiny = np.zeros((10, 10), bool)
    tiny[1, 1] = tiny[5:7, 5:7] = True  # every island small: keep the largest
    kept, _ = remove_small_regions(tiny, 100, "islands")
    assert kept.sum() == 4 and kept[5, 5]
