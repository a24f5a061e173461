"""Segment Anything through onnxruntime: "segment everything" with user-supplied ONNX files.

The user exports two ONNX files from a SAM-family checkpoint (see ``docs/sam.md``): an image
encoder (image -> image embedding, run once per image) and a prompt/mask decoder (embedding +
point prompts -> mask logits + predicted IoU). Supported layouts, detected from the files' input
names and shapes:

* ``sam`` -- segment-anything / MobileSAM decoders as written by segment-anything's
  ``scripts/export_onnx_model.py`` and samexporter (inputs ``image_embeddings``,
  ``point_coords`` [B, N, 2], ``point_labels`` [B, N], ``mask_input`` [1, 1, 4e, 4e],
  ``has_mask_input`` [1], ``orig_im_size`` [2]; outputs ``masks``, ``iou_predictions``,
  ``low_res_masks``), with either encoder form of samexporter:

  - ``nchw``: input [1, 3, S, S] (S = 1024): RGB in 0-255 resized so the longest side is S,
    normalised with the ImageNet mean/std (in 0-255 units) and zero-padded to S x S
    (bottom/right);
  - ``hwc`` (``--use-preprocess``): input [h, w, 3], the resized 0-255 RGB image; the model
    normalises and pads itself.

  Point coordinates are given in the resized (S-frame) pixel units, followed by a padding point
  (0, 0) with label -1, as SAM's predictor does for point-only prompts (the same values
  SamAutomaticMaskGenerator feeds; the model's prompt encoder adds its own half-pixel shift).
* ``efficientsam`` -- EfficientSAM's split export (encoder input ``batched_images``
  [B, 3, H, W], RGB in 0-1 at the original size; decoder inputs ``image_embeddings``,
  ``batched_point_coords`` [1, Q, N, 2] in original pixels, ``batched_point_labels``
  [1, Q, N], ``orig_im_size`` int64 [2]; outputs ``output_masks`` [1, Q, 3, H, W] logits and
  ``iou_predictions`` [1, Q, 3]).

SAM 2 exports (decoder inputs ``image_embed``, ``high_res_feats_*``) are not supported and are
reported as such. A file that is missing, not loadable ONNX, or of another signature raises
:class:`gdiff.errors.ModelFileError` naming the file, the config key and what was expected.

Automatic mask generation follows segment-anything's ``SamAutomaticMaskGenerator``: a regular
grid of single foreground points (optionally repeated on overlapping crops), decoder masks
thresholded at logit 0, filtering by predicted IoU and by stability score, box NMS, optional
removal of small islands and holes, and masks returned at the original image resolution. The
image embedding is computed once per image (once per crop).

Coordinates: pixel (x, y) has its centre at (x + 0.5, y + 0.5); point prompts are continuous
pixel positions (x right, y down) in the image given to :meth:`SamOnnxSegmenter.segment`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from ..errors import ConfigError, ModelFileError
from .base import ALPHA_MIN, Instance, mask_bbox
from .sam_masks import (box_nms, crop_boxes, mask_boxes, near_crop_edge, point_grid,
                        remove_small_regions, stability_score)

log = logging.getLogger("gdiff.segment.sam_onnx")

#: ImageNet mean / std in 0-255 units (SAM's pixel_mean / pixel_std).
PIXEL_MEAN = np.array([123.675, 116.28, 103.53], dtype=np.float32)
PIXEL_STD = np.array([58.395, 57.12, 57.375], dtype=np.float32)

SAM_DECODER_INPUTS = ("image_embeddings", "point_coords", "point_labels", "mask_input",
                      "has_mask_input", "orig_im_size")
EFFICIENTSAM_DECODER_INPUTS = ("image_embeddings", "batched_point_coords",
                               "batched_point_labels", "orig_im_size")
_DOCS = "see docs/sam.md for exporting SAM / MobileSAM / EfficientSAM to ONNX"


@dataclass
class SamOptions:
    """Options of the SAM backend (``segment`` config section; defaults as segment-anything).

    sam_encoder, sam_decoder: paths of the image-encoder and mask-decoder ONNX files.
    points_per_side: the prompt grid has points_per_side^2 points over the image (per crop).
    points_per_batch: prompts decoded per step (one decoder call when the decoder's batch
        dimension is dynamic, else one call per prompt); bounds memory, not results.
    pred_iou_thresh: keep masks whose predicted IoU is above this (0 disables).
    stability_score_thresh: keep masks whose stability score is at least this (0 disables).
    stability_score_offset: logit offset of the stability score (masks at +-offset compared).
    box_nms_thresh: box IoU above which the lower-scoring of two masks is dropped.
    crop_n_layers: extra layers of overlapping crops (layer i has 2^i x 2^i crops); 0 = none.
    crop_nms_thresh: box IoU for removing duplicates between crops (smaller crops win).
    crop_overlap_ratio: crop overlap as a fraction of the short image side (at layer 1).
    crop_n_points_downscale_factor: layer i uses points_per_side / factor^i points per side.
    min_mask_region_area: fill holes and drop islands smaller than this many pixels in every
        proposal (0 disables), as SamAutomaticMaskGenerator's post-processing.
    min_region_area: final instances (after overlaps are resolved) smaller than this many
        pixels are dropped.
    alpha_min: pixels whose rendered alpha is below this are left out of every instance.
    threads: onnxruntime intra-op threads (0 = onnxruntime's default).
    providers: onnxruntime execution providers, e.g. ["CUDAExecutionProvider",
        "CPUExecutionProvider"]; None = CUDA when available, else CPU.
    """

    sam_encoder: str | None = None
    sam_decoder: str | None = None
    points_per_side: int = 32
    points_per_batch: int = 64
    pred_iou_thresh: float = 0.88
    stability_score_thresh: float = 0.95
    stability_score_offset: float = 1.0
    box_nms_thresh: float = 0.7
    crop_n_layers: int = 0
    crop_nms_thresh: float = 0.7
    crop_overlap_ratio: float = 512 / 1500
    crop_n_points_downscale_factor: int = 1
    min_mask_region_area: int = 0
    min_region_area: int = 64
    alpha_min: float = ALPHA_MIN
    threads: int = 0
    providers: list[str] | None = None

    def __post_init__(self):
        def need(ok: bool, key: str, what: str):
            if not ok:
                raise ConfigError(f"config key 'segment.{key}' = {getattr(self, key)!r}: {what}")

        need(self.points_per_side >= 1, "points_per_side", "must be >= 1")
        need(self.points_per_batch >= 1, "points_per_batch", "must be >= 1")
        need(self.stability_score_offset > 0, "stability_score_offset", "must be > 0")
        for key in ("pred_iou_thresh", "stability_score_thresh", "box_nms_thresh",
                    "crop_nms_thresh", "crop_overlap_ratio", "alpha_min"):
            need(0.0 <= getattr(self, key) <= 1.0, key, "must be in [0, 1]")
        need(self.crop_n_layers >= 0, "crop_n_layers", "must be >= 0")
        need(self.crop_n_points_downscale_factor >= 1, "crop_n_points_downscale_factor",
             "must be >= 1")
        need(self.min_mask_region_area >= 0, "min_mask_region_area", "must be >= 0")
        need(self.min_region_area >= 0, "min_region_area", "must be >= 0")
        need(self.threads >= 0, "threads", "must be >= 0")

    @classmethod
    def from_segment_options(cls, options: Any, **overrides) -> "SamOptions":
        """Take every field of ``options`` (e.g. a ``SegmentOptions``) that SamOptions also has."""
        names = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in vars(options).items() if k in names}
        values.update(overrides)
        return cls(**values)


@dataclass
class Embedding:
    """An image embedding with the geometry needed to map prompts and masks.

    ``features``: the encoder output [1, C, e, e]; ``orig_size``: (h, w) of the encoded image;
    ``resized_size``: (h', w') of the image inside the model's S x S frame (SAM layout; equal to
    ``orig_size`` for EfficientSAM, whose decoder works in original pixels).
    """

    features: np.ndarray
    orig_size: tuple[int, int]
    resized_size: tuple[int, int]
    feeds: dict = field(default_factory=dict, repr=False)  # decoder inputs that do not change
    grid: Any = field(default=None, repr=False)  # low-res -> image sampling grid (cached)


@dataclass
class MaskProposal:
    """One automatic-mask-generator result (masks may overlap each other).

    ``mask``: bool [H, W] at the original image size; ``bbox``: (x0, y0, x1, y1), exclusive;
    ``predicted_iou`` and ``stability_score`` in [0, 1]; ``point``: the prompt (x, y) in pixels;
    ``crop_box``: the crop it was found in.
    """

    mask: np.ndarray
    bbox: tuple[int, int, int, int]
    predicted_iou: float
    stability_score: float
    point: tuple[float, float]
    crop_box: tuple[int, int, int, int]

    @property
    def score(self) -> float:
        """Predicted IoU x stability score, clipped to [0, 1]."""
        return float(np.clip(self.predicted_iou * self.stability_score, 0.0, 1.0))


# --------------------------------------------------------------------------------------------
# model files


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0][:300] if text else type(e).__name__


def default_providers() -> list[str]:
    """CUDA (when onnxruntime has it) then CPU."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]


