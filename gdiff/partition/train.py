"""Training of the partition stage: ``fine_tune`` (losses, optimiser, checkpoints / resume) and
``train_partition`` (the stage: inputs -> ``partition/`` outputs).

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import resource
import shutil
import time as _time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from ..cameras import Camera, image_root
from ..device import resolve_device
from ..errors import TrainingError
from ..io import atomic_path, remove_stale_temporaries, save_torch, write_csv, write_json
from ..knn import NeighbourIndex
from ..log import progress
from ..metrics import confusion, scores_from_counts
from ..splat.gaussians import camera_extent
from ..splat.losses import l1
from ..splat.model import load_model
from ..splat.train import FitOptions
from .data import _load_image, _load_mask, light_changed, read_key_views
from .export import choose_threshold, key_view_maps, write_key_maps, write_split_ply
from .head import ChangeHead
from .losses import bce_on_change_logit, changed_fraction, ignore_weight, neighbour_kl
from .model import PartitionModel, partition_blob, save_partition_model
from .options import PartitionOptions
from .render import blend_weights, blended_change_logit, change_logit_parts, render_features

log = logging.getLogger("gdiff.partition")


def _fit_options(fit) -> dict:
    """The fit stage's options as saved in ``model.meta`` (defaults of FitOptions if absent)."""
    saved = (getattr(fit, "meta", None) or {}).get("options") or {}
    base = dataclasses.asdict(FitOptions())
    return {**base, **{k: v for k, v in saved.items() if k in base}}


def _param_groups(pm: PartitionModel, opts: PartitionOptions, extent: float) -> list[dict]:
    """Adam groups: encodings, conv, and (unless ``geometry_lr_scale`` is 0) the fitted
    parameters at the fit stage's final learning rates x ``geometry_lr_scale`` (they get no
    gradient, so no update, during the frozen steps; the groups do not depend on
    ``iterations``, so a run can be resumed with more steps)."""
    groups = [{"name": "encoding", "params": [pm.head.encoding], "lr": opts.lr_encoding},
              {"name": "conv", "params": list(pm.head.conv.parameters()), "lr": opts.lr_head}]
    s = opts.geometry_lr_scale
    fit = pm.fit
    if s <= 0:
        fit.requires_grad_(False)
        return groups
    fo = _fit_options(fit)
    lrs = {"means": fo["lr_means_final"] * extent, "scales": fo["lr_scales"],
           "quats": fo["lr_quats"], "opacities": fo["lr_opacities"], "sh0": fo["lr_sh0"],
           "shN": fo["lr_shN"]}
    for name, p in fit.splats.items():
        if name in lrs:
            groups.append({"name": name, "params": [p], "lr": lrs[name] * s})
        else:
            p.requires_grad_(False)
    if fit.environment is not None:  # the light stays as fitted, like the colour-change terms
        fit.environment.requires_grad_(False)
    if fit.deformation is not None:
        groups.append({"name": "grid", "params": fit.deformation.grid_parameters(),
                       "lr": fo["lr_grid_final"] * s})
        groups.append({"name": "deform", "params": fit.deformation.mlp_parameters(),
                       "lr": fo["lr_deform_final"] * extent * s})
    return groups


def _tv_loss(pm: PartitionModel, lambda_tv: float | None) -> torch.Tensor:
    """L_TV: the fit stage's grid regularisers of the deformation field (HexPlane TV, time
    smoothness, time L1) with its weights; ``lambda_tv`` overrides the TV weight. 0 for a
    static model."""
    d = pm.fit.deformation
    if d is None or not pm.fit.deforming:
        return pm.background.new_zeros(())
    fo = _fit_options(pm.fit)
    r = d.regularizers()
    w_tv = fo["plane_tv_weight"] if lambda_tv is None else lambda_tv
    return (w_tv * r["plane_tv"] + fo["time_smooth_weight"] * r["time_smooth"]
            + fo["time_l1_weight"] * r["time_l1"])


def _latest_checkpoint(ckdir):
    remove_stale_temporaries(ckdir)
    files = sorted(Path(ckdir).glob("ckpt_*.pt"))
    return files[-1] if files else None


# options that do not change the result: a checkpoint stays valid when they differ
_NON_RESULT_OPTIONS = ("iterations", "checkpoint_every", "log_every", "threshold",
                       "before_gate")


