"""Gaussian splatting: the differentiable rasterizer (:mod:`gdiff.splat.rasterize`), spherical
harmonics (:mod:`gdiff.splat.sh`) and the compiled CPU kernel (:mod:`gdiff.splat.csrc`)."""