def open_session(path: str | os.PathLike | None, role: str, key: str,
                 providers: Sequence[str] | None = None, threads: int = 0):
    """Load one ONNX file with onnxruntime; problems are :class:`ModelFileError` naming ``key``."""
    import onnxruntime as ort

    if not path:
        raise ModelFileError(f"config key 'segment.{key}' is not set; give the path of the SAM "
                             f"{role} ONNX file ({_DOCS})")
    p = Path(path).expanduser()
    if not p.is_file():
        raise ModelFileError(f"{p}: SAM {role} ONNX file not found (config key "
                             f"'segment.{key}'); fix the path or export the file ({_DOCS})")
    so = ort.SessionOptions()
    so.log_severity_level = 3
    if threads:
        so.intra_op_num_threads = int(threads)
        so.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(str(p), sess_options=so,
                                    providers=list(providers or default_providers()))
    except Exception as e:  # onnxruntime raises several exception types for unreadable files
        raise ModelFileError(f"{p}: not a loadable ONNX model ({_first_line(e)}); config key "
                             f"'segment.{key}' must name the SAM {role} .onnx file "
                             f"({_DOCS})") from None


def _describe(args) -> str:
    return ", ".join(f"{a.name} {list(a.shape)}" for a in args) or "none"


def _static(dim) -> int | None:
    """A dimension's size, or None when it is symbolic."""
    return dim if isinstance(dim, int) and dim > 0 else None