def run_key(opts: PartitionOptions, **inputs) -> dict:
    """What a checkpoint must match to be resumed from: the options that shape the result and
    fingerprints of the inputs (``inputs``: name -> str)."""
    d = {k: v for k, v in dataclasses.asdict(opts).items() if k not in _NON_RESULT_OPTIONS}
    return {**d, **{k: str(v) for k, v in inputs.items()}}


def _save_checkpoint(ckdir, it, pm, opt, index, rows, opts, key) -> None:
    ckdir = Path(ckdir)
    blob = {"iteration": it, "pmodel": partition_blob(pm, opts), "optimizer": opt.state_dict(),
            "index": index.state_dict(), "log": rows, "key": key}
    save_torch(blob, ckdir / f"ckpt_{it:06d}.pt")
    for old in sorted(ckdir.glob("ckpt_*.pt"))[:-2]:  # keep the two newest
        old.unlink(missing_ok=True)


def _view_rng(seed: int, it: int, purpose: int) -> np.random.Generator:
    """Per-iteration random generator: training is reproducible and resumes exactly."""
    return np.random.default_rng([int(seed), int(it), int(purpose)])


def fine_tune(pm: PartitionModel, data: list[dict], opts: PartitionOptions, ckdir=None,
              extent: float = 1.0, key: dict | None = None) -> list[dict]:
    """Optimise ``pm`` on ``data``: L = L1 + L_TV + lambda_2d BCE + lambda_3d L3d.

    Two phases. Geometry frozen (the first ``frozen_iterations`` steps, all of them when
    ``geometry_lr_scale`` is 0): L1 and L_TV are constants and skipped, the blending
    weights of every training view are computed once (:func:`blend_weights`) and a step blends
    one number per Gaussian (the change logit) instead of rasterizing; the encodings and conv
    converge here. Joint (the steps after): the fitted parameters are
    fine-tuned too (at ``geometry_lr_scale`` x the fit's final learning rates) and every step
    rasterizes colour + change logit, so Gaussians straddling a changed object's outline can
    adapt to the masks while L1 keeps the images.
    The BCE weighs each pixel by ``weight`` when a ``data`` item has one (see
    :func:`ignore_weight`) and is class balanced (:func:`bce_on_change_logit`) with
    ``opts.balance_classes``; the changed-pixel fraction is then taken over all targets.

    Args:
        pm: the model (modified in place; its device is used).
        data: one dict per training photo: ``camera`` (Camera), ``time`` (0/1), ``image``
            [H, W, 3] float tensor (sRGB), ``target`` [H, W] float tensor in [0, 1] and
            optionally ``weight`` [H, W] (per-pixel BCE weight, None = 1).
        opts: options (iterations, weights, learning rates, kNN settings, checkpointing).
        ckdir: checkpoint folder (``ckpt_NNNNNN.pt`` every ``checkpoint_every`` iterations and
            at the end, the two newest kept); training resumes from the newest one when its
            iteration is <= ``opts.iterations`` and its ``key`` matches.
        extent: scene extent (world units) scaling the position / deformation learning rates.
        key: :func:`run_key` of this run (default: from ``opts`` alone); a checkpoint with
            another key (other options or inputs) is ignored with a warning.
    Returns:
        the training log: one dict per ``log_every`` iterations (iteration, loss terms, seconds).
    Raises:
        gdiff.errors.TrainingError: the loss became NaN/inf (names iteration and checkpoint).
    """
    if not data:
        raise ValueError("no training views")
    index = NeighbourIndex(opts.knn_k, opts.knn_samples, opts.knn_refresh, opts.seed)
    start, rows = 0, []
    key = run_key(opts) if key is None else key
    ck = _latest_checkpoint(ckdir) if ckdir is not None else None
    if ck is not None:
        try:
            blob = torch.load(ck, map_location="cpu", weights_only=True)
        except Exception as e:  # written atomically, so only a foreign/corrupt file
            log.warning("ignoring unreadable checkpoint %s (%s)", ck, e)
            blob = {"iteration": -1}
        if blob.get("key") != key or blob["iteration"] < 0:
            log.warning("checkpoint %s is from other options or inputs; starting afresh", ck)
            ck = None
        elif blob["iteration"] <= opts.iterations:
            _load_state(pm, blob["pmodel"])
            start, rows = int(blob["iteration"]), list(blob["log"])
            index.load_state_dict(blob["index"])
            log.info("resuming partition training from %s (iteration %d)", ck, start)
        else:
            ck = None
    pm.train()
    # steps [0, frozen_until) keep the geometry (independent of ``iterations``: resumable)
    frozen_until = opts.frozen_iterations if opts.geometry_lr_scale > 0 else opts.iterations
    pos_fraction = (changed_fraction([v["target"] for v in data],
                                     [v.get("weight") for v in data])
                    if opts.balance_classes else None)
    opt = torch.optim.Adam(_param_groups(pm, opts, extent), eps=1e-15)
    frozen_g = weights = None
    if start < frozen_until:
        frozen_g, weights = _cache_weights(pm, data, opts.frozen_scale, opts.cache_max_mb)
    if ck is not None:
        opt.load_state_dict(blob["optimizer"])
    last_ck = str(ck) if ck is not None else "none"
    acc = {"l1": 0.0, "tv": 0.0, "bce": 0.0, "l3d": 0.0, "n3d": 0}
    t0 = _time.perf_counter()
    for it in progress(range(start, opts.iterations), desc="partition", initial=start,
                       total=opts.iterations):
        vi = int(_view_rng(opts.seed, it, 0).integers(len(data)))
        v = data[vi]
        if it == frozen_until and weights is not None:  # the cache is not needed any more
            frozen_g = weights = None
            _log_phase("frozen phase", it - start)
        if it < frozen_until:
            g = frozen_g[float(v["time"])]
            bw, target, weight = weights[vi]
            z = blended_change_logit(pm.head, bw)
            loss_bce = bce_on_change_logit(z, target, pos_fraction, weight)
            loss_l1 = loss_tv = loss_bce.new_full((), float("nan"))  # constants: not computed
            loss = opts.lambda_2d * loss_bce
        else:
            g = pm.fit.at_time(float(v["time"]))
            # the head is affine: rasterize the per-Gaussian change logit (1 channel) next to
            # the colour instead of the D-channel encodings, then add the bias difference
            zg, bias = change_logit_parts(pm.head)
            r = render_features(g, zg[:, None], v["camera"], pm.background, with_rgb=True)
            loss_l1 = l1(r["rgb"], v["image"])
            loss_tv = _tv_loss(pm, opts.lambda_tv)
            loss_bce = bce_on_change_logit(r["features"][..., 0] + bias, v["target"],
                                           pos_fraction, v.get("weight"))
            loss = loss_l1 + loss_tv + opts.lambda_2d * loss_bce
        if opts.lambda_3d > 0 and it % opts.l3d_every == 0:
            s, nb = index.sample(g.means, rng=_view_rng(opts.seed, it, 1))
            loss_3d = neighbour_kl(pm.head.gaussian_logits(), s, nb)
            loss = loss + opts.lambda_3d * loss_3d
            acc["l3d"] += loss_3d.item()
            acc["n3d"] += 1
        if not torch.isfinite(loss):
            raise TrainingError(
                f"partition training diverged: loss is {loss.item()} at iteration {it} "
                f"(L1 {loss_l1.item():.4g}, BCE {loss_bce.item():.4g}); last checkpoint: "
                f"{last_ck}. Lower partition.lr_encoding / lr_head / geometry_lr_scale and "
                "rerun (training resumes from the checkpoint)")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        acc["l1"] += loss_l1.item()
        acc["tv"] += loss_tv.item()
        acc["bce"] += loss_bce.item()
        done = it + 1
        if done % opts.log_every == 0 or done == opts.iterations:
            n = done - (rows[-1]["iteration"] if rows else 0)
            rows.append({"iteration": done, "l1": acc["l1"] / n, "tv": acc["tv"] / n,
                         "bce": acc["bce"] / n,
                         "l3d": acc["l3d"] / acc["n3d"] if acc["n3d"] else float("nan"),
                         "seconds": _time.perf_counter() - t0})
            acc = {"l1": 0.0, "tv": 0.0, "bce": 0.0, "l3d": 0.0, "n3d": 0}
        if ckdir is not None and (done % opts.checkpoint_every == 0 or done == opts.iterations):
            _save_checkpoint(ckdir, done, pm, opt, index, rows, opts, key)
            last_ck = str(Path(ckdir) / f"ckpt_{done:06d}.pt")
    frozen_g = weights = None
    _log_phase("training", opts.iterations - start)
    pm.eval()
    return rows


