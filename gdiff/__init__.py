"""gdiff: 3D instance-level change detection with 4D Gaussian splatting (Gaussian Difference).

Conventions used everywhere in the package (see docs/design.md):

* Cameras: OpenCV axes (x right, y down, z forward). ``c2w`` is a 4x4 camera-to-world matrix,
  ``w2c`` / ``viewmat`` its inverse (world-to-camera). Pixel (col i, row j) has its centre at
  (i + 0.5, j + 0.5) in the intrinsics' pixel coordinates (COLMAP / NeRF convention).
* Time: ``t`` in [0, 1]; the "before" images are t = 0 and the "after" images t = 1.
* Images: float32 in [0, 1], shape [H, W, 3] (numpy or torch). The radiance model is fitted to
  the sRGB-encoded values of the photos (as 3DGS does, so PLY colours look right in viewers);
  EXR exports convert to linear.
"""

import os as _os

# Intel MKL (torch's CPU BLAS) splits a matrix product's sums over its threads in a way that
# depends on the CPU and the thread count, so the deformation MLP's weight gradients (sums over
# every Gaussian) came out differently on one thread and on two. MKL's strict reproducibility
# mode (``MKL_CBWR=AUTO,STRICT``) sums ?gemm in an order no thread count changes. MKL reads the
# variable at its first call, so this takes effect when gdiff is imported before any matrix
# product has run (the workflow's scripts, the CLI and the tests do); a value the user set wins.
_os.environ.setdefault("MKL_CBWR", "AUTO,STRICT")

__version__ = "0.1.0"
