"""Options of the poses stage (config section ``poses``)."""

from __future__ import annotations

from dataclasses import dataclass


MATCHERS = ("auto", "exhaustive", "retrieval", "sequential")
CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
TURN_BASELINES = ("given", "refined")


@dataclass
class PosesOptions:
    """Options of the poses stage (config section ``poses``).

    Attributes:
        source: ``auto`` (known poses if the scene has cameras.json / transforms.json, else
            COLMAP), ``colmap`` or ``known``.
        matcher: ``auto`` (``exhaustive`` up to ``exhaustive_max_images`` images, else
            ``retrieval``), ``exhaustive`` (all pairs: cost grows with the square of the image
            count), ``retrieval`` (each image with its ``retrieval_neighbours`` most similar
            images by a bag of visual words learnt from the scene's own features, shared
            evenly among the sets so that every image has partners in the other visit, plus
            its ``sequential_overlap`` capture-order neighbours; no pre-trained vocabulary) or
            ``sequential`` (capture-order neighbours within each set + evenly spaced links
            between all images).
        exhaustive_max_images: image count up to which ``auto`` matches all pairs (beyond it
            the pair count grows linearly); None (the default) = while all pairs are no more
            than retrieval would match (``2 * (retrieval_neighbours + sequential_overlap) + 1``
            images), so the cost of matching never grows faster than the image count. A
            number above that buys all pairs for larger sets, quadratic in the image count.
            With known poses, larger sets are matched by camera proximity instead.
        retrieval_neighbours: most similar images each image is matched with (``retrieval``),
            the same number from each set (at least one).
        sequential_overlap: capture-order neighbours matched on each side (``sequential``,
            ``retrieval``).
        sequential_links: evenly spaced images of every set each image is also matched with.
        camera_model: COLMAP camera model: ``PINHOLE`` (fx, fy, cx, cy), ``SIMPLE_PINHOLE``
            (one focal length), or a model with lens distortion estimated by COLMAP:
            ``SIMPLE_RADIAL`` (f, k1), ``RADIAL`` (f, k1, k2) or ``OPENCV`` (fx, fy, k1, k2, p1,
            p2); with those the photos are undistorted once (into ``poses/images/``) and
            every later stage uses the undistorted photos and pinhole cameras. Known poses
            take their distortion from cameras.json / transforms.json instead.
        max_image_size: longer image side for feature extraction (larger images are
            downscaled for SIFT; poses and intrinsics stay in full-resolution pixels).
        resample_max_side: photos from different cameras (sizes, aspect ratios, focal
            lengths differ) are resampled once into ``poses/images/`` to one common pinhole
            camera: the field of view all photos cover at the pixel density of the finest
            photo, its longer side capped at this many pixels (0 = no cap). Later stages work
            at ``fit.max_side`` anyway; a cap near it saves disk and reading time.
        max_num_features: SIFT features per image.
        domain_size_pooling: DSP-SIFT descriptors (pooled over several patch sizes): more
            distinctive under lighting change and on small images, fewer false matches; about
            5x slower feature extraction (matching often gets faster).
        min_num_matches: verified matches needed for an image pair to count in mapping.
        max_reproj_error: reprojection error (pixels of the feature-extraction image) above
            which an observation is an outlier: used by the mapper (triangulation, filtering;
            camera registration allows 3x, two-view RANSAC 2x) and by the final refinement.
            COLMAP's default of 4 px is meant for megapixel photos; on small images it lets
            false matches (e.g. on moving shadow edges) bias the focal length and rotations.
        refine_iterations: rounds of the final global refinement (bundle adjustment of all
            cameras, shared intrinsics and points with a Cauchy loss, then removal of
            observations beyond ``max_reproj_error``); 0 keeps the mapper's model as is.
        map_max_images: scenes with more images than this map a core of this many, spread
            evenly over each set's capture order, and register each other image to that model
            on its own (absolute pose + refinement of that pose): incremental mapping costs
            more than linearly in the image count (every point is seen by more images as views
            get denser), registration per image does not. None maps all images.
        mapper_attempts: incremental mapping runs tried while the best model so far leaves
            images unregistered. Run k (from 0) uses seed ``seed + k`` and mapper thresholds
            ``(k + 1) * max_reproj_error``: a strict threshold keeps mapping accurate, a looser
            one can register weakly connected images (the final refinement then removes the
            outliers at ``max_reproj_error``). The model with the most registered images, then
            the lowest reprojection error, is kept.
        refine_principal_point: let bundle adjustment move the principal point (off = keep it
            at the image centre, COLMAP's default).
        min_points_per_image: when triangulation leaves fewer sparse points than this per
            registered image (known poses on few, weakly textured or imprecisely posed
            photos), ``seed_points_per_image`` points per image are added to the initial point
            cloud (``points.ply``; not to the COLMAP model) in the camera frusta: random pixel
            rays, depths within the scene's range, colours from the photos (see
            ``gdiff.sfm.seed``), so a fit never starts from a handful of Gaussians.
            0 = never seed.
        seed_points_per_image: points seeded per image when seeding (see above).
        seed_cells: otherwise the parts of each photo that no triangulated point projects
            into (cells of a grid with this many cells along the image's longer side) are
            seeded the same way, ``seed_points_per_image`` x their share of the cells per
            image: a sparse capture of weakly textured surfaces triangulates points on a few
            textured spots only, and a fit does not grow Gaussians from there over the rest.
            0 = only the whole-frustum seeding above.
        seed_min_empty: ... when the empty cells are at least this share of all the photos'
            cells (a dense capture leaves a few per cent empty, which the fit's densification
            fills from the neighbouring points; points seeded there at random depths are
            floaters).
        seed_sweep_extra: a seeded point takes its depth from a plane sweep of the photos
            where they agree on one (a textured patch seen from elsewhere), else a random
            depth; per seeded point this many more pixels are drawn and swept, and those the
            sweep places are added, so textured surfaces get denser seeds where they stand.
            0 = only the ``seed_points_per_image`` points.
        refine_known: known poses (cameras.json / transforms.json) are refined by bundle
            adjustment of the matched features before anything uses them, and mapped back
            into their own frame and scale (:mod:`gdiff.sfm.refine_known`). A robot's poses
            are off by a degree or two, 10-30 px on its photos: the visits would disagree by
            that much, and the comparison would take the shift for change. Images that fewer
            than ``min_num_matches`` points tie to the others are turned to agree with a photo
            from the same place, or take the refined images' common correction
            (:mod:`gdiff.sfm.refine_known`). Off =
            the poses are used as given (exact poses of a rendered scene, a motion-capture
            rig).
        turn_baseline: how an image that no triangulated points tie to the others is turned to
            agree with a photo from the same place (:func:`gdiff.sfm.refine_known.best_turn`):
            ``refined`` (default) fits the baseline's direction with the turn (its length and
            the given centre kept) and gives the turn the photos show; ``given`` fits the turn
            with the given baseline between the two held, where centres a few centimetres off
            let the turn slide degrees off along the epipolar lines (see design.md).
        known_max_error: how far off the given poses may be, as a reprojection error in
            fractions of the longer image side: the first triangulation accepts this much,
            then the threshold halves each round of the refinement down to
            ``max_reproj_error``.
        max_unregistered_fraction: if a set (before, after, eval_before, eval_after) loses more
            than this fraction of its images, the stage fails listing them; otherwise they are
            dropped with a warning.
        num_threads: CPU threads (-1 = all) for COLMAP's matching (worker processes when
            ``repeatable``, see :mod:`gdiff.sfm.match`) and verification always, and for its
            other steps when ``repeatable`` is off.
        repeatable: run COLMAP's feature extraction, mapping and bundle adjustment on one
            thread, and its matching in ``num_threads`` worker processes on one thread each,
            so two runs on the same photos give byte-identical poses and points. With several
            threads the extraction order decides COLMAP's image ids, the order of sums in
            mapping moves the solution slightly, and matchers running at once in one process
            now and then lose a pair's matches; the fit then grows such differences.
            Verification runs on ``num_threads`` either way: each pair's RANSAC is seeded with
            ``seed``, so with the image ids fixed its result does not depend on the thread that
            verifies it. Off = every step on ``num_threads`` threads.
        seed: random seed of COLMAP's RANSAC and mapper (for repeatable runs).
        colmap_log: let COLMAP write its own INFO log lines to stderr.
    """

    source: str = "auto"
    matcher: str = "auto"
    exhaustive_max_images: int | None = None
    retrieval_neighbours: int = 20
    sequential_overlap: int = 8
    sequential_links: int = 6
    camera_model: str = "PINHOLE"
    max_image_size: int = 1600
    resample_max_side: int = 1600
    max_num_features: int = 8192
    domain_size_pooling: bool = False
    min_num_matches: int = 15
    max_reproj_error: float = 2.0
    refine_iterations: int = 3
    map_max_images: int | None = 80
    mapper_attempts: int = 3
    refine_principal_point: bool = False
    min_points_per_image: int = 10
    seed_points_per_image: int = 1000
    seed_cells: int = 16
    seed_min_empty: float = 0.5
    seed_sweep_extra: int = 3
    refine_known: bool = True
    turn_baseline: str = "refined"
    known_max_error: float = 0.03
    max_unregistered_fraction: float = 0.2
    num_threads: int = -1
    repeatable: bool = True
    seed: int = 0
    colmap_log: bool = False

    def __post_init__(self):
        if self.source not in ("auto", "colmap", "known"):
            raise ValueError(f"source must be auto, colmap or known, not {self.source!r}")
        if self.matcher not in MATCHERS:
            raise ValueError(f"matcher must be one of {', '.join(MATCHERS)}, not "
                             f"{self.matcher!r}")
        if self.retrieval_neighbours < 1:
            raise ValueError("retrieval_neighbours must be >= 1")
        if self.camera_model not in CAMERA_MODELS:
            raise ValueError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}, not "
                             f"{self.camera_model!r}")
        if not 0.0 <= self.max_unregistered_fraction <= 1.0:
            raise ValueError("max_unregistered_fraction must lie in [0, 1]")
        if self.sequential_overlap < 1 or self.sequential_links < 0:
            raise ValueError("sequential_overlap must be >= 1 and sequential_links >= 0")
        if not self.max_reproj_error > 0:
            raise ValueError("max_reproj_error must be > 0 (pixels)")
        if self.seed_cells < 0 or not 0.0 <= self.seed_min_empty <= 1.0:
            raise ValueError("seed_cells must be >= 0 and seed_min_empty in [0, 1]")
        if self.seed_sweep_extra < 0:
            raise ValueError("seed_sweep_extra must be >= 0")
        if self.min_points_per_image < 0 or self.seed_points_per_image < 1:
            raise ValueError("min_points_per_image must be >= 0 and seed_points_per_image "
                             ">= 1")
        if self.resample_max_side < 0:
            raise ValueError("resample_max_side must be >= 0 (pixels; 0 = no cap)")
        if self.map_max_images is not None and self.map_max_images < 10:
            raise ValueError("map_max_images must be >= 10 (or null: map all images)")
        if self.turn_baseline not in TURN_BASELINES:
            raise ValueError(f"turn_baseline must be one of {', '.join(TURN_BASELINES)}, not "
                             f"{self.turn_baseline!r}")
        if not 0.0 < self.known_max_error <= 0.5:
            raise ValueError("known_max_error must lie in (0, 0.5] (fraction of the longer "
                             "image side)")
        if self.refine_iterations < 0 or self.mapper_attempts < 1:
            raise ValueError("refine_iterations must be >= 0 and mapper_attempts >= 1")

    def colmap_threads(self) -> int:
        """Threads for COLMAP's extraction, mapping and bundle adjustment: 1 when
        ``repeatable`` (their results depend on the threads' order), else ``num_threads``."""
        return 1 if self.repeatable else self.num_threads

    def exhaustive_limit(self) -> int:
        """Image count up to which ``matcher: auto`` matches all pairs."""
        if self.exhaustive_max_images is not None:
            return self.exhaustive_max_images
        return 2 * (self.retrieval_neighbours + self.sequential_overlap) + 1