# Per pixel, cached blend weights whose sum stays below this are dropped (the faint pairs behind
# an opaque surface, most of a pixel's pairs): a blended change logit moves by at most this
# fraction of the largest dropped per-Gaussian logit. Weights are stored as float16.
CACHE_TOLERANCE = 1e-3


def _cache_weights(pm: PartitionModel, data: list[dict], scale: float | None = None,
                   max_mb: float = 1024.0):
    """Frozen geometry: the activated Gaussians per training time (no grad) and, for every view
    in ``data`` (same order), ``(BlendWeights, target, weight)`` with the camera, target and
    BCE weight resized by ``scale`` (area averaging: soft targets at the edges); the weights
    are float16, faint pairs dropped up to :data:`CACHE_TOLERANCE` per pixel.

    ``scale`` None: the views at their training size when all their weights fit in ``max_mb``
    MB; once they do not, the pairs counted so far, extrapolated to all views, give the scale
    whose pixels fit (the pairs of a view grow with its pixel count) and the views are cached
    again at that scale."""
    t0 = _time.perf_counter()
    with torch.no_grad():
        gs = {t: pm.fit.at_time(t) for t in sorted({float(v["time"]) for v in data})}
    if scale is not None:
        out, _ = _view_weights(gs, data, scale)
        how = f"partition.frozen_scale {scale:g}"
    else:
        budget = max_mb * 2**20
        out, expected = _view_weights(gs, data, 1.0, budget)
        if out is None:  # over the budget at the training size
            scale = max(0.01, math.floor(100 * math.sqrt(budget / expected)) / 100)
            how = (f"the training size would take about {expected / 2**20:.0f} MB, over "
                   f"partition.cache_max_mb ({max_mb:g})")
            out, _ = _view_weights(gs, data, scale)
        else:
            scale, how = 1.0, f"the training size fits in partition.cache_max_mb ({max_mb:g})"
    log.info("blend weights of %d views at %dx%d (scale %.2f: %s): %d pairs, %.0f MB, %.1f s",
             len(data), out[0][0].width, out[0][0].height, scale, how,
             sum(len(w[0].gid) for w in out), sum(w[0].nbytes for w in out) / 2**20,
             _time.perf_counter() - t0)
    _log_phase("blend weights", len(data))
    return gs, out


