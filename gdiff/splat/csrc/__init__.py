"""Compiled CPU kernels of gdiff.splat (C++ torch extension), built on first use.

:func:`load` compiles the kernels (``kernels.cpp``, which includes every ``*_cpu.cpp`` file
here) with the machine's C++ compiler through ``torch.utils.cpp_extension.load`` into torch's
extension cache (``TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``; one compiler
run; the operators are registered as ``torch.ops.gdiff_splat.*``). Each version of the sources
has its own build there (:func:`build_name`), which later processes reuse. If compilation
fails, ``load(required=False)`` logs one warning and returns None, and the rasterizer falls
back to the torch backend. Set ``GDIFF_NO_CPP=1`` to skip the kernel altogether.

The build also holds ``project_cpu.cpp`` (:func:`project_cpp`, the EWA projection of
:func:`gdiff.splat.rasterize.project_gaussians` with the 3D covariance, fused), ``sh_cpu.cpp``
(:func:`sh_to_color_cpp`, the colour of :func:`gdiff.splat.sh.sh_to_color`), the mirror
directions of :mod:`gdiff.splat.reflection` (:func:`reflect_cpp`, in ``project_cpu.cpp``) and
``hexplane_cpu.cpp`` (:func:`hexplane_sample`, the bilinear look-up of the deformation field's
feature planes, see :mod:`gdiff.splat.deform`). Each has a hand-written backward pass and is
tested against its torch reference.

:func:`rasterize_cpp` has the same contract as
:func:`gdiff.splat.rasterize.rasterize_torch` (it is tested against it) and a hand-written
backward pass.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import platform
import threading
from pathlib import Path

import torch

from ...errors import GdiffError

log = logging.getLogger("gdiff.splat.csrc")

TILE_SIZE = 16
_SRC = Path(__file__).with_name("rasterize_cpu.cpp")
_UNIT = Path(__file__).with_name("kernels.cpp")  # includes the files below: one compiler run
_SOURCES = [_SRC] + [Path(__file__).with_name(f) for f in
                     ("project_cpu.cpp", "sh_cpu.cpp", "hexplane_cpu.cpp", "normalize.h")]
_lock = threading.Lock()
_module = None
_failed: str | None = None


STALE_LOCK_SECONDS = 600  # a build takes well under a minute; an older lock was left by a kill


def clear_stale_lock(build_dir: str | os.PathLike, max_age: float = STALE_LOCK_SECONDS) -> bool:
    """Remove ``build_dir/lock`` when it is older than ``max_age`` seconds.

    torch's extension builder holds that file while compiling and waits, without a time limit,
    for another process's lock to go away; a process killed mid-build (Ctrl-C, a killed
    Snakemake job) leaves it behind, and every later run would then wait forever. Returns
    whether a lock was removed (logged as a warning).
    """
    import time

    lock = Path(build_dir) / "lock"
    try:
        age = time.time() - lock.stat().st_mtime
    except FileNotFoundError:
        return False
    if age <= max_age:
        return False
    lock.unlink(missing_ok=True)
    log.warning("removed a stale build lock %s (%.0f s old, left by an interrupted build)",
                lock, max(age, 0.0))
    return True


GUARD_NAME = "gdiff-build.lock"  # gdiff's own lock file, beside torch's ``lock``


@contextlib.contextmanager
def build_guard(build_dir: str | os.PathLike):
    """Hold gdiff's lock on the extension's build folder while torch builds or loads it.

    torch's builder marks a build in progress by the file ``build_dir/lock`` and waits, without
    a time limit, while it exists; a process killed mid-build leaves it behind. gdiff's lock is
    an OS file lock (``flock``) on ``build_dir/gdiff-build.lock``, which the OS releases when
    its holder exits in any way. Every gdiff process builds or loads only while holding it, so
    a ``lock`` found while holding it was left by a process that died: it is removed at once
    (logged as a warning), and a run started right after a killed one does not hang. Waiting
    for another live process's build is logged. Without ``fcntl`` (not POSIX) the lock is
    removed only once older than :data:`STALE_LOCK_SECONDS` (:func:`clear_stale_lock`)."""
    build_dir = Path(build_dir)
    build_dir.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:
        clear_stale_lock(build_dir)
        yield
        return
    with open(build_dir / GUARD_NAME, "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("waiting for another process building the C++ kernels in %s", build_dir)
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            clear_stale_lock(build_dir, max_age=-1.0)
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def build_name() -> str:
    """Name of the build in torch's extension cache: machine type + a hash of all kernel
    sources (``kernels.cpp`` includes the others, which torch does not see). Each version of
    the sources has its own build, so two checkouts of different versions (a release and a
    development tree, tests of another commit) each reuse theirs instead of rebuilding over
    each other's on every start; an old version's build stays in the cache (a few MB) until
    the cache is cleared."""
    digest = hashlib.sha1(b"".join(p.read_bytes() for p in _SOURCES)).hexdigest()[:12]
    return f"gdiff_splat_cpu_{platform.machine()}_{digest}"


def load(required: bool = False, verbose: bool = False):
    """Build (first time) and import the extension module.

    Returns the operator namespace ``torch.ops.gdiff_splat``, or None when it cannot be built and ``required`` is False (a warning
    is logged once). With ``required=True`` a failure raises :class:`GdiffError`.
    """
    global _module, _failed
    with _lock:
        if _module is None and _failed is None:
            if os.environ.get("GDIFF_NO_CPP") == "1":
                _failed = "disabled by GDIFF_NO_CPP=1"
            else:
                try:
                    from torch.utils.cpp_extension import _get_build_directory
                    from torch.utils.cpp_extension import load as _load

                    name = build_name()
                    with build_guard(_get_build_directory(name, False)):
                        _load(name=name, sources=[str(_UNIT)], verbose=verbose,
                              is_python_module=False,
                              extra_cflags=["-O3", "-march=native", "-ffp-contract=off",
                                            "-fno-math-errno", "-fopenmp"],
                              extra_ldflags=["-fopenmp"])
                    _module = torch.ops.gdiff_splat
                except Exception as e:  # compiler missing, headers missing, build error
                    _failed = f"{type(e).__name__}: {str(e).strip().splitlines()[-1:]}"
                    log.warning("C++ rasterizer could not be built (%s); using the torch "
                                "rasterizer, which is slower", _failed)
        if _module is None and required:
            raise GdiffError(f"rasterize backend 'cpp' is not available ({_failed}); install a "
                             "C++ compiler (g++) or set the rasterize backend to 'auto' or "
                             "'torch'")
        return _module


class _RasterizeCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, extents, visible, order, width, height,
                absgrad):
        mod = load(required=True)
        out, alpha, T_final, last, offsets, ids = mod.rasterize_forward(
            means2d, conics, colors, opacities, extents, visible, order, width, height, TILE_SIZE)
        ctx.save_for_backward(means2d, conics, colors, opacities, extents, offsets, ids,
                              T_final, last)
        ctx.size = (width, height)
        ctx.absgrad = absgrad
        ctx.mark_non_differentiable(T_final)
        return out, alpha

    @staticmethod
    def backward(ctx, grad_out, grad_alpha):
        means2d, conics, colors, opacities, extents, offsets, ids, T_final, last = \
            ctx.saved_tensors
        width, height = ctx.size
        g_m, g_q, g_c, g_o, g_abs = load(required=True).rasterize_backward(
            means2d, conics, colors, opacities, extents, offsets, ids, T_final, last,
            grad_out.contiguous(), grad_alpha.contiguous(), width, height, TILE_SIZE,
            ctx.absgrad is not None)
        if ctx.absgrad is not None:
            ctx.absgrad.append(g_abs)
        return g_m, g_q, g_c, g_o, None, None, None, None, None, None


def depth_order(depths: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """[C,N] int64: per camera, the visible Gaussians by increasing depth (ties by index, as a
    stable sort of all of them), then the others (the kernel skips those). Sorting only the
    visible ones (often half) halves the cost of the sort."""
    rows = []
    for d, v in zip(depths, visible):
        vis = v.nonzero().squeeze(1)
        rows.append(torch.cat([vis[torch.argsort(d[vis], stable=True)], (~v).nonzero().squeeze(1)]))
    return torch.stack(rows) if rows else torch.empty_like(depths, dtype=torch.long)


def rasterize_cpp(means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor,
                  opacities: torch.Tensor, extents: torch.Tensor, visible: torch.Tensor,
                  depths: torch.Tensor, width: int, height: int,
                  absgrad: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite projected Gaussians with the C++ kernel (differentiable).

    Args and returns as :func:`gdiff.splat.rasterize.rasterize_torch`: means2d [C,N,2],
    conics [C,N,3], colors [C,N,D], opacities [C,N], extents [C,N,2], visible [C,N] bool,
    depths [C,N] -> (features [C,H,W,D] without background, alphas [C,H,W,1]).
    With ``absgrad`` the backward pass sets ``means2d.absgrad`` [C,N,2].
    """
    dtype = colors.dtype
    order = depth_order(depths.detach(), visible)
    holder = [] if (absgrad and means2d.requires_grad) else None
    out, alpha = _RasterizeCpp.apply(
        means2d.to(dtype).contiguous(), conics.to(dtype).contiguous(), colors.contiguous(),
        opacities.to(dtype).contiguous(), extents.detach().to(dtype).contiguous(),
        visible.contiguous(), order.contiguous(), int(width), int(height), holder)
    if holder is not None:
        def hook(grad):
            if holder:
                means2d.absgrad = holder.pop().to(grad.dtype)
            return grad

        means2d.register_hook(hook)
    return out, alpha


