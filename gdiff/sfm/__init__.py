"""Poses stage: register every image of a scene (before, after, eval) in one frame.

Two sources of poses:

* ``colmap`` — SIFT features, matching and incremental mapping with pycolmap. Images of one
  size share one pinhole camera. Matching is exhaustive for small image sets; for
  large ones each image is matched with its most similar images by a bag of visual words
  learnt from the scene's own SIFT features (k-means, tf-idf; no vocabulary file to download)
  and with its capture-order neighbours, so the number of pairs grows linearly with the
  images. A ``sequential`` pair list (capture-order neighbours plus evenly spaced links into
  every set) is available too.
  Outlier thresholds are ``max_reproj_error`` pixels of the feature-extraction image (COLMAP's
  4 px defaults suit megapixel photos; on 320 px images false matches, e.g. on shadow edges
  that move between before and after, then survive and pull the focal length and rotations).
  Mapping is retried with further seeds and looser thresholds while images stay
  unregistered, and the kept model gets a final global refinement: bundle adjustment of all
  cameras, the shared intrinsics and points under a Cauchy loss, alternated with removal of
  observations beyond the threshold.
* ``known`` — ``cameras.json`` (gdiff layout, or the ground-truth layout with an
  ``intrinsics`` block) or a nerfstudio / instant-ngp ``transforms.json`` in the scene folder.
  Sparse points are triangulated with pycolmap from features matched between the images
  (pose-proximity pairs for large sets), and the poses are refined with them by bundle
  adjustment (:mod:`gdiff.sfm.refine_known`; ``refine_known: false`` keeps them as given).
  Lens distortion given in the file (OpenCV k1, k2, p1, p2[, k3]) is removed first: the photos
  are undistorted once (:mod:`gdiff.sfm.undistort`) and later stages read them from
  ``images/``.

With ``camera_model`` OPENCV / RADIAL / SIMPLE_RADIAL, COLMAP estimates the distortion and the
photos are undistorted the same way.

Photos from different cameras: COLMAP gives each image size one camera (known poses may give
per-frame intrinsics); when the registered cameras do not share one size, intrinsics and
distortion, every photo is resampled once to one common pinhole camera
(:mod:`gdiff.sfm.resample`; distortion removed in the same step) into ``images/``, and the
sparse model follows. Photos with an EXIF orientation tag are given to COLMAP as upright copies
(:mod:`gdiff.sfm.upright`: pycolmap ignores the tag; every gdiff stage reads photos upright);
without further resampling those copies are the ``images/`` of later stages. When triangulation leaves fewer than
``min_points_per_image`` points per image, points seeded in the camera frusta
(:mod:`gdiff.sfm.seed`) are added to ``points.ply`` so a fit never starts from a handful;
otherwise the parts of each photo that no point projects into (``seed_cells``) are seeded
so, so a fit has Gaussians everywhere a photo shows something.

Outputs in ``out_dir`` (written in a temporary folder inside ``out_dir`` and moved in at the
end; ``cameras.json`` last, so its presence means the stage finished):

* ``sparse/0/`` — the COLMAP binary model (cameras, images, points3D),
* ``images/`` — undistorted, resampled or upright photos (and eval masks) under their
  scene-relative paths (only when a camera had distortion, the cameras differed or a photo had
  an EXIF orientation tag; ``cameras.json`` then has ``"image_dir": "images"``),
* ``points.ply`` — sparse points (and seeded ones, see above), binary little-endian ``x y z`` float32 +
  ``red green blue`` uint8,
* ``cameras.json`` — see :mod:`gdiff.cameras` (c2w in OpenCV axes, pixel centres at +0.5,
  which is also COLMAP's convention).
"""

from .colmap import extraction_scale, refine_model
from .images import SET_FOLDERS, discover_images, set_from_path
from .known import load_known_cameras, read_cameras_file
from .options import PosesOptions
from .pairs import proximity_pairs, retrieval_pairs, sequential_pairs, word_histograms
from .run import run_poses

__all__ = ["PosesOptions", "SET_FOLDERS", "discover_images", "extraction_scale",
           "load_known_cameras", "proximity_pairs", "read_cameras_file", "refine_model",
           "retrieval_pairs", "run_poses", "sequential_pairs", "set_from_path",
           "word_histograms"]