def _view_weights(gs: dict, data: list[dict], scale: float,
                  max_bytes: float | None = None) -> tuple[list | None, float]:
    """``(views, nbytes)``: the ``(BlendWeights, target, weight)`` of every view at ``scale``
    (see :func:`_cache_weights`) and their bytes; with ``max_bytes``, as soon as the views so
    far take more, ``(None, their bytes extrapolated to all views)``."""
    out, nbytes = [], 0
    for i, v in enumerate(progress(data, desc="partition weights")):
        cam = v["camera"] if scale == 1.0 else v["camera"].scaled(scale)
        bw = blend_weights(gs[float(v["time"])], cam, tolerance=CACHE_TOLERANCE,
                           dtype=torch.float16)
        out.append((bw, _resized(v["target"], cam), _resized(v.get("weight"), cam)))
        nbytes += bw.nbytes
        if max_bytes is not None and nbytes > max_bytes:
            return None, float(nbytes * len(data) / (i + 1))
    return out, float(nbytes)


def _resized(x: torch.Tensor | None, cam) -> torch.Tensor | None:
    """[H, W] map resized to the camera's size by area averaging (None stays None)."""
    if x is None or tuple(x.shape) == (cam.height, cam.width):
        return x
    return torch.nn.functional.interpolate(x[None, None], size=(cam.height, cam.width),
                                           mode="area")[0, 0]