class _ProjectCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmats, Ks, width, height, near_plane, far_plane,
                eps2d, radius_clip):
        out = load(required=True).project_forward(means, quats, scales, viewmats, Ks, width,
                                                  height, near_plane, far_plane, eps2d,
                                                  radius_clip)
        ctx.save_for_backward(means, quats, scales, viewmats, Ks)
        ctx.args = (width, height, near_plane, far_plane, eps2d)
        ctx.mark_non_differentiable(*out[3:])
        return tuple(out)

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, *_):
        means, quats, scales, viewmats, Ks = ctx.saved_tensors
        g_m, g_q, g_s = load(required=True).project_backward(
            means, quats, scales, viewmats, Ks, *ctx.args, g_means2d.contiguous(),
            g_conics.contiguous(), g_depths.contiguous())
        return g_m, g_q, g_s, None, None, None, None, None, None, None, None


def project_cpp(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                near_plane: float = 0.01, far_plane: float = 1e10, eps2d: float = 0.3,
                radius_clip: float = 0.0) -> dict[str, torch.Tensor]:
    """``project_gaussians(means, covariance_3d(quats, scales), ...)`` in one C++ kernel.

    Args: means [N,3], quats [N,4] (w,x,y,z, any norm), scales [N,3] (activated), viewmats
        [C,4,4] world-to-camera (OpenCV), Ks [C,3,3]; the rest as
        :func:`gdiff.splat.rasterize.project_gaussians`, which defines the outputs (same dict).
    Differentiable with respect to means, quats and scales; the cameras get no gradient (use
    the torch version to optimise them).
    """
    dtype = means.dtype
    m2d, conics, depths, radii, extents, visible = _ProjectCpp.apply(
        means.contiguous(), quats.to(dtype).contiguous(), scales.to(dtype).contiguous(),
        viewmats.detach().to(dtype).contiguous(), Ks.detach().to(dtype).contiguous(),
        int(width), int(height), float(near_plane), float(far_plane), float(eps2d),
        float(radius_clip))
    return dict(means2d=m2d, conics=conics, depths=depths, radii=radii, extents=extents,
                visible=visible)


