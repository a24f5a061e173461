"""Scene folders: discovery, validation, manifest.

A scene folder holds::

    before/*.png|jpg            images before the change (t = 0), at least 3
    after/*.png|jpg             images after the change (t = 1), at least 3
    eval/before/NAME, eval/after/NAME, eval/masks/NAME
                                optional evaluation views with ground-truth change masks
                                (255 = changed), matched by file stem; every view needs its mask
                                and at least one of its before/after images (a missing one is
                                rendered from the model at evaluation)
    eval/boxes.json             optional box ground truth (see gdiff.evaluate), also for
                                training images: a scene may have it as its only eval/ file
    cameras.json | transforms.json
                                optional known poses (else COLMAP registers the images)

Images may come from different cameras (sizes, aspect ratios, focal lengths may differ between
and within the sets; the poses stage resamples them to one common camera) and may carry an
EXIF orientation tag (read upright everywhere). An eval mask has the size of its eval image.

Instead of the photos of ``before/`` or ``after/``, a set may be a video: ``before.mp4`` (any
of :data:`gdiff.video.VIDEO_EXTENSIONS`) or one video inside ``before/``. The manifest stage
(:func:`write_manifest`) turns it into photos under ``results/<scene>/input/images/`` (see
:mod:`gdiff.video`).

The ``scenes`` config key names what to run on (see :func:`discover_scenes`):

* ``synth:<preset>`` — a built-in synthetic scene that the workflow generates itself
  (default ``synth:demo``) with the config's ``synth_seed``, named ``<preset>``;
  ``synth:<preset>:<seed>`` the same scene drawn with its own seed, named
  ``<preset>_s<seed>`` (so one run can hold several seeds of a preset);
* a scene folder (has ``before/`` and ``after/``);
* a folder of scene folders;
* a TSV/CSV sheet with columns ``name``, ``path`` and optional per-scene overrides: extra
  columns named ``<section>.<key>`` (e.g. ``fit.max_side``, ``poses.source``) whose cells
  (YAML scalars) override the config for that scene; empty cells keep the default.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import jsonschema
import numpy as np
import yaml

from .config import sections as config_sections
from .errors import ConfigError, SceneError
from .io import IMAGE_EXTENSIONS, IMREAD_UPRIGHT, link_or_copy, read_json, write_json
from .video import InputOptions, extract_frames, find_video, is_video, video_info

MIN_IMAGES = 3
SCENE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
SYNTH_PREFIX = "synth:"


@dataclass
class SceneSpec:
    """One scene to run: a name (results/<name>/), where its folder is, per-scene overrides."""

    name: str
    path: Path
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    synth_preset: str | None = None  # set when the workflow generates the scene itself
    synth_seed: int | None = None  # its own seed (None: the config's synth_seed)

    @property
    def has_eval(self) -> bool:
        """Whether the scene has evaluation pairs (synth scenes always do)."""
        return self.synth_preset is not None or (self.path / "eval").is_dir()


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder`` (png/jpg), sorted by name; hidden files skipped."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix in IMAGE_EXTENSIONS and not p.name.startswith("."))


def is_scene_folder(path: Path) -> bool:
    """Whether ``path`` has a before and an after set (a folder, or a video per set)."""
    def has(set_name):
        return (path / set_name).is_dir() or any(is_video(p) for p in path.glob(f"{set_name}.*"))

    return has("before") and has("after")


def _check_name(name: str, where: str) -> str:
    if not SCENE_NAME.match(name):
        raise ConfigError(f"{where}: scene name {name!r} may contain only letters, digits, '.', "
                          "'_' and '-' (it becomes the folder results/<name>/)")
    return name


def discover_scenes(spec: str | Path, synth_root: str | Path = "resources/synth",
                    base: str | Path = ".") -> dict[str, SceneSpec]:
    """Resolve the ``scenes`` config value into scenes, keyed by name (see module docstring).

    Relative paths are taken relative to ``base`` (for a sheet: relative to the sheet's folder).
    Raises :class:`ConfigError` with the offending value when nothing usable is found.
    """
    spec = str(spec).strip()
    if spec.startswith(SYNTH_PREFIX):
        preset, seed = parse_synth(spec, "config key 'scenes'")
        name = synth_folder_name(preset, seed)
        return {name: SceneSpec(name, Path(synth_root) / name, synth_preset=preset,
                                synth_seed=seed)}
    path = Path(spec)
    if not path.is_absolute():
        path = Path(base) / path
    if not path.exists():
        raise ConfigError(f"config key 'scenes': {spec} does not exist; give a scene folder "
                          "(with before/ and after/), a folder of scene folders, a .tsv sheet, "
                          "or synth:demo")
    if path.is_file():
        return read_scene_sheet(path)
    if is_scene_folder(path):
        name = _check_name(path.resolve().name, f"scene folder {path}")
        return {name: SceneSpec(name, path)}
    scenes = {}
    for sub in sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if is_scene_folder(sub):
            name = _check_name(sub.name, f"scene folder {sub}")
            scenes[name] = SceneSpec(name, sub)
    if not scenes:
        raise ConfigError(f"config key 'scenes': {path} is neither a scene folder (no before/ and "
                          "after/ inside) nor a folder of scene folders (no sub-folder has both)")
    return scenes


def parse_synth(spec: str, where: str) -> tuple[str, int | None]:
    """``synth:<preset>`` -> ``(preset, None)``; ``synth:<preset>:<seed>`` -> ``(preset, seed)``."""
    body = spec.strip()[len(SYNTH_PREFIX):]
    preset, _, seed = body.partition(":")
    _check_name(preset, where)
    if not _:
        return preset, None
    try:
        value = int(seed)
    except ValueError:
        value = -1
    if value < 0:
        raise ConfigError(f"{where}: {spec!r}: the seed after '{SYNTH_PREFIX}{preset}:' must be a "
                          "whole number >= 0 (e.g. synth:demo:1)")
    return preset, value


def synth_folder_name(preset: str, seed: int | None) -> str:
    """Scene name and folder (under the synth root) of a synthetic scene: ``<preset>``, or
    ``<preset>_s<seed>`` when it has its own seed."""
    return preset if seed is None else f"{preset}_s{seed}"


def read_scene_sheet(path: str | Path) -> dict[str, SceneSpec]:
    """Read a scenes sheet (TSV, or CSV by extension): ``name``, ``path``, ``section.key`` overrides.

    Every problem names the sheet, the row (1 = first data row) and the column.
    """
    import pandas as pd

    path = Path(path)
    sep = "," if path.suffix.lower() == ".csv" else "\t"
    try:
        df = pd.read_csv(path, sep=sep, dtype=str, keep_default_na=False, comment="#")
    except Exception as e:  # pandas raises several parser errors
        raise ConfigError(f"scenes sheet {path}: cannot be parsed as "
                          f"{'CSV' if sep == ',' else 'TSV'} ({e})") from None
    df.columns = [c.strip() for c in df.columns]
    missing = [c for c in ("name", "path") if c not in df.columns]
    if missing:
        raise ConfigError(f"scenes sheet {path}: missing column(s) {', '.join(missing)}; the "
                          "header needs 'name' and 'path' (tab-separated), then optional "
                          "'<section>.<key>' override columns")
    override_cols = [c for c in df.columns if c not in ("name", "path")]
    for c in override_cols:
        if c.count(".") != 1:
            raise ConfigError(f"scenes sheet {path}: column {c!r} is not of the form "
                              "'<section>.<key>' (e.g. fit.max_side)")
    scenes: dict[str, SceneSpec] = {}
    for i, row in enumerate(df.itertuples(index=False), start=1):
        row = dict(zip(df.columns, row))
        name, p = row["name"].strip(), row["path"].strip()
        where = f"scenes sheet {path}, row {i}"
        if not name or not p:
            raise ConfigError(f"{where}: 'name' and 'path' must both be filled in")
        _check_name(name, where)
        if name in scenes:
            raise ConfigError(f"{where}: scene name {name!r} appears twice")
        seed = None
        if p.startswith(SYNTH_PREFIX):
            spec = next(iter(discover_scenes(p).values()))
            scene_path, preset, seed = spec.path, spec.synth_preset, spec.synth_seed
        else:
            scene_path = Path(p) if Path(p).is_absolute() else path.parent / p
            preset = None
            if not is_scene_folder(scene_path):
                raise ConfigError(f"{where}: path {p} is not a scene folder (needs before/ and "
                                  "after/ inside)")
        overrides: dict[str, dict[str, Any]] = {}
        for c in override_cols:
            cell = row[c].strip()
            if cell == "":
                continue
            section, key = c.split(".")
            try:
                overrides.setdefault(section, {})[key] = yaml.safe_load(cell)
            except yaml.YAMLError:
                raise ConfigError(f"{where}, column {c}: cannot read value {cell!r}") from None
        scenes[name] = SceneSpec(name, scene_path, overrides, synth_preset=preset,
                                 synth_seed=seed)
    if not scenes:
        raise ConfigError(f"scenes sheet {path}: no rows")
    return scenes


def check_overrides(scenes: dict[str, SceneSpec], schema: dict) -> None:
    """Raise :class:`ConfigError` when a scene's sheet overrides a key the configuration does
    not have: ``schema`` is the workflow's config schema (``workflow/schemas/config.schema.yaml``
    as a dict); a sheet column ``<section>.<key>`` must name a section with keys there and one
    of its keys (an unknown column would otherwise be read and never used), and its cells must
    be values the schema allows for that key (type, range)."""
    known = config_sections(schema)
    for name, spec in scenes.items():
        for section, values in spec.overrides.items():
            where = f"scenes sheet, scene {name!r}, column '{section}.{next(iter(values))}'"
            if section not in known:
                raise ConfigError(f"{where}: '{section}' is not a configuration section a sheet "
                                  f"can override (sections: {', '.join(sorted(known))}; see "
                                  "config/config.yaml). A synthetic scene's size and views are "
                                  "its preset's (synth:<preset>[:<seed>]); for others make its "
                                  "folder with `gdiff synth --preset P --seed S --n-before N "
                                  "--n-after N DIR` and give DIR as the path")
            keys = known[section]
            for key, value in values.items():
                where = f"scenes sheet, scene {name!r}, column '{section}.{key}'"
                if key not in keys:
                    raise ConfigError(f"{where}: '{section}' has no key '{key}' (its keys: "
                                      f"{', '.join(sorted(keys))})")
                try:
                    jsonschema.validate(value, keys[key])
                except jsonschema.ValidationError as e:
                    raise ConfigError(f"{where}: {e.message}; write it as in "
                                      "config/config.yaml") from None


def _size_and_sha1(path: Path) -> tuple[int, int, str]:
    """(width, height, sha1) of an image, read once and decoded fully so corrupt files are
    caught here; the size is that of the upright image (EXIF orientation applied, as every
    stage reads it, see :data:`gdiff.io.IMREAD_UPRIGHT`)."""
    data = path.read_bytes()
    img = cv2.imdecode(np.frombuffer(data, np.uint8), IMREAD_UPRIGHT)
    if img is None:
        raise SceneError(f"{path}: cannot be decoded as an image (corrupt, truncated or not an "
                         "image); replace or remove the file")
    return int(img.shape[1]), int(img.shape[0]), hashlib.sha1(data).hexdigest()


def validate_scene(scene_dir: str | Path) -> dict:
    """Check a scene folder and return its manifest (see module docstring for the rules).

    Manifest: ``{"scene": path, "width", "height", "sizes", "images": [{"path": rel, "set":
    before|after|eval_before|eval_after|eval_mask, "width", "height", "sha1"}], "eval_views":
    [stems]}``. Image sizes are those of the images as displayed (EXIF orientation applied) and
    may differ between images (photos from different cameras; the poses stage resamples them
    to one camera); ``sizes`` lists the distinct ``[width, height]`` in order of appearance and
    the top-level ``width``/``height`` are the shared size, or null when sizes differ.
    Raises :class:`SceneError` naming the folder or file and the fix.
    """
    root = Path(scene_dir)
    if not root.is_dir():
        raise SceneError(f"scene folder {root} does not exist")
    images: list[dict] = []
    sets = {"before": root / "before", "after": root / "after"}
    for name, folder in sets.items():
        video = find_video(root, name)
        if video is not None:
            info = video_info(video)
            images.append({"path": str(video.relative_to(root)), "set": name, "video": True,
                           "frames": info["frames"], "width": info["width"],
                           "height": info["height"]})
            continue
        if not folder.is_dir():
            raise SceneError(f"{root}: missing folder {name}/ (put the images taken "
                             f"{'before' if name == 'before' else 'after'} the change there)")
        files = list_images(folder)
        if not files:
            raise SceneError(f"{folder}: no images (.png/.jpg) found")
        if len(files) < MIN_IMAGES:
            raise SceneError(f"{folder}: only {len(files)} image(s); at least {MIN_IMAGES} are "
                             "needed to register and fit a scene (more overlapping views give "
                             "better results)")
        images += [{"path": str(p.relative_to(root)), "set": name} for p in files]
    eval_views: list[str] = []
    ev = root / "eval"
    if ev.is_dir():
        parts = {k: {p.stem: p for p in list_images(ev / k)} for k in ("before", "after", "masks")}
        stems = set(parts["before"]) | set(parts["after"])
        if not stems and not (ev / "boxes.json").is_file():
            raise SceneError(f"{ev}: folder exists but eval/before/ and eval/after/ hold no "
                             "images (and there is no eval/boxes.json); remove eval/ or add the "
                             "evaluation pairs")
        for stem in sorted(stems):
            if stem not in parts["masks"]:
                have = [k for k in ("before", "after") if stem in parts[k]]
                raise SceneError(f"{ev}: eval view '{stem}' has {' and '.join(have)} but no "
                                 f"eval/masks/{stem}.* ; every eval view needs its ground-truth "
                                 "change mask (255 = changed) with the same name")
            # One-sided views (only eval/after, as in 3DGS-CD or PASLCD) are allowed: the
            # evaluation renders the missing time from the fitted model.
            for k, st in (("before", "eval_before"), ("after", "eval_after")):
                if stem in parts[k]:
                    images.append({"path": str(parts[k][stem].relative_to(root)), "set": st})
            images.append({"path": str(parts["masks"][stem].relative_to(root)),
                           "set": "eval_mask"})
            eval_views.append(stem)
        extra = set(parts["masks"]) - stems
        if extra:
            raise SceneError(f"{ev / 'masks'}: mask(s) {', '.join(sorted(extra))} have no "
                             "eval/before and eval/after images")
        if (ev / "boxes.json").is_file():  # now, not when evaluate reads it at the end
            from .evaluate import check_boxes

            check_boxes(ev / "boxes.json", root, stems)
    for rec in images:
        if rec.get("video"):
            w, h = rec["width"], rec["height"]
            sha1 = hashlib.sha1((root / rec["path"]).read_bytes()).hexdigest()
        else:
            w, h, sha1 = _size_and_sha1(root / rec["path"])
        rec["width"], rec["height"], rec["sha1"] = w, h, sha1
    _check_eval_mask_sizes(root, images)
    sizes = list(dict.fromkeys((r["width"], r["height"]) for r in images))
    one = sizes[0] if len(sizes) == 1 else (None, None)
    return {"scene": str(root.resolve()), "width": one[0], "height": one[1],
            "sizes": [list(s) for s in sizes], "images": images, "eval_views": eval_views}


def _check_eval_mask_sizes(root: Path, images: list[dict]) -> None:
    """Every eval mask has the size of its view's eval/after image or of its eval/before
    image (the poses stage resamples it with the camera of that image)."""
    by_stem: dict[str, dict[str, dict]] = {}
    for rec in images:
        if rec["set"] in ("eval_before", "eval_after", "eval_mask"):
            by_stem.setdefault(Path(rec["path"]).stem, {})[rec["set"]] = rec
    for stem, recs in by_stem.items():
        mask = recs["eval_mask"]
        shown = {(r["width"], r["height"]): r["path"] for k, r in recs.items() if k != "eval_mask"}
        if (mask["width"], mask["height"]) not in shown:
            have = ", ".join(f"{p} is {w}x{h}" for (w, h), p in shown.items())
            raise SceneError(f"{root / mask['path']}: mask is {mask['width']}x{mask['height']} "
                             f"but {have}; a ground-truth mask must have the size of its eval "
                             "image (as displayed, EXIF orientation applied): resize the mask "
                             "to it")


IMAGES_DIR = "images"  # beside the manifest: the scene's images when a set is a video


def write_manifest(scene_dir: str | Path, out_path: str | Path, options=None) -> dict:
    """Validate ``scene_dir`` and write its manifest JSON atomically; returns the manifest.

    When a set is a video (``options``: :class:`gdiff.video.InputOptions`), its frames are
    picked and written to ``<manifest folder>/images/<set>/`` and every photo of the scene is
    linked (or copied) beside them, so that one folder holds all the scene's images; the
    manifest then lists the frames like photos and names that folder in ``image_root``
    (relative to the manifest). Without videos the manifest lists the scene's own files.
    """
    options = options or InputOptions()
    manifest = validate_scene(scene_dir)
    if any(r.get("video") for r in manifest["images"]):
        root, out_root = Path(scene_dir), Path(out_path).parent / IMAGES_DIR
        images = []
        for rec in manifest["images"]:
            if rec.get("video"):
                names = extract_frames(root / rec["path"], out_root / rec["set"],
                                       options.video_frames)
                for n in names:
                    images.append({"path": f"{rec['set']}/{n}", "set": rec["set"],
                                   "width": rec["width"], "height": rec["height"],
                                   "video": rec["path"]})
            else:
                if not rec["set"].startswith("eval"):  # eval/ is linked whole below
                    link_or_copy(root / rec["path"], out_root / rec["path"])
                images.append(rec)
        if (root / "eval").is_dir():  # eval images, masks and any other ground truth
            for f in sorted((root / "eval").rglob("*")):
                if f.is_file():
                    link_or_copy(f, out_root / f.relative_to(root))
        manifest["images"] = images
        manifest["image_root"] = IMAGES_DIR
    write_json(out_path, manifest)
    return manifest


def manifest_image_root(manifest_path: str | Path, scene_dir: str | Path) -> Path:
    """The folder the images listed in a manifest are relative to (``image_root``, else the
    scene folder)."""
    data = read_json(manifest_path)
    if data.get("image_root"):
        return Path(manifest_path).parent / data["image_root"]
    return Path(scene_dir)