def _log_phase(name: str, steps: int) -> None:
    """Log the process's CPU seconds (user + system, all threads) and peak RSS so far."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    log.info("%s done (%d steps): CPU %.1f s so far, peak RSS %.0f MB", name, steps,
             ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024)


def _load_state(pm: PartitionModel, blob: dict) -> None:
    """Copy fitted parameters, encodings and head from a :func:`partition_blob` into ``pm``."""
    with torch.no_grad():
        pm.fit.load_state_dict(blob["fit"]["state_dict"])
        pm.head.load_state_dict(blob["head"])


def train_partition(fit_model_path, cameras_json, keyframes_csv, scene_dir, out_dir,
                    options: PartitionOptions | None = None, device="auto") -> dict:
    """The ``partition`` stage: fine-tune the fitted 4D model with change encodings.

    Args:
        fit_model_path: ``results/<scene>/fit/model.pt``.
        cameras_json: ``results/<scene>/poses/cameras.json`` (key images and eval views).
        keyframes_csv: ``results/<scene>/change/keyframes.csv`` (targets, see
            :func:`read_key_views`).
        scene_dir: the scene folder (photos).
        out_dir: ``results/<scene>/partition/``; receives ``model.pt``, ``changed.ply``,
            ``unchanged.ply`` (+ per-time ``changed_t0/_t1`` PLYs),
            ``probability.npy`` (per-Gaussian change probability [N] float32),
            ``maps/`` (change maps at every key pose, see :func:`write_key_maps`),
            ``keypose_scores.csv``, ``train_log.csv``, ``summary.json``; ``ckpt/`` while
            training (removed when the stage completes; a rerun resumes from it).
        options: :class:`PartitionOptions` (defaults when None).
        device: ``auto``/``cpu``/``cuda``.
    Returns:
        summary dict (counts of Gaussians, mean key-pose IoU, seconds).
    """
    opts = options or PartitionOptions()
    dev = resolve_device(device)
    out = Path(out_dir)
    t_start = _time.perf_counter()
    torch.manual_seed(opts.seed)
    fit = load_model(fit_model_path, dev)
    fo = _fit_options(fit)
    max_side = fo["max_side"] if opts.max_side is None else opts.max_side
    views = read_key_views(keyframes_csv, cameras_json, image_root(scene_dir, cameras_json),
                           max_side)
    data = [{"camera": v.camera, "time": v.time,
             "image": torch.from_numpy(_load_image(v.image, v.camera)).to(dev),
             "target": torch.from_numpy(_load_mask(v.target, v.camera)).to(dev),
             "weight": (torch.from_numpy(ignore_weight(_load_mask(v.target, v.camera),
                                                       _load_mask(v.other, v.camera))).to(dev)
                        if opts.ignore_other_time else None)} for v in views]
    head = ChangeHead(len(fit), opts.encoding_dim, opts.seed)
    bg = [1.0, 1.0, 1.0] if fo["background"] == "white" else None  # random/black: black
    meta = getattr(fit, "meta", None) or {}
    cam0 = Camera(**meta["camera"]) if "camera" in meta else views[0].camera.with_pose(np.eye(4))
    gate = opts.before_gate
    if gate > 0 and light_changed(keyframes_csv):
        log.info("partition: the union map is the plain union of the two times' maps "
                 "(partition.before_gate not applied): the compare stage took the scene for a "
                 "change of light, and the two times' renders then differ everywhere")
        gate = 0.0
    pm = PartitionModel(fit, head, cam0, bg, 0.5 if opts.threshold is None else opts.threshold,
                        gate).to(dev)
    extent = float(meta.get("extent") or camera_extent(
        np.stack([v.camera.center for v in views])))
    log.info("partition: %d Gaussians, %d key views, %d iterations on %s", len(fit), len(views),
             opts.iterations, dev)
    key = run_key(opts, fit=_sha1(fit_model_path), keyframes=_sha1(keyframes_csv),
                  cameras=_sha1(cameras_json))
    rows = fine_tune(pm, data, opts, out / "ckpt", extent, key)
    t_train = _time.perf_counter() - t_start
    # the threshold is chosen on the plain union: the key-view masks it is measured against
    # hold the surface an added object hid from the before photos, which the gate leaves out
    maps = key_view_maps(pm, views, before_gate=0.0)
    pm.threshold = _pick_threshold(opts, views, maps, out / "threshold.json")
    if gate > 0:  # the gate's unchanged pixels are those under the chosen threshold
        maps = key_view_maps(pm, views)
    save_partition_model(pm, out / "model.pt", opts)
    write_csv(out / "train_log.csv", pd.DataFrame(rows))
    prob = pm.gaussian_probability().detach().cpu().numpy().astype(np.float32)
    with atomic_path(out / "probability.npy") as tmp:
        np.save(tmp, prob)
    counts = write_split_ply(pm, out, pm.threshold)
    scores = write_key_maps(pm, views, out / "maps", maps)
    del maps
    write_csv(out / "keypose_scores.csv", scores)
    summary = {"gaussians": len(fit), **counts, "key_views": len(views),
               "iterations": opts.iterations, "threshold": pm.threshold,
               "before_gate": pm.before_gate,
               "keypose_iou_own_time": _mean_defined(scores["iou_own_time"]),
               "keypose_iou_union": _mean_defined(scores["iou_union"]),
               "seconds_train": t_train, "seconds_total": _time.perf_counter() - t_start}
    write_json(out / "summary.json", summary)
    shutil.rmtree(out / "ckpt", ignore_errors=True)  # finished: nothing to resume
    log.info("partition done: %s", summary)
    return summary


def _mean_defined(x) -> float:
    """Mean of the defined (non-NaN) values; NaN, without a warning, when there are none (no
    key view with a changed pixel in its mask or its map: IoU is undefined there)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else float("nan")