_NP_TYPES = {"tensor(float)": np.float32, "tensor(double)": np.float64,
             "tensor(int64)": np.int64, "tensor(int32)": np.int32, "tensor(float16)": np.float16}


class SamOnnxModel:
    """The two SAM ONNX sessions: :meth:`embed` an image once, then :meth:`predict` prompts.

    ``variant`` is ``"sam"`` or ``"efficientsam"``; ``encoder_layout`` is ``"nchw"``, ``"hwc"``
    (SAM) or ``"nchw_unit"`` (EfficientSAM); ``image_size`` is the SAM frame size S;
    ``batched`` tells whether one decoder call takes several prompts.
    """

    def __init__(self, encoder_path: str | os.PathLike | None,
                 decoder_path: str | os.PathLike | None,
                 providers: Sequence[str] | None = None, threads: int = 0):
        self.encoder_path = Path(encoder_path) if encoder_path else None
        self.decoder_path = Path(decoder_path) if decoder_path else None
        self.encoder = open_session(encoder_path, "image-encoder", "sam_encoder", providers,
                                    threads)
        self.decoder = open_session(decoder_path, "mask-decoder", "sam_decoder", providers,
                                    threads)
        self._detect()

    # ---- signature detection ----------------------------------------------------------------
    def _detect(self) -> None:
        dec_in = {a.name: a for a in self.decoder.get_inputs()}
        enc_in = self.encoder.get_inputs()
        enc_names = {a.name for a in enc_in}
        if set(SAM_DECODER_INPUTS) <= dec_in.keys():
            self.variant = "sam"
        elif set(EFFICIENTSAM_DECODER_INPUTS) <= dec_in.keys():
            self.variant = "efficientsam"
        else:
            if {"point_coords", "batched_point_coords"} & enc_names:
                raise ModelFileError(
                    f"{self.decoder_path}: this looks like a SAM image encoder and "
                    f"{self.encoder_path} like the decoder; swap 'segment.sam_encoder' and "
                    f"'segment.sam_decoder'")
            if "batched_images" in dec_in:
                raise ModelFileError(
                    f"{self.decoder_path}: EfficientSAM's combined model (image + prompts in "
                    f"one file); export and use its *_encoder.onnx / *_decoder.onnx pair "
                    f"({_DOCS})")
            if "image_embed" in dec_in or any(n.startswith("high_res_feats") for n in dec_in):
                raise ModelFileError(
                    f"{self.decoder_path}: a SAM 2 decoder (inputs {_describe(dec_in.values())})"
                    f"; SAM 2 exports are not supported, use a SAM, MobileSAM or EfficientSAM "
                    f"export ({_DOCS})")
            raise ModelFileError(
                f"{self.decoder_path}: not a SAM mask decoder this backend knows; it has inputs "
                f"{_describe(dec_in.values())} but a SAM/MobileSAM decoder needs "
                f"{', '.join(SAM_DECODER_INPUTS)} and an EfficientSAM decoder needs "
                f"{', '.join(EFFICIENTSAM_DECODER_INPUTS)} ({_DOCS})")
        self._dec_in = dec_in
        self._dec_out = self.decoder.get_outputs()

        emb = dec_in["image_embeddings"].shape
        if len(emb) != 4:
            raise ModelFileError(f"{self.decoder_path}: input image_embeddings has shape "
                                 f"{list(emb)}; expected [1, C, e, e]")
        self.embed_channels = _static(emb[1])
        self.embed_size = _static(emb[2]) or 64

        if len(enc_in) != 1:
            raise ModelFileError(f"{self.encoder_path}: a SAM image encoder has one input (the "
                                 f"image); this file has {_describe(enc_in)}")
        enc = enc_in[0]
        self._enc_name = enc.name
        shape = list(enc.shape)
        if self.variant == "sam" and len(shape) == 4 and (
                enc.name == "batched_images" or None in [_static(d) for d in shape[2:]]):
            raise ModelFileError(f"{self.encoder_path}: input {enc.name} {shape} is an "
                                 f"EfficientSAM encoder (any image size) but "
                                 f"{self.decoder_path} is a SAM/MobileSAM decoder; use the "
                                 f"decoder exported with this encoder")
        if self.variant == "sam" and len(shape) == 4 and _static(shape[1]) in (3, None):
            self.encoder_layout = "nchw"
            self.image_size = _static(shape[2])
            if _static(shape[3]) != self.image_size:
                raise ModelFileError(f"{self.encoder_path}: input {enc.name} {shape} is not "
                                     f"square; a SAM encoder takes [1, 3, S, S]")
        elif self.variant == "sam" and len(shape) == 3 and _static(shape[2]) in (3, None):
            self.encoder_layout = "hwc"
            self.image_size = 16 * self.embed_size
        elif self.variant == "efficientsam" and len(shape) == 4 and _static(shape[1]) in (3, None):
            self.encoder_layout = "nchw_unit"
            self.image_size = 16 * self.embed_size
        else:
            expect = ("[1, 3, 1024, 1024] (normalised, padded) or [h, w, 3] (samexporter "
                      "--use-preprocess)" if self.variant == "sam" else "[B, 3, H, W]")
            raise ModelFileError(f"{self.encoder_path}: image-encoder input {enc.name} {shape} "
                                 f"does not fit the {self.variant} decoder "
                                 f"{self.decoder_path}; expected {expect} ({_DOCS})")
        out = self.encoder.get_outputs()[0].shape
        if len(out) != 4 or any(a is not None and b is not None and a != b for a, b in
                                zip(map(_static, out[1:]), map(_static, emb[1:]))):
            raise ModelFileError(f"{self.encoder_path}: encoder output {list(out)} does not fit "
                                 f"decoder input image_embeddings {list(emb)} of "
                                 f"{self.decoder_path}; the two files must come from the same "
                                 f"model")

        coords = dec_in["point_coords" if self.variant == "sam" else "batched_point_coords"]
        batch_axis = 0 if self.variant == "sam" else 1
        self.batched = _static(coords.shape[batch_axis]) is None
        names = [o.name for o in self._dec_out]
        if self.variant == "sam":
            self._iou_idx = names.index("iou_predictions") if "iou_predictions" in names else 1
            self._mask_idx = names.index("masks") if "masks" in names else 0
            self._low_idx = (names.index("low_res_masks") if "low_res_masks" in names else
                             (2 if len(names) == 3 else None))
        else:
            self._iou_idx = names.index("iou_predictions") if "iou_predictions" in names else 1
            self._mask_idx = names.index("output_masks") if "output_masks" in names else 0
            self._low_idx = None
        if len(names) <= max(self._iou_idx, self._mask_idx):
            raise ModelFileError(f"{self.decoder_path}: outputs {names}; expected masks and "
                                 f"iou_predictions")
        log.info("SAM ONNX: %s decoder (%s prompts per call), %s encoder, frame %d, embedding "
                 "%s x %d x %d", self.variant, "many" if self.batched else "one",
                 self.encoder_layout, self.image_size, self.embed_channels or "C",
                 self.embed_size, self.embed_size)

    # ---- encoder ------------------------------------------------------------------------------
    def resized_size(self, h: int, w: int) -> tuple[int, int]:
        """(h', w') of an h x w image resized so that its longest side is S (SAM rounding)."""
        scale = self.image_size / max(h, w)
        return int(h * scale + 0.5), int(w * scale + 0.5)

    def embed(self, rgb: np.ndarray) -> Embedding:
        """Run the encoder on ``rgb`` float32 [H, W, 3] (sRGB values in [0, 1])."""
        h, w = rgb.shape[:2]
        if self.encoder_layout == "nchw_unit":
            inp = np.ascontiguousarray(rgb.transpose(2, 0, 1)[None], dtype=np.float32)
            resized = (h, w)
        else:
            resized = self.resized_size(h, w)
            interp = cv2.INTER_AREA if resized[0] < h else cv2.INTER_LINEAR
            img = cv2.resize(np.ascontiguousarray(rgb * 255.0, dtype=np.float32),
                             (resized[1], resized[0]), interpolation=interp)
            if self.encoder_layout == "hwc":
                inp = img
            else:
                s = self.image_size
                norm = (img - PIXEL_MEAN) / PIXEL_STD
                padded = np.zeros((s, s, 3), dtype=np.float32)
                padded[:resized[0], :resized[1]] = norm
                inp = np.ascontiguousarray(padded.transpose(2, 0, 1)[None])
        try:
            feats = self.encoder.run(None, {self._enc_name: inp})[0]
        except Exception as e:
            raise ModelFileError(f"{self.encoder_path}: the image encoder failed on a "
                                 f"{list(inp.shape)} input ({_first_line(e)})") from None
        return Embedding(np.asarray(feats, dtype=np.float32), (h, w), resized)

    # ---- decoder ------------------------------------------------------------------------------
    def _feed(self, name: str, value: np.ndarray) -> np.ndarray:
        dtype = _NP_TYPES.get(self._dec_in[name].type, np.float32)
        return np.ascontiguousarray(value, dtype=dtype)

    def predict(self, emb: Embedding,
                points: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """Masks for single foreground point prompts, before mapping to the image.

        ``points``: [B, 2] (x, y) in pixels of the embedded image. Returns mask logits float32
        [B, M, a, b], predicted IoUs float32 [B, M] and ``lowres``: True when the logits are
        SAM's low-resolution grid over the S x S frame (map them with :meth:`to_image`), False
        when they are already at the embedded image's size. M is the number of multi-mask
        outputs (3 for SAM/MobileSAM/EfficientSAM; 1 for single-mask exports).
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        step = max(len(points) if self.batched else 1, 1)
        run = self._run_sam if self.variant == "sam" else self._run_efficientsam
        parts = [run(emb, points[i:i + step]) for i in range(0, len(points), step)]
        lowres = parts[0][2]
        return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                lowres)

    def to_image(self, emb: Embedding, logits: np.ndarray, lowres: bool) -> np.ndarray:
        """Logits [K, a, b] from :meth:`predict` -> float32 [K, h, w] at the embedded image."""
        if not lowres:
            return logits.astype(np.float32, copy=False)
        if emb.grid is None:
            emb.grid = lowres_grid(emb.resized_size, self.image_size, emb.orig_size)
        return lowres_to_image(logits, emb.resized_size, self.image_size, emb.orig_size,
                               grid=emb.grid)

    def _run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        try:
            return self.decoder.run(None, feeds)
        except Exception as e:
            raise ModelFileError(f"{self.decoder_path}: the mask decoder failed on inputs "
                                 f"{ {k: list(v.shape) for k, v in feeds.items()} } "
                                 f"({_first_line(e)})") from None

    def _run_sam(self, emb: Embedding, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        b = len(pts)
        (h, w), (rh, rw) = emb.orig_size, emb.resized_size
        coords = np.zeros((b, 2, 2))
        coords[:, 0, 0] = pts[:, 0] * (rw / w)
        coords[:, 0, 1] = pts[:, 1] * (rh / h)
        labels = np.tile(np.array([[1.0, -1.0]]), (b, 1))
        mshape = [(_static(d) or (b if k == 0 else 1 if k == 1 else 4 * self.embed_size))
                  for k, d in enumerate(self._dec_in["mask_input"].shape)]
        if not emb.feeds or emb.feeds["mask_input"].shape != tuple(mshape):
            emb.feeds = {"image_embeddings": self._feed("image_embeddings", emb.features),
                         "mask_input": self._feed("mask_input", np.zeros(mshape)),
                         "has_mask_input": self._feed("has_mask_input", np.zeros(1)),
                         "orig_im_size": self._feed("orig_im_size", np.array([h, w]))}
        feeds = dict(emb.feeds, point_coords=self._feed("point_coords", coords),
                     point_labels=self._feed("point_labels", labels))
        out = self._run(feeds)
        iou = np.asarray(out[self._iou_idx], dtype=np.float32).reshape(b, -1)
        low = out[self._low_idx] if self._low_idx is not None else None
        lowres = low is not None and low.ndim == 4 and low.shape[:2] == (b, iou.shape[1])
        if lowres:
            logits = np.asarray(low, dtype=np.float32)
        else:
            masks = np.asarray(out[self._mask_idx], dtype=np.float32)
            if masks.ndim != 4 or masks.shape[0] != b:
                raise ModelFileError(f"{self.decoder_path}: output masks has shape "
                                     f"{list(masks.shape)}; expected [{b}, M, {h}, {w}]")
            logits = resize_logits(masks, (h, w))
        if iou.shape[1] == 4:  # SAM's token 0 is the single-mask output: keep the multimask 1..3
            iou, logits = iou[:, 1:], logits[:, 1:]
        return logits, iou, lowres

    def _run_efficientsam(self, emb: Embedding,
                          pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        b = len(pts)
        h, w = emb.orig_size
        if not emb.feeds:
            emb.feeds = {"image_embeddings": self._feed("image_embeddings", emb.features),
                         "orig_im_size": self._feed("orig_im_size", np.array([h, w]))}
        feeds = dict(emb.feeds,
                     batched_point_coords=self._feed("batched_point_coords",
                                                     pts.reshape(1, b, 1, 2)),
                     batched_point_labels=self._feed("batched_point_labels", np.ones((1, b, 1))))
        out = self._run(feeds)
        masks = np.asarray(out[self._mask_idx], dtype=np.float32)
        iou = np.asarray(out[self._iou_idx], dtype=np.float32)
        if masks.ndim != 5 or masks.shape[:2] != (1, b):
            raise ModelFileError(f"{self.decoder_path}: output masks has shape "
                                 f"{list(masks.shape)}; expected [1, {b}, 3, {h}, {w}]")
        return resize_logits(masks[0], (h, w)), iou.reshape(b, -1), False


def lowres_grid(resized_size: tuple[int, int], image_size: int, orig_size: tuple[int, int]):
    """Sampling grid (torch float32 [h, w, 2], grid_sample's [-1, 1], align_corners=False) that
    puts each original pixel centre into SAM's S x S frame, where the image occupies the
    top-left ``resized_size`` (h', w')."""
    import torch

    (h, w), (rh, rw) = orig_size, resized_size
    gx = (torch.arange(w, dtype=torch.float32) + 0.5) * (rw / w) * (2.0 / image_size) - 1.0
    gy = (torch.arange(h, dtype=torch.float32) + 0.5) * (rh / h) * (2.0 / image_size) - 1.0
    return torch.stack(torch.meshgrid(gx, gy, indexing="xy"), dim=-1)


def lowres_to_image(low: np.ndarray, resized_size: tuple[int, int], image_size: int,
                    orig_size: tuple[int, int], grid=None) -> np.ndarray:
    """Map SAM low-resolution logits to the original image.

    ``low``: float [K, L, L] logits over the model's S x S frame (L = S / 4); the image occupies
    the top-left ``resized_size`` (h', w') of that frame. Returns float32 [K, h, w]: one bilinear
    resampling at the original pixel centres (undoes the padding and the resize in one step;
    edge values are repeated outside the grid). ``grid``: :func:`lowres_grid`, if precomputed.
    """
    import torch
    import torch.nn.functional as F

    h, w = orig_size
    if grid is None:
        grid = lowres_grid(resized_size, image_size, orig_size)
    low_t = torch.from_numpy(np.ascontiguousarray(low, dtype=np.float32))
    n = low_t.shape[-1]
    out = np.empty((low_t.shape[0], h, w), dtype=np.float32)
    for k in range(0, low_t.shape[0], 256):
        chunk = low_t[k:k + 256].reshape(-1, 1, n, n)
        g = grid.expand(chunk.shape[0], h, w, 2)
        out[k:k + 256] = F.grid_sample(chunk, g, mode="bilinear", padding_mode="border",
                                       align_corners=False)[:, 0].numpy()
    return out


def resize_logits(masks: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of logits [B, M, h0, w0] to [B, M, h, w] (no-op when already that size)."""
    h, w = size
    if masks.shape[-2:] == (h, w):
        return masks.astype(np.float32, copy=False)
    flat = masks.reshape(-1, *masks.shape[-2:])
    out = np.stack([cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR) for m in flat])
    return out.reshape(*masks.shape[:-2], h, w)


# --------------------------------------------------------------------------------------------
# automatic mask generation


@dataclass
class _Batch:
    masks: list = field(default_factory=list)  # bool [h, w] in crop frame
    boxes: list = field(default_factory=list)  # image frame
    iou: list = field(default_factory=list)
    stab: list = field(default_factory=list)
    points: list = field(default_factory=list)  # image frame


class SamOnnxSegmenter:
    """"Segment everything" with SAM ONNX models (a :class:`gdiff.segment.base.Segmenter`).

    Build it with the file paths and options (``SamOnnxSegmenter(encoder, decoder,
    points_per_side=32, ...)``, keywords as :class:`SamOptions`), from a :class:`SamOptions`
    (``options=``), or from the ``segment`` section's ``SegmentOptions`` (positional, as
    :func:`gdiff.segment.base.make_segmenter` does). Raises :class:`ModelFileError` for
    missing or incompatible files and :class:`ConfigError` for bad option values.

    ``last_stats`` holds the counts of the last :meth:`generate` call (prompts, candidates, and
    what each filter kept).
    """

    def __init__(self, encoder_path: Any = None, decoder_path: str | os.PathLike | None = None,
                 options: SamOptions | None = None, **overrides):
        if encoder_path is not None and not isinstance(encoder_path, (str, os.PathLike)):
            options = SamOptions.from_segment_options(encoder_path, **overrides)  # SegmentOptions
        elif options is None:
            try:
                options = SamOptions(**overrides)
            except TypeError as e:
                raise ConfigError(f"SAM backend: {e}") from None
        elif overrides:
            options = dataclasses.replace(options, **overrides)
        if encoder_path is not None and isinstance(encoder_path, (str, os.PathLike)):
            options = dataclasses.replace(options, sam_encoder=str(encoder_path))
        if decoder_path is not None:
            options = dataclasses.replace(options, sam_decoder=str(decoder_path))
        self.options = options
        self.model = SamOnnxModel(options.sam_encoder, options.sam_decoder,
                                  providers=options.providers, threads=options.threads)
        self.last_stats: dict[str, int] = {}

    # ---- public -----------------------------------------------------------------------------
    def segment(self, rgb: np.ndarray, depth: np.ndarray | None = None,
                alpha: np.ndarray | None = None) -> list[Instance]:
        """Non-overlapping instances of ``rgb`` float32 [H, W, 3] (sRGB, [0, 1]).

        Proposals from :meth:`generate` claim pixels in order of decreasing score (predicted IoU
        x stability); pixels with ``alpha`` [H, W] below ``alpha_min`` belong to no instance;
        islands smaller than ``min_region_area`` are dropped, as are instances left smaller
        than that. ``depth`` is not used by SAM. Returns instances by decreasing score.
        """
        rgb = self._check_image(rgb)
        h, w = rgb.shape[:2]
        proposals = sorted(self.generate(rgb), key=lambda p: -p.score)
        free = np.ones((h, w), dtype=bool)
        if alpha is not None:
            alpha = np.asarray(alpha, dtype=np.float32)
            if alpha.shape != (h, w):
                raise ValueError(f"alpha must be [H, W] = [{h}, {w}], got {alpha.shape}")
            free &= alpha >= self.options.alpha_min
        min_area = max(int(self.options.min_region_area), 1)
        instances = []
        for p in proposals:
            m = p.mask & free
            if min_area > 1 and m.any():
                m, _ = remove_small_regions(m, min_area, "islands")
            if np.count_nonzero(m) < min_area:
                continue
            free &= ~m
            instances.append(Instance(mask=m, score=p.score, bbox=mask_bbox(m)))
        self.last_stats["instances"] = len(instances)
        log.debug("SAM: %s", self.last_stats)
        return instances

    def generate(self, rgb: np.ndarray) -> list[MaskProposal]:
        """SamAutomaticMaskGenerator proposals (may overlap) for ``rgb`` float32 [H, W, 3]."""
        o = self.options
        rgb = self._check_image(rgb)
        h, w = rgb.shape[:2]
        stats = dict(prompts=0, candidates=0, after_iou=0, after_stability=0, after_edge=0,
                     after_nms=0)
        boxes, layers = crop_boxes(h, w, o.crop_n_layers, o.crop_overlap_ratio)
        props: list[MaskProposal] = []
        for box, layer in zip(boxes, layers):
            props += self._process_crop(rgb, box, layer, stats)
        if len(boxes) > 1 and props:
            # duplicates between crops: prefer masks from smaller crops
            scores = [1.0 / max((c[2] - c[0]) * (c[3] - c[1]), 1) for c in
                      (p.crop_box for p in props)]
            keep = box_nms(np.array([p.bbox for p in props]), scores, o.crop_nms_thresh)
            props = [props[i] for i in sorted(keep)]
        stats["after_crop_nms"] = len(props)
        if o.min_mask_region_area > 0 and props:
            props = self._postprocess_small_regions(props, o.min_mask_region_area)
        stats["proposals"] = len(props)
        self.last_stats = stats
        return props

    # ---- steps ------------------------------------------------------------------------------
    @staticmethod
    def _check_image(rgb: np.ndarray) -> np.ndarray:
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or min(rgb.shape[:2]) < 1:
            raise ValueError(f"rgb must be [H, W, 3], got shape {rgb.shape}")
        return np.clip(rgb.astype(np.float32, copy=False), 0.0, 1.0)

    def _process_crop(self, rgb: np.ndarray, box: tuple[int, int, int, int], layer: int,
                      stats: dict) -> list[MaskProposal]:
        o = self.options
        x0, y0, x1, y1 = box
        h, w = rgb.shape[:2]
        emb = self.model.embed(rgb[y0:y1, x0:x1])
        cw, ch = x1 - x0, y1 - y0
        n_side = max(int(o.points_per_side / o.crop_n_points_downscale_factor ** layer), 1)
        points = point_grid(n_side) * np.array([cw, ch])
        stats["prompts"] += len(points)
        is_full = box == (0, 0, w, h)
        acc = _Batch()
        for i in range(0, len(points), o.points_per_batch):
            pts = points[i:i + o.points_per_batch]
            raw, iou, lowres = self.model.predict(emb, pts)  # [B, M, a, b], [B, M]
            m = raw.shape[1]
            raw = raw.reshape(-1, *raw.shape[2:])
            iou = iou.reshape(-1)
            pts_rep = np.repeat(pts, m, axis=0)
            stats["candidates"] += len(iou)
            keep = iou > o.pred_iou_thresh if o.pred_iou_thresh > 0 else np.ones(len(iou), bool)
            stats["after_iou"] += int(keep.sum())
            idx = np.flatnonzero(keep)
            if idx.size == 0:
                continue
            logits = self.model.to_image(emb, raw[idx], lowres)  # [k, ch, cw]
            stab = stability_score(logits, 0.0, o.stability_score_offset)
            sel = stab >= o.stability_score_thresh if o.stability_score_thresh > 0 else \
                np.ones(len(idx), bool)
            stats["after_stability"] += int(sel.sum())
            masks = logits[sel] > 0.0
            idx, stab = idx[sel], stab[sel]
            bxs = mask_boxes(masks) + np.array([x0, y0, x0, y0])
            ok = masks.any(axis=(1, 2))
            if not is_full:
                ok &= ~near_crop_edge(bxs, box, (0, 0, w, h))
            stats["after_edge"] += int(ok.sum())
            for j in np.flatnonzero(ok):
                acc.masks.append(masks[j])
                acc.boxes.append(bxs[j])
                acc.iou.append(float(iou[idx[j]]))
                acc.stab.append(float(stab[j]))
                acc.points.append(pts_rep[idx[j]] + np.array([x0, y0]))
        if not acc.masks:
            return []
        keep = box_nms(np.array(acc.boxes), np.array(acc.iou), o.box_nms_thresh)
        stats["after_nms"] += len(keep)
        out = []
        for j in sorted(keep):
            full = np.zeros((h, w), dtype=bool)
            full[y0:y1, x0:x1] = acc.masks[j]
            out.append(MaskProposal(mask=full, bbox=tuple(int(v) for v in acc.boxes[j]),
                                    predicted_iou=acc.iou[j], stability_score=acc.stab[j],
                                    point=(float(acc.points[j][0]), float(acc.points[j][1])),
                                    crop_box=tuple(box)))
        return out

    def _postprocess_small_regions(self, props: list[MaskProposal],
                                   area: int) -> list[MaskProposal]:
        """Fill small holes, drop small islands, then NMS preferring masks that did not change."""
        changed_score = []
        for p in props:
            m, c1 = remove_small_regions(p.mask, area, "holes")
            m, c2 = remove_small_regions(m, area, "islands")
            p.mask = m
            p.bbox = mask_bbox(m)
            changed_score.append(0.0 if (c1 or c2) else 1.0)
        keep = box_nms(np.array([p.bbox for p in props]), changed_score,
                       self.options.box_nms_thresh)
        return [props[i] for i in sorted(keep)]
