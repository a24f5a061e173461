"""Geometric change evidence in 3D: surfaces that appear or vanish between the two times,
voted over every pose that sees them.

The ID comparison (:mod:`gdiff.compare.change`) judges whole segments; when the segmenter
merges an object with the surface it stands on at one time (a cone on a table, one segment),
no ID is absent at that time and the object is missed. The rendered depth still shows it: at
the same pose, the surface at one time lies clearly nearer than at the other.

Per pose (:func:`pose_flags`), a pixel is an *appearing* surface at t1 when its t1 surface is
nearer than its t0 surface by more than ``depth_change_rel`` in inverse depth relative to the
pose's median depth (or has a surface at t1 only) and its appearance differs between the times
(a surface that moved in depth but renders as before is a floater of the fit, not a change
anyone could see); symmetrically a *vanishing* surface at t0. Both count only inside coherent
blobs (``evidence_open``) and, with key views, where photos of both times observed the surface.
A change of appearance alone (a moved shadow or highlight, but also a flat object) never
counts here; the ID comparison handles those.

Each such pixel's world point (at its own time) votes for a voxel; every observed pixel with a
surface at that time counts as a look at its voxel. A voxel is flagged when at least
``geometry_vote`` of the poses that looked at it flagged it, and at least ``geometry_min_poses``
did. Flagged voxels are grouped into 3D components (26-neighbourhood); a component is a change
when it holds an object's worth of voxels. The voxel side is scene-relative:
``geometry_voxel_px`` pixels at the median depth of the frames, so an object spans many voxels
whatever the scene's units.

Back at each pose, flagged pixels whose voxel lies in a changed component are change pixels of
their time (``mask_t0``: vanished surfaces, ``mask_t1``: appeared surfaces).

Coordinates: world frame of the poses stage; depth is camera-frame z (OpenCV axes, pixel
centres at +0.5), as rendered into the EXR ``Z`` channel.
"""

from __future__ import annotations

import logging
import zipfile
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..errors import SceneError
from ..io import atomic_path
from ..track import world_points
from .change import coherent, surfaces

log = logging.getLogger("gdiff.compare")

# 26-neighbourhood offsets of a voxel (the voxel itself excluded)
_NEIGHBOURS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                        if (i, j, k) != (0, 0, 0)], np.int64)
_BITS = 21  # voxel coordinates packed into one int64 key, 21 bits per axis (signed offset)
_OFF = 1 << (_BITS - 1)


def _pack(v: np.ndarray) -> np.ndarray:
    """int64 keys [M] of integer voxel coordinates [M, 3]."""
    v = v.astype(np.int64) + _OFF
    return (v[:, 0] << (2 * _BITS)) | (v[:, 1] << _BITS) | v[:, 2]


def voxel_keys_of(points: np.ndarray, voxel: float) -> np.ndarray:
    """int64 [M] packed keys of the voxels (side ``voxel``, world units) that the finite world
    points [M, 3] lie in."""
    return _pack(np.floor(points / voxel)) if len(points) else np.zeros(0, np.int64)


def pixel_scale(depth: np.ndarray, camera) -> float | None:
    """World units per pixel at the median depth of a z-depth map [H, W] seen by ``camera``
    (median z / fx), over its pixels with a surface; None when it has none."""
    zz = np.asarray(depth)[np.isfinite(depth) & (np.asarray(depth) > 0)]
    return float(np.median(zz)) / float(camera.fx) if zz.size else None


def _unpack(k: np.ndarray) -> np.ndarray:
    mask = (1 << _BITS) - 1
    return np.stack([(k >> (2 * _BITS)) & mask, (k >> _BITS) & mask, k & mask], -1) - _OFF


@dataclass
class _Pose:
    """What pass 2 needs of one pose: flagged pixels (flat indices) and their voxel keys."""
    shape: tuple[int, int]
    idx: list = field(default_factory=lambda: [None, None])    # per time: int64 [K]
    keys: list = field(default_factory=lambda: [None, None])   # per time: int64 [K]