# pooled key-view F1 the maps must reach at a threshold off 0.5 for it to be taken: at 1/2 the
# pixels where map and masks agree on a change (2 TP) are as many as those where they disagree
# (FP + FN); below it no threshold reproduces the masks, and the maximum follows stray pixels
MIN_REPRODUCED_F1 = 0.5


def operating_point(best_threshold: float | None, best_f1: float, f1_at_half: float,
                    min_gain: float) -> tuple[float, str]:
    """The map threshold when ``partition.threshold`` is null, and why.

    0.5 is the probability a BCE-trained head calls even; it stays unless the threshold that
    best reproduces the key-view masks (``best_threshold``, pooled F1 ``best_f1``) beats it
    there by more than ``min_gain`` F1 and reproduces them at least half-way (``best_f1`` >=
    :data:`MIN_REPRODUCED_F1`): a head that could not fit its supervision (masks that
    disagree between views leave changed Gaussians at low probabilities) gets the threshold
    its own training views call for, while a nearly flat F1 curve is not read as a reason to
    move (on views it was trained on, the maximum also fits their noise), nor is a curve that
    stays low everywhere (a scene with next to no change: a few stray changed pixels in the
    masks would pull the threshold down to where the map paints noise over every view).
    """
    if best_threshold is None:
        return 0.5, "default 0.5 (the key-view masks have no changed or no unchanged pixel)"
    if best_f1 < MIN_REPRODUCED_F1:
        return 0.5, (f"0.5: no threshold reproduces the key-view masks (best F1 {best_f1:.3f} "
                     f"at {best_threshold:.2f}, < {MIN_REPRODUCED_F1})")
    if best_f1 - f1_at_half > min_gain:
        return float(best_threshold), (f"max F1 over the key views ({best_f1:.3f}, "
                                       f"{best_f1 - f1_at_half:+.3f} over 0.5)")
    return 0.5, (f"0.5: the key-view maximum ({best_threshold:.2f}) gains "
                 f"{best_f1 - f1_at_half:.3f} F1 there, <= partition.threshold_gain")


def _pick_threshold(opts: PartitionOptions, views, maps, path) -> float:
    """The map threshold: ``opts.threshold`` when set, else :func:`operating_point` from the
    key views (how well the union maps reproduce the compare stage's union masks there,
    :func:`choose_threshold`). Logs it and writes ``path`` (JSON: the threshold, how it was
    chosen, the key-view F1 at it and at 0.5, the key-view best and the F1 curve)."""
    masks = [_load_mask(v.masks["union"], v.camera) > 0.5 for v in views]
    best = choose_threshold([m["prob"] for m in maps], masks)
    curve = best["curve"].set_index("threshold")["F1"]

    def f1_at(x):
        s = scores_from_counts(*np.sum([confusion(m["prob"] > x, k) for m, k in
                                        zip(maps, masks)], axis=0))
        return s["F1"]

    if opts.threshold is not None:
        th, source = float(opts.threshold), "fixed (partition.threshold)"
    else:
        th, source = operating_point(best["threshold"], best["f1"], f1_at(0.5),
                                     opts.threshold_gain)

    info = {"threshold": th, "source": source, "key_view_f1": f1_at(th),
            "key_view_f1_at_0.5": f1_at(0.5), "key_view_best_threshold": best["threshold"],
            "key_view_best_f1": best["f1"],
            "curve": [{"threshold": float(t), "f1": float(f)} for t, f in curve.items()]}
    write_json(path, info)
    log.info("partition threshold %.2f: %s; key-view F1 %.3f (at 0.5: %.3f)", th, source,
             info["key_view_f1"], info["key_view_f1_at_0.5"])
    return th


def _sha1(path) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
