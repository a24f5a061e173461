"""Tiny SAM-family ONNX models for the tests, built offline with ``onnx.helper``.

The models have the input/output names, dtypes and (symbolic where the real exports are) shapes
of the real exports, with tiny weights (a few KB):

* SAM / MobileSAM image encoder (samexporter): ``input_image`` [1, 3, 1024, 1024] normalised and
  padded (``layout="nchw"``), or [image_height, image_width, 3] 0-255 (``layout="hwc"``,
  samexporter ``--use-preprocess``) -> ``image_embeddings`` [1, C, 64, 64].
* SAM / MobileSAM decoder (segment-anything ``export_onnx_model.py`` / samexporter):
  ``image_embeddings``, ``point_coords`` [1 or batch, num_points, 2], ``point_labels``,
  ``mask_input`` [1, 1, 256, 256], ``has_mask_input`` [1], ``orig_im_size`` [2] ->
  ``masks`` [B, 4, H, W], ``iou_predictions`` [B, 4], ``low_res_masks`` [B, 4, 256, 256].
* EfficientSAM encoder ``batched_images`` [batch, 3, height, width] (0-1) and decoder
  (``batched_point_coords`` [1, Q, num_points, 2] in original pixels, ``batched_point_labels``,
  ``orig_im_size`` int64 -> ``output_masks`` [1, Q, 3, H, W], ``iou_predictions`` [1, Q, 3]).

What they compute: the encoder average-pools the normalised image over 16 x 16 blocks (``oracle``:
the 3 colour channels are the embedding; ``random``: a random 1x1 convolution to 8 channels and
tanh). The decoder samples the embedding at the first prompt point (bilinear) and gives, for each
mask token k, logits ``slope_k * (tau_k - d2)`` where d2 is the squared embedding distance of
every embedding cell to the prompt's embedding (upsampled from 64 x 64 to 256 x 256): a mask
of the region that looks like the prompt point. The ``oracle`` models have fixed tokens (see
``ORACLE_SAM_TOKENS``) so a test can predict which masks pass each filter and where segments
appear; the ``random`` models draw token parameters, channel weights and a sigmoid IoU head
from ``seed``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
S = 1024   # SAM frame size
E = 64     # embedding grid size
L = 256    # low-resolution mask size
MEAN = np.array([123.675, 116.28, 103.53], dtype=np.float32)
STD = np.array([58.395, 57.12, 57.375], dtype=np.float32)

#: Oracle SAM decoder tokens (tau, slope, predicted IoU). Token 0 is SAM's single-mask output
#: (dropped by "segment everything"); 1 is a tight, stable, confident mask; 2 is confident but
#: unstable (its logits never exceed the stability offset); 3 is a loose mask with low IoU.
ORACLE_SAM_TOKENS = [(2.0, 40.0, 0.50), (2.0, 40.0, 0.97), (2.0, 0.4, 0.95), (6.0, 40.0, 0.70)]
#: Oracle EfficientSAM tokens (its decoder has no single-mask token).
ORACLE_ESAM_TOKENS = ORACLE_SAM_TOKENS[1:]


class _Graph:
    """Accumulates nodes and constants; ``op`` returns the (unique) output name."""

    def __init__(self):
        self.nodes, self.inits, self._n = [], [], 0

    def const(self, value, dtype=np.float32) -> str:
        self._n += 1
        name = f"c{self._n}"
        self.inits.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def op(self, op_type: str, *inputs: str, out: str | None = None, **attrs) -> str:
        self._n += 1
        name = out or f"t{self._n}"
        self.nodes.append(helper.make_node(op_type, list(inputs), [name], **attrs))
        return name

    def save(self, path, inputs, outputs, name: str) -> Path:
        graph = helper.make_graph(self.nodes, name, inputs, outputs, self.inits)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                                  producer_name="gdiff-tests")
        model.ir_version = 8
        onnx.checker.check_model(model)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        onnx.save(model, str(path))
        return path


def _embed_head(g: _Graph, pooled: str, kind: str, rng) -> tuple[str, int]:
    """Oracle: the pooled colours; random: 1x1 conv to 8 channels + tanh."""
    if kind == "oracle":
        return pooled, 3
    c = 8
    w = g.const(rng.normal(0, 0.7, (c, 3, 1, 1)))
    b = g.const(rng.normal(0, 0.1, (c,)))
    return g.op("Tanh", g.op("Conv", pooled, w, b)), c


def sam_encoder(path, layout: str = "nchw", kind: str = "oracle", seed: int = 0) -> Path:
    """A SAM/MobileSAM image encoder as samexporter writes it (see module docstring)."""
    rng = np.random.default_rng(seed)
    g = _Graph()
    if layout == "nchw":
        x = helper.make_tensor_value_info("input_image", TensorProto.FLOAT, [1, 3, S, S])
        img = "input_image"
    elif layout == "hwc":
        x = helper.make_tensor_value_info("input_image", TensorProto.FLOAT,
                                          ["image_height", "image_width", 3])
        norm = g.op("Div", g.op("Sub", "input_image", g.const(MEAN)), g.const(STD))
        chw = g.op("Unsqueeze", g.op("Transpose", norm, perm=[2, 0, 1]),
                   g.const([0], np.int64))
        hw = g.op("Slice", g.op("Shape", "input_image"), g.const([0], np.int64),
                  g.const([2], np.int64))
        pads = g.op("Concat", g.const([0, 0, 0, 0, 0, 0], np.int64),
                    g.op("Sub", g.const([S, S], np.int64), hw), axis=0)
        img = g.op("Pad", chw, pads, g.const(0.0))
    else:
        raise ValueError(layout)
    pooled = g.op("AveragePool", img, kernel_shape=[16, 16], strides=[16, 16])
    emb, c = _embed_head(g, pooled, kind, rng)
    g.op("Identity", emb, out="image_embeddings")
    y = helper.make_tensor_value_info("image_embeddings", TensorProto.FLOAT, [1, c, E, E])
    return g.save(path, [x], [y], "sam_encoder")


def efficientsam_encoder(path, kind: str = "oracle", seed: int = 0) -> Path:
    """An EfficientSAM image encoder (RGB in 0-1 at any size; resizes to 1024 inside)."""
    rng = np.random.default_rng(seed)
    g = _Graph()
    x = helper.make_tensor_value_info("batched_images", TensorProto.FLOAT,
                                      ["batch", 3, "height", "width"])
    bc = g.op("Slice", g.op("Shape", "batched_images"), g.const([0], np.int64),
              g.const([2], np.int64))
    sizes = g.op("Concat", bc, g.const([S, S], np.int64), axis=0)
    img = g.op("Resize", "batched_images", "", "", sizes, mode="linear")
    norm = g.op("Div", g.op("Sub", img, g.const((MEAN / 255).reshape(1, 3, 1, 1))),
                g.const((STD / 255).reshape(1, 3, 1, 1)))
    pooled = g.op("AveragePool", norm, kernel_shape=[16, 16], strides=[16, 16])
    emb, c = _embed_head(g, pooled, kind, rng)
    g.op("Identity", emb, out="image_embeddings")
    y = helper.make_tensor_value_info("image_embeddings", TensorProto.FLOAT, ["batch", c, E, E])
    return g.save(path, [x], [y], "efficientsam_encoder")


def _token_logits(g: _Graph, emb1: str, point_grid: str, n_prompts: str, tokens, kind: str,
                  channels: int, rng) -> tuple[str, str]:
    """Low-res logits [B, K, 256, 256] and IoU [B, K] for prompts at ``point_grid`` [B,1,1,2]."""
    k = len(tokens)
    shape_b111 = g.op("Concat", n_prompts, g.const([1, 1, 1], np.int64), axis=0)
    emb_b = g.op("Expand", emb1, shape_b111)
    at_point = g.op("GridSample", emb_b, point_grid, align_corners=0, mode="bilinear",
                    padding_mode="border")  # [B, C, 1, 1]
    diff = g.op("Sub", emb1, at_point)  # [B, C, 64, 64]
    sq = g.op("Mul", diff, diff)
    if kind == "random":
        sq = g.op("Mul", sq, g.const(rng.uniform(0.5, 1.5, (1, channels, 1, 1))))
    d2 = g.op("ReduceSum", sq, g.const([1], np.int64), keepdims=1)  # [B, 1, 64, 64]
    if kind == "oracle":
        tau = [t[0] for t in tokens]
        slope = [t[1] for t in tokens]
    else:
        tau = rng.uniform(0.1, 2.0, k)
        slope = rng.uniform(1.0, 40.0, k)
    logits = g.op("Mul", g.op("Sub", g.const(np.reshape(tau, (1, k, 1, 1))), d2),
                  g.const(np.reshape(slope, (1, k, 1, 1))))
    logits = g.op("Resize", logits, "", g.const([1, 1, L / E, L / E]), mode="linear")
    if kind == "oracle":
        shape_bk = g.op("Concat", n_prompts, g.const([k], np.int64), axis=0)
        iou = g.op("Expand", g.const(np.reshape([t[2] for t in tokens], (1, k))), shape_bk)
    else:
        feat = g.op("Reshape", at_point, g.const([-1, channels], np.int64))
        lin = g.op("Add", g.op("MatMul", feat, g.const(rng.normal(0, 2.0, (channels, k)))),
                   g.const(rng.normal(1.5, 1.0, (k,))))
        iou = g.op("Sigmoid", lin)
    return logits, iou


def sam_decoder(path, kind: str = "oracle", batched: bool = False, low_res: bool = True,
                single_mask: bool = False, channels: int | None = None, seed: int = 0) -> Path:
    """A SAM/MobileSAM prompt+mask decoder (segment-anything's ONNX signature).

    ``batched``: the point_coords batch dimension is symbolic (several prompts per call);
    otherwise it is 1 as in the official export. ``single_mask``: one mask per prompt (the
    export's ``--return-single-mask``; for a point + padding prompt SAM returns its best
    multimask output, here oracle token 1). ``low_res``: also output ``low_res_masks``
    (the official export does); ``masks`` is always output, at ``orig_im_size`` (the resized
    image's part of the low-resolution logits, resized).
    """
    rng = np.random.default_rng(seed + 1)
    c = channels or (3 if kind == "oracle" else 8)
    b = "batch" if batched else 1
    f = TensorProto.FLOAT
    inputs = [helper.make_tensor_value_info("image_embeddings", f, [1, c, E, E]),
              helper.make_tensor_value_info("point_coords", f, [b, "num_points", 2]),
              helper.make_tensor_value_info("point_labels", f, [b, "num_points"]),
              helper.make_tensor_value_info("mask_input", f, [1, 1, L, L]),
              helper.make_tensor_value_info("has_mask_input", f, [1]),
              helper.make_tensor_value_info("orig_im_size", f, [2])]
    g = _Graph()
    p0 = g.op("Gather", "point_coords", g.const(0, np.int64), axis=1)  # [B, 2]
    grid = g.op("Reshape", g.op("Sub", g.op("Mul", p0, g.const(2.0 / S)), g.const(1.0)),
                g.const([-1, 1, 1, 2], np.int64))
    n_prompts = g.op("Slice", g.op("Shape", "point_coords"), g.const([0], np.int64),
                     g.const([1], np.int64))
    tokens = ORACLE_SAM_TOKENS if kind == "oracle" else [None] * 4
    if single_mask:
        tokens = tokens[1:2]
    m = len(tokens)
    logits, iou = _token_logits(g, "image_embeddings", grid, n_prompts, tokens, kind, c, rng)
    # a prompt mask (has_mask_input = 1) shifts the logits, so the inputs are really used
    prior = g.op("Mul", "has_mask_input", g.op("ReduceMean", "mask_input", keepdims=0))
    low = g.op("Add", logits, prior, out="low_res_masks" if low_res else None)
    g.op("Identity", iou, out="iou_predictions")
    # SAM postprocessing (upsample to S x S, crop the resized image, resize to the original
    # size), with the crop taken on the low-resolution grid to keep the tiny model cheap
    bk = g.op("Slice", g.op("Shape", low), g.const([0], np.int64), g.const([2], np.int64))
    scale = g.op("Div", g.const(float(L)), g.op("ReduceMax", "orig_im_size", keepdims=0))
    low_hw = g.op("Cast", g.op("Ceil", g.op("Mul", "orig_im_size", scale)), to=TensorProto.INT64)
    crop = g.op("Slice", low, g.const([0, 0], np.int64), low_hw, g.const([2, 3], np.int64))
    orig_i = g.op("Cast", "orig_im_size", to=TensorProto.INT64)
    g.op("Resize", crop, "", "", g.op("Concat", bk, orig_i, axis=0), mode="linear", out="masks")
    outputs = [helper.make_tensor_value_info("masks", f, [b, m, "H", "W"]),
               helper.make_tensor_value_info("iou_predictions", f, [b, m])]
    if low_res:
        outputs.append(helper.make_tensor_value_info("low_res_masks", f, [b, m, L, L]))
    return g.save(path, inputs, outputs, "sam_decoder")


def efficientsam_decoder(path, kind: str = "oracle", batched: bool = False,
                         seed: int = 0) -> Path:
    """An EfficientSAM decoder (point prompts in original pixels, masks at the original size)."""
    rng = np.random.default_rng(seed + 1)
    c = 3 if kind == "oracle" else 8
    q = "num_queries" if batched else 1
    f = TensorProto.FLOAT
    inputs = [helper.make_tensor_value_info("image_embeddings", f, ["batch", c, E, E]),
              helper.make_tensor_value_info("batched_point_coords", f, [1, q, "num_points", 2]),
              helper.make_tensor_value_info("batched_point_labels", f, [1, q, "num_points"]),
              helper.make_tensor_value_info("orig_im_size", TensorProto.INT64, [2])]
    g = _Graph()
    wh = g.op("Gather", g.op("Cast", "orig_im_size", to=TensorProto.FLOAT),
              g.const([1, 0], np.int64), axis=0)
    first = g.op("Gather", g.op("Gather", "batched_point_coords", g.const(0, np.int64), axis=0),
                 g.const(0, np.int64), axis=1)  # [Q, 2]
    grid = g.op("Reshape", g.op("Sub", g.op("Mul", g.op("Div", first, wh), g.const(2.0)),
                                g.const(1.0)), g.const([-1, 1, 1, 2], np.int64))
    n_prompts = g.op("Slice", g.op("Shape", first), g.const([0], np.int64),
                     g.const([1], np.int64))
    emb1 = g.op("Slice", "image_embeddings", g.const([0], np.int64), g.const([1], np.int64))
    tokens = ORACLE_ESAM_TOKENS if kind == "oracle" else [None] * 3
    logits, iou = _token_logits(g, emb1, grid, n_prompts, tokens, kind, c, rng)
    # labels are used as SAM uses them: a -1 (padding) point would not count; here all are 1
    lab = g.op("ReduceMean", "batched_point_labels", keepdims=0)
    logits = g.op("Add", logits, g.op("Sub", lab, g.const(1.0)))
    qk = g.op("Slice", g.op("Shape", logits), g.const([0], np.int64), g.const([2], np.int64))
    full = g.op("Resize", logits, "", "", g.op("Concat", qk, "orig_im_size", axis=0),
                mode="linear")
    g.op("Unsqueeze", full, g.const([0], np.int64), out="output_masks")
    g.op("Unsqueeze", iou, g.const([0], np.int64), out="iou_predictions")
    outputs = [helper.make_tensor_value_info("output_masks", f, [1, q, 3, "H", "W"]),
               helper.make_tensor_value_info("iou_predictions", f, [1, q, 3])]
    return g.save(path, inputs, outputs, "efficientsam_decoder")


def unrelated_model(path, input_name: str = "x") -> Path:
    """A valid ONNX file that is not a SAM model (one Identity node)."""
    g = _Graph()
    g.op("Identity", input_name, out="y")
    return g.save(path, [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, [1, 4])],
                  [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4])], "unrelated")


def sam2_like_decoder(path) -> Path:
    """A decoder with SAM 2's input names (image_embed, high_res_feats_0/1, ...)."""
    f = TensorProto.FLOAT
    g = _Graph()
    g.op("Identity", "image_embed", out="masks")
    ins = [helper.make_tensor_value_info("image_embed", f, [1, 256, 64, 64]),
           helper.make_tensor_value_info("high_res_feats_0", f, [1, 32, 256, 256]),
           helper.make_tensor_value_info("high_res_feats_1", f, [1, 64, 128, 128]),
           helper.make_tensor_value_info("point_coords", f, [1, "n", 2])]
    return g.save(path, ins, [helper.make_tensor_value_info("masks", f, [1, 256, 64, 64])],
                  "sam2_decoder")


def model_pair(folder, variant: str = "sam", kind: str = "oracle",
               **decoder_kw) -> tuple[Path, Path]:
    """Write an (encoder, decoder) pair into ``folder``.

    ``variant``: ``sam`` (nchw encoder), ``sam_hwc`` (samexporter --use-preprocess encoder) or
    ``efficientsam``; ``decoder_kw`` go to the decoder builder (``batched``, ``low_res``, ...).
    """
    folder = Path(folder)
    seed = decoder_kw.pop("seed", 0)
    if variant == "efficientsam":
        enc = efficientsam_encoder(folder / "esam_encoder.onnx", kind, seed)
        dec = efficientsam_decoder(folder / "esam_decoder.onnx", kind, seed=seed, **decoder_kw)
        return enc, dec
    layout = "hwc" if variant == "sam_hwc" else "nchw"
    enc = sam_encoder(folder / f"{variant}_encoder.onnx", layout, kind, seed)
    dec = sam_decoder(folder / f"{variant}_decoder.onnx", kind, seed=seed, **decoder_kw)
    return enc, dec