@dataclass
class PoseRecord:
    """One pose's share of a :class:`GeometryEvidence` (:func:`pose_record`)."""
    pose: _Pose
    flags: list          # per time: float32 [K, 3] world points of the flagged pixels
    looks: list          # per time: float32 [L, 3] world points of the looks
    scales: list         # per time with a surface: median z / fx


def pose_record(depth0: np.ndarray, depth1: np.ndarray, camera, flagged0: np.ndarray,
                flagged1: np.ndarray, looked0: np.ndarray, looked1: np.ndarray,
                points: tuple[np.ndarray, np.ndarray] | None = None,
                stride: int = 2) -> PoseRecord:
    """What :meth:`GeometryEvidence.add` keeps of one pose (arguments as there; ``stride``:
    the evidence's look sampling). Depends on this pose alone, so poses can be recorded in
    parallel."""
    rec = _Pose(tuple(depth0.shape))
    sub = np.zeros(depth0.shape, bool)
    sub[::stride, ::stride] = True
    if points is None:
        points = (world_points(depth0, camera), world_points(depth1, camera))
    flags, looks, scales = [], [], []
    for t, (z, fl, lk) in enumerate(((depth0, flagged0, looked0), (depth1, flagged1, looked1))):
        P = points[t].reshape(-1, 3)
        ok = np.isfinite(P).all(-1)
        fl = np.asarray(fl, bool).ravel() & ok
        lk = (np.asarray(lk, bool).ravel() & sub.ravel() & ok) | fl
        rec.idx[t] = np.flatnonzero(fl)
        flags.append(P[rec.idx[t]].astype(np.float32))
        looks.append(P[lk].astype(np.float32))
        scale = pixel_scale(z, camera)
        if scale is not None:
            scales.append(scale)
    return PoseRecord(rec, flags, looks, scales)