class _Reflect(torch.autograd.Function):
    @staticmethod
    def forward(ctx, dirs, quats, scales):
        ctx.save_for_backward(dirs, quats, scales)
        return load(required=True).reflect_forward(dirs, quats, scales)

    @staticmethod
    def backward(ctx, grad):
        dirs, quats, scales = ctx.saved_tensors
        g_d, g_q = load(required=True).reflect_backward(dirs, quats, scales, grad.contiguous())
        return g_d, g_q, None


def reflect_cpp(dirs: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """``reflect(dirs, shortest_axis(quats, scales)[None])`` of :mod:`gdiff.splat.reflection`
    in one C++ kernel: dirs [C,N,3] (any norm), quats [N,4] (w,x,y,z, any norm), scales [N,3]
    -> unit mirror directions [C,N,3]; differentiable in dirs and quats (the choice of axis
    is not)."""
    dtype = dirs.dtype
    return _Reflect.apply(dirs.contiguous(), quats.to(dtype).contiguous(),
                          scales.detach().to(dtype).contiguous())


class _ShToColor(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coeffs, dirs, degree):
        ctx.save_for_backward(coeffs, dirs)
        ctx.degree = degree
        return load(required=True).sh_forward(coeffs, dirs, degree)

    @staticmethod
    def backward(ctx, grad):
        coeffs, dirs = ctx.saved_tensors
        g_c, g_d = load(required=True).sh_backward(coeffs, dirs, ctx.degree, grad.contiguous())
        return g_c, g_d, None


def sh_to_color_cpp(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """:func:`gdiff.splat.sh.sh_to_color` in one C++ kernel for coeffs [N,K,3] seen along
    dirs [C,N,3] (world frame, any norm): colours [C,N,3], differentiable in both."""
    dtype = coeffs.dtype
    return _ShToColor.apply(coeffs.contiguous(), dirs.to(dtype).contiguous(), int(degree))


class _HexPlaneSample(torch.autograd.Function):
    @staticmethod
    def forward(ctx, table, coords, planes, group):
        # the samples of every plane [N, P, F] are kept for the backward pass, which then
        # needs no second look-up in the table
        out, samples = load(required=True).hexplane_forward_samples(table, coords, planes, group)
        ctx.save_for_backward(samples, coords, planes)
        ctx.group, ctx.rows = group, table.shape[0]
        return out

    @staticmethod
    def backward(ctx, grad):
        samples, coords, planes = ctx.saved_tensors
        g = load(required=True).hexplane_backward(samples, grad.contiguous(), coords, planes,
                                                  ctx.group, ctx.rows)
        return g, None, None, None


def hexplane_sample(table: torch.Tensor, coords: torch.Tensor, planes: torch.Tensor,
                    group: int) -> torch.Tensor:
    """Bilinear look-up of many feature planes stored in one channels-last table, with the
    samples of each group of ``group`` consecutive planes multiplied (one HexPlane level).

    Args:
        table: [R, F] float32 CPU; plane p's texel (x, y) is row ``offset_p + y * W_p + x``.
        coords: [N, 4] float32 normalised coordinates in [-1, 1] (no gradient).
        planes: [P, 5] int64 rows ``(axis a, axis b, W, H, offset)``: plane p samples
            ``coords[:, a]`` along its width and ``coords[:, b]`` along its height; P is a
            multiple of ``group``.
        group: planes per product (6 for a HexPlane level).
    Returns:
        [N, P / group, F]: per group, the product of ``grid_sample(bilinear, border,
        align_corners=True)`` of its planes; differentiable with respect to ``table``.
    """
    if not (table.requires_grad and torch.is_grad_enabled()):  # no samples kept
        return load(required=True).hexplane_forward(table.contiguous(),
                                                    coords.detach().contiguous(),
                                                    planes.contiguous(), int(group))
    return _HexPlaneSample.apply(table.contiguous(), coords.detach().contiguous(),
                                 planes.contiguous(), int(group))
