"""Similarity alignment of camera sets and pose-accuracy scores.

Estimated poses (COLMAP) live in an arbitrary frame: unknown scale, rotation and translation.
To score them against ground truth, the estimated camera centres are aligned to the ground-truth
centres with the least-squares similarity transform of Umeyama (1991), and then each camera's
rotation and centre are compared.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from .cameras import Camera


def umeyama_sim3(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ≈ s * R @ src + t``.

    Args:
        src, dst: corresponding points, float [N, 3], N >= 3 and not all collinear.

    Returns:
        ``(s, R, t)``: scale (float > 0), rotation [3, 3] (det +1), translation [3].
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama_sim3 needs two [N, 3] arrays with N >= 3, got {src.shape} "
                         f"and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs ** 2).sum() / len(src)
    if var_s <= 0:
        raise ValueError("umeyama_sim3: source points are all identical")
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s)
    t = mu_d - s * R @ mu_s
    return s, R, t


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle(s) in degrees of rotation matrices [..., 3, 3] (numerically clipped)."""
    tr = np.trace(np.asarray(R), axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Degrees between the orientations of two poses [4, 4] (or rotations [3, 3]) given the same
    way, camera-to-world or world-to-camera; either order."""
    return float(rotation_angle_deg(np.asarray(b)[:3, :3].T @ np.asarray(a)[:3, :3]))


def orbit_radius(centers: np.ndarray) -> float:
    """Median distance of camera centres [N, 3] from their centroid (the scale of the capture)."""
    c = np.asarray(centers, dtype=np.float64)
    return float(np.median(np.linalg.norm(c - c.mean(0), axis=1)))


def pose_errors(estimated: list[Camera], gt: list[Camera]) -> pd.DataFrame:
    """Per-image pose errors of ``estimated`` against ``gt`` after Sim3 alignment of centres.

    Cameras are matched by ``image`` name; images missing from ``estimated`` are left out (count
    them separately as unregistered). The Sim3 maps estimated centres onto GT centres; each
    estimated camera-to-world rotation is rotated by it before comparison.

    Returns:
        DataFrame with one row per matched image: ``image``, ``set``, ``rot_err_deg`` (angle of
        ``R_gt^T R_aligned``), ``center_err`` (GT world units) and ``center_err_frac``
        (``center_err`` / orbit radius, the median distance of the matched GT centres from their
        centroid). ``df.attrs`` holds ``scale``, ``R``, ``t`` (the Sim3) and ``orbit_radius``.
    """
    gt_by_name = {c.image: c for c in gt}
    pairs = [(e, gt_by_name[e.image]) for e in estimated if e.image in gt_by_name]
    if len(pairs) < 3:
        raise ValueError(f"pose_errors: only {len(pairs)} images in common (need >= 3)")
    ce = np.stack([e.center for e, _ in pairs])
    cg = np.stack([g.center for _, g in pairs])
    s, R, t = umeyama_sim3(ce, cg)
    aligned = (s * (R @ ce.T)).T + t
    radius = orbit_radius(cg)
    Re = np.stack([R @ e.c2w[:3, :3] for e, _ in pairs])
    Rg = np.stack([g.c2w[:3, :3] for _, g in pairs])
    rot = rotation_angle_deg(np.einsum("nji,njk->nik", Rg, Re))
    cerr = np.linalg.norm(aligned - cg, axis=1)
    df = pd.DataFrame({
        "image": [e.image for e, _ in pairs],
        "set": [g.set or e.set for e, g in pairs],
        "rot_err_deg": rot,
        "center_err": cerr,
        "center_err_frac": cerr / radius if radius > 0 else np.nan,
    })
    df.attrs.update(scale=s, R=R, t=t, orbit_radius=radius)
    return df


def relative_rotation_errors(estimated: list[Camera], gt: list[Camera]) -> np.ndarray:
    """Angle (degrees) between estimated and true relative rotations ``R_i^T R_j``
    (camera-to-world rotations) over every pair of images both lists hold (matched by
    ``image``), float [P]: how well the cameras agree with each other, whatever frame either
    list is in (no alignment needed, a common rotation of all cameras does not count)."""
    g = {c.image: c for c in gt}
    est = sorted((c for c in estimated if c.image in g), key=lambda c: c.image)
    out = []
    for i, a in enumerate(est):
        for b in est[i + 1:]:
            rel = a.c2w[:3, :3].T @ b.c2w[:3, :3]
            rel_gt = g[a.image].c2w[:3, :3].T @ g[b.image].c2w[:3, :3]
            out.append(float(rotation_angle_deg(rel_gt.T @ rel)))
    return np.asarray(out, dtype=np.float64)