class GeometryEvidence:
    """Accumulates the per-pose evidence (:meth:`add`), then decides (:meth:`finish`) and
    returns per pose the change pixels of each time (:meth:`masks`). See the module docstring.

    Args:
        voxel_px: voxel side in pixels at the median depth of the frames.
        vote: fraction of the looks at a voxel that must flag it.
        min_poses: a voxel must be flagged at this many poses at least.
        min_object: a change must hold at least ``min_object * H * W / voxel_px**2`` voxels
            (at least 2): an object seen as that share of the image at the median depth.
        stride: pixels sampled every ``stride`` rows and columns for the looks (the flagged
            pixels are all kept).
    """

    def __init__(self, voxel_px: float = 4.0, vote: float = 0.5, min_poses: int = 3,
                 min_object: float = 0.003, stride: int = 2):
        self.voxel_px, self.vote, self.min_poses = voxel_px, vote, min_poses
        self.min_object, self.stride = min_object, stride
        self._poses: dict = {}
        # per time, per pose: world points [K, 3] float32 of the looks and of the flagged pixels
        self._looks: list[list[np.ndarray]] = [[], []]
        self._flags: list[list[np.ndarray]] = [[], []]
        self._scale: list[float] = []                     # median z / f per pose
        self.voxel: float | None = None
        self.changed: list[np.ndarray] = [np.zeros(0, np.int64), np.zeros(0, np.int64)]
        # per time: the component (0, 1, ...; numbered over both times) of each changed voxel
        self.component: list[np.ndarray] = [np.zeros(0, np.int64), np.zeros(0, np.int64)]

    def __contains__(self, pose) -> bool:
        return pose in self._poses

    def add(self, pose, depth0: np.ndarray, depth1: np.ndarray, camera, flagged0: np.ndarray,
            flagged1: np.ndarray, looked0: np.ndarray, looked1: np.ndarray,
            points: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """One pose: z-depth [H, W] at t0 and t1, its camera (camera-to-world ``c2w``,
        intrinsics) and the bool [H, W] masks of :func:`pose_flags`: ``flagged0`` vanished
        (t0) and ``flagged1`` appeared (t1) surfaces, ``looked{t}`` pixels whose surface at
        time t counts as a look. ``points``: the world points [H, W, 3] of the two depths
        (:func:`gdiff.track.world_points`) when the caller has them already.

        The same as ``put(pose, pose_record(...))``: poses may be recorded in parallel and put
        in their order (the result depends only on that order)."""
        self.put(pose, pose_record(depth0, depth1, camera, flagged0, flagged1, looked0,
                                   looked1, points, self.stride))

    def put(self, pose, record: "PoseRecord") -> None:
        """Add one pose's :func:`pose_record` (poses in a fixed order give a fixed result)."""
        for t in (0, 1):
            self._flags[t].append(record.flags[t])
            self._looks[t].append(record.looks[t])
        self._scale.extend(record.scales)
        self._poses[pose] = record.pose

    def _keys(self, P: np.ndarray) -> np.ndarray:
        return voxel_keys_of(P, self.voxel)

    def finish(self, max_rate: float | None = None) -> dict:
        """Decide the changed voxels; returns counts for the log.

        ``max_rate`` (None: no limit): when the voxels that pass the vote are more than this
        share of the voxels looked at from ``min_poses`` poses or more, at either time, the
        evidence is taken to come from a change that touches the whole scene (a change of
        light shows on every surface) and no voxel is changed (``stats["rate"]`` says why)."""
        stats = {"voxel": None, "changed_voxels": 0, "objects": 0, "rate": 0.0,
                 "rejected": False}
        if not self._scale:
            return stats
        self.voxel = stats["voxel"] = self.voxel_px * float(np.median(self._scale))
        h, w = next(iter(self._poses.values())).shape
        min_px = int(round(self.min_object * h * w))
        min_vox = max(2, int(np.ceil(min_px / self.voxel_px ** 2)))
        voted = []
        for t in (0, 1):
            looks, flags = [], []
            for pose, L, F in zip(self._poses.values(), self._looks[t], self._flags[t]):
                pose.keys[t] = self._keys(F)
                looks.append(np.unique(self._keys(L)))
                flags.append(np.unique(pose.keys[t]))
            self._looks[t], self._flags[t] = [], []
            lk, ln = np.unique(np.concatenate(looks), return_counts=True)
            fk, fn = np.unique(np.concatenate(flags), return_counts=True)
            seen = ln[np.searchsorted(lk, fk)]  # every flag is a look too
            voted.append(fk[(fn >= self.min_poses) & (fn >= self.vote * seen)])
            judged = int((ln >= self.min_poses).sum())
            stats["rate"] = max(stats["rate"], len(voted[t]) / max(judged, 1))
        if max_rate is not None and stats["rate"] > max_rate:
            stats["rejected"] = True
            return stats
        for t in (0, 1):
            self.changed[t], lab, n = _objects(voted[t], min_vox)
            self.component[t] = lab + stats["objects"]
            stats["changed_voxels"] += len(self.changed[t])
            stats["objects"] += n
        return stats

    def drop(self, components) -> int:
        """Remove the changed voxels of ``components`` (numbers as in :meth:`labels`), after
        :meth:`finish`; returns the number of voxels removed. The other components keep their
        numbers."""
        removed = 0
        for t in (0, 1):
            keep = ~np.isin(self.component[t], np.asarray(components, np.int64))
            removed += int((~keep).sum())
            self.changed[t], self.component[t] = self.changed[t][keep], self.component[t][keep]
        return removed

    def centres(self, keys: np.ndarray) -> np.ndarray:
        """World points [K, 3] of the centres of the voxels ``keys`` (after :meth:`finish`)."""
        return (_unpack(np.asarray(keys, np.int64)) + 0.5) * self.voxel

    def masks(self, pose) -> tuple[np.ndarray, np.ndarray]:
        """bool [H, W] change pixels of ``pose`` at t0 (vanished) and t1 (appeared)."""
        l0, l1 = self.labels(pose)
        return l0 >= 0, l1 >= 0

    def labels(self, pose) -> tuple[np.ndarray, np.ndarray]:
        """int [H, W] per time: the changed component each change pixel of ``pose`` belongs to
        (numbered from 0 over both times), -1 elsewhere."""
        rec = self._poses[pose]
        out = []
        for t in (0, 1):
            m = np.full(rec.shape[0] * rec.shape[1], -1, np.int64)
            if len(self.changed[t]) and rec.keys[t] is not None and len(rec.keys[t]):
                j = np.minimum(np.searchsorted(self.changed[t], rec.keys[t]),
                               len(self.changed[t]) - 1)
                hit = self.changed[t][j] == rec.keys[t]
                m[rec.idx[t][hit]] = self.component[t][j[hit]]
            out.append(m.reshape(rec.shape))
        return out[0], out[1]


def _objects(keys: np.ndarray, min_vox: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Keys (sorted) of the voxels of the 26-connected components of ``keys`` (sorted, unique)
    that hold at least ``min_vox`` voxels, each voxel's component (0 .. n-1) and their number
    n."""
    if len(keys) < min_vox:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), 0
    v = _unpack(keys)
    rows, cols = [], []
    for d in _NEIGHBOURS:
        nk = _pack(v + d)
        j = np.minimum(np.searchsorted(keys, nk), len(keys) - 1)
        hit = keys[j] == nk
        rows.append(np.flatnonzero(hit))
        cols.append(j[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(len(keys), len(keys)))
    n, lab = connected_components(graph, directed=False)
    keep = np.bincount(lab, minlength=n) >= min_vox
    renum = np.cumsum(keep) - 1
    return keys[keep[lab]], renum[lab[keep[lab]]], int(keep.sum())


def _relative_inverse_depth(z0: np.ndarray, z1: np.ndarray, v0: np.ndarray, v1: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Inverse depth times the pose's median depth (over ``z0[v0]`` and ``z1[v1]``) [H, W] at
    each time; 0 where there is no surface. A difference of ``rel`` is a relative depth change
    of ``rel`` at the median depth."""
    zm = float(np.median(np.concatenate([z0[v0], z1[v1]])))
    return (np.where(v0, zm / np.where(v0, z0, 1.0), 0.0),
            np.where(v1, zm / np.where(v1, z1, 1.0), 0.0))


def pose_flags(depth0: np.ndarray, depth1: np.ndarray, rel: float, open_frac: float,
               known: np.ndarray | None = None, looks_differ: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-pose input of :meth:`GeometryEvidence.add` from the z-depth [H, W] at t0 and t1.

    Returns bool [H, W] ``(vanished0, appeared1, looked0, looked1)``:

    * ``vanished0``: pixels whose surface at t0 lies nearer than at t1 (or exists at t0 only);
      ``appeared1``: the same at t1. "Nearer" is measured in inverse depth relative to the
      pose's median depth ``zm``: ``(1/z_near - 1/z_far) * zm > rel``; at the median depth this
      is a relative depth change of ``rel``; nearer surfaces need less, farther ones more (the
      depth a fit resolves from a baseline shrinks with the square of the distance). Only
      pixels that also ``looks_differ`` (bool [H, W], e.g.
      :func:`~gdiff.compare.change.appearance_change`, which ignores changes of light; None:
      every pixel) and only inside blobs at least ``open_frac`` of the image's longer side
      wide (:func:`~gdiff.compare.change.coherent`);
    * ``looked0`` / ``looked1``: pixels with a surface at each time.

    ``known`` (bool [H, W], observed by photos of both times, :mod:`gdiff.compare.coverage`)
    restricts all four.
    """
    z0, z1, v0, v1 = surfaces(depth0, depth1, known)
    if not (v0.any() and v1.any()):
        none = np.zeros(z0.shape, bool)
        return none, none, v0, v1
    d0, d1 = _relative_inverse_depth(z0, z1, v0, v1)
    differ = np.ones(z0.shape, bool) if looks_differ is None else np.asarray(looks_differ, bool)
    vanished = coherent(v0 & (d0 - d1 > rel) & differ, open_frac)
    appeared = coherent(v1 & (d1 - d0 > rel) & differ, open_frac)
    return vanished, appeared, v0, v1


def flat_flags(depth0: np.ndarray, depth1: np.ndarray, rel: float, open_frac: float,
               known: np.ndarray | None, looks_differ: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-pose input of a :class:`GeometryEvidence` for changes of appearance on a surface
    that stays in place (a flat object put onto or taken off a surface; but also a moved
    shadow, which :meth:`GeometryEvidence.finish` ``max_rate`` is there to reject).

    Returns bool [H, W] ``(flagged, flagged, looked, looked)``: ``flagged`` are pixels with a
    surface at both times whose inverse depth (relative to the pose's median depth, as in
    :func:`pose_flags`) changed by at most ``rel`` and that ``looks_differ`` (bool [H, W],
    :func:`~gdiff.compare.change.appearance_change`), inside blobs at least ``open_frac`` of
    the image's longer side wide; ``looked`` are pixels with a surface at both times. The
    surface is the same at both times, so it is flagged (and looked at) at both.
    ``known`` (bool [H, W] or None) restricts both."""
    z0, z1, v0, v1 = surfaces(depth0, depth1, known)
    v = v0 & v1
    if not v.any():
        none = np.zeros(z0.shape, bool)
        return none, none, v, v
    d0, d1 = _relative_inverse_depth(z0, z1, v, v)
    fl = coherent(v & (np.abs(d0 - d1) <= rel) & np.asarray(looks_differ, bool), open_frac)
    return fl, fl, v, v


# ------------------------------------------------------------------------------------------
# the changed voxels on disk (change/evidence3d.npz) and seen from any camera
# ------------------------------------------------------------------------------------------

EVIDENCE_KINDS = ("geometry", "flat")


def write_evidence(path, evidence: dict[str, tuple[float | None, np.ndarray, np.ndarray]]
                   ) -> None:
    """Write the changed voxels of each kind of 3D evidence, atomically, as ``.npz``:
    ``{kind}_voxel`` (voxel side, world units; NaN when the kind found nothing to decide on),
    ``{kind}_t0`` / ``{kind}_t1`` (int64 packed voxel keys of the surfaces that vanished /
    appeared, or for ``flat`` the surface whose appearance changed, at each time).
    ``evidence[kind] = (voxel, keys_t0, keys_t1)``."""
    arrays = {}
    for kind, (voxel, k0, k1) in evidence.items():
        arrays[f"{kind}_voxel"] = np.float64(np.nan if voxel is None else voxel)
        arrays[f"{kind}_t0"] = np.asarray(k0, np.int64)
        arrays[f"{kind}_t1"] = np.asarray(k1, np.int64)
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)


def read_evidence(path) -> dict[str, tuple[float | None, np.ndarray, np.ndarray]]:
    """The changed voxels written by :func:`write_evidence`; a missing or unreadable file is a
    :class:`~gdiff.errors.SceneError` naming it."""
    try:
        with np.load(path) as z:
            out = {}
            for kind in EVIDENCE_KINDS:
                if f"{kind}_voxel" in z:
                    v = float(z[f"{kind}_voxel"])
                    out[kind] = (None if not np.isfinite(v) else v, z[f"{kind}_t0"],
                                 z[f"{kind}_t1"])
            return out
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:
        raise SceneError(f"{path}: not a readable 3D evidence file ({e}); re-run the compare "
                         "rule (snakemake --forcerun compare)") from e


def evidence_masks(evidence: dict[str, tuple[float | None, np.ndarray, np.ndarray]],
                   camera, depth0: np.ndarray, depth1: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """bool [H, W] at t0 and t1: pixels of ``camera`` (any camera; camera-to-world ``c2w``)
    whose surface at that time (z-depth [H, W] rendered from the fitted model at t0 / t1)
    lies in a changed voxel of that time."""
    out = []
    for t, z in enumerate((depth0, depth1)):
        P = world_points(z, camera).reshape(-1, 3)
        ok = np.isfinite(P).all(-1)  # world_points: NaN where there is no depth
        m = np.zeros(len(P), bool)
        at = {}  # the pixels' voxel keys per voxel size (the kinds share one)
        for voxel, *keys in evidence.values():
            if voxel is None or not len(keys[t]):
                continue
            if voxel not in at:
                at[voxel] = voxel_keys_of(P[ok], voxel)
            m[np.flatnonzero(ok)[np.isin(at[voxel], keys[t])]] = True
        out.append(m.reshape(np.asarray(z).shape))
    return out[0], out[1]
