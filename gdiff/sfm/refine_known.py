"""Known poses that are only roughly right: a robot's ``/map`` -> camera transforms (wheel
odometry, localisation, head joints) are off by a degree or two and a few centimetres, which
on a 640 px photo is 10-30 px. Photos of the two visits then disagree by that much: features
do not triangulate within COLMAP's reprojection threshold, and a fit renders the unchanged
scene shifted between the times, which the comparison takes for change.

:func:`refine_known_poses` triangulates the matched features with a tolerance wide enough for
such errors, bundle-adjusts poses and points (intrinsics held: they are known) while the
tolerance narrows to ``max_reproj_error`` with a retriangulation per round, and maps the
adjusted cameras back into the given frame (a similarity fitted to the given centres and
viewing directions), so world frame and scale stay the user's.

An image that too few triangulated points tie to the others (a view no other waypoint
shares) often shares many matches with the photo of the same waypoint on the other visit: two
photos from about one place, too close for triangulation, but their matches give the rotation
between them (:func:`best_turn`; by default, ``poses.turn_baseline: refined``, the
baseline's direction is refined with it, its length and the centres kept as given). Such an
image is turned to agree with that photo and moved with it. Of a pair of which neither is tied, the
before photo keeps its given centre and takes the correction all refined photos share (their
mean turn: a camera mounted a few degrees off turns every pose alike), and the after photo is
turned to agree with it. A robot's other pose errors differ from waypoint to waypoint (the
localisation at each stop), so a neighbouring waypoint's own correction does not carry over.

Conventions: ``Camera.c2w`` is camera-to-world (OpenCV axes: x right, y down, z forward);
pycolmap images hold world-to-camera (``cam_from_world``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..align import angle_between_deg, orbit_radius, rotation_angle_deg, umeyama_sim3
from ..cameras import Camera
from .colmap import _c2w_of, _mapper_options, bundle_options
from .options import PosesOptions

log = logging.getLogger("gdiff.sfm")


def triangulate(rec, db: Path, root: Path, out: Path, opts: PosesOptions, n_images: int,
                scale: float, relax: float, clear: bool):
    """pycolmap's point triangulator on ``rec``'s poses (held fixed), thresholds ``relax`` x
    ``opts.max_reproj_error`` (extraction pixels x ``scale``); returns the new model."""
    import pycolmap

    out.mkdir(parents=True, exist_ok=True)
    return pycolmap.triangulate_points(rec, db, root, out, clear_points=clear,
                                       options=_mapper_options(opts, n_images, scale,
                                                               relax=relax),
                                       refine_intrinsics=False)


def _set_pose(rec, image, c2w: np.ndarray) -> None:
    """Give a pycolmap image (of a trivial frame) the camera-to-world pose ``c2w`` [4, 4]."""
    import pycolmap

    w2c = np.linalg.inv(c2w)
    rec.frames[image.frame_id].rig_from_world = pycolmap.Rigid3d(
        pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])


def _anchor_points(c2ws: list[np.ndarray], reach: float) -> np.ndarray:
    """Each camera's centre and the point ``reach`` ahead on its optical axis (+z), [2N, 3]:
    a similarity fitted to these keeps the cameras' viewing directions too, also when the
    centres lie on a line (a robot driving along a wall)."""
    pts = []
    for c2w in c2ws:
        pts.append(c2w[:3, 3])
        pts.append(c2w[:3, 3] + reach * c2w[:3, 2])
    return np.stack(pts)


def _spread(c2ws: list[np.ndarray]) -> float:
    """RMS distance of the camera centres from their centroid."""
    c = np.stack([m[:3, 3] for m in c2ws])
    return float(np.sqrt(((c - c.mean(0)) ** 2).sum(1).mean()))


def _back_to_given(adjusted: list[np.ndarray], given: list[np.ndarray], reach: float
                   ) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``given ≈ s * R @ adjusted + t`` of two sets of camera-to-world poses:
    its scale from the spread of the centres (bundle adjustment leaves the scale free), then
    rotation and translation from each camera's centre and the point ``reach`` (given frame's
    units) ahead on its axis, so viewing directions count as well as centres."""
    a, g = _spread(adjusted), _spread(given)
    s0 = g / a if a > 1e-12 and g > 1e-12 else 1.0  # cameras at one spot: no scale to see
    return umeyama_sim3(_anchor_points(adjusted, reach / s0), _anchor_points(given, reach))


def _pair_matches(db: Path) -> dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]:
    """Verified matches of every image pair in a COLMAP database: ``(name1, name2) ->
    (xy1, xy2)``, keypoint pixels [M, 2] (COLMAP's convention, pixel centres at +0.5, like
    gdiff's), both orders."""
    import pycolmap

    d = pycolmap.Database.open(str(db))
    try:
        names = {im.image_id: im.name for im in d.read_all_images()}
        keys = {i: d.read_keypoints(i)[:, :2] for i in names}
        pair_ids, geometries = d.read_two_view_geometries()
    finally:
        d.close()
    out = {}
    for pid, g in zip(pair_ids, geometries):
        a, b = pycolmap.pair_id_to_image_pair(pid)
        m = np.asarray(g.inlier_matches)
        if len(m) == 0:
            continue
        xa, xb = keys[a][m[:, 0]].astype(np.float64), keys[b][m[:, 1]].astype(np.float64)
        out[(names[a], names[b])] = (xa, xb)
        out[(names[b], names[a])] = (xb, xa)
    return out


def turn_between(xy1: np.ndarray, xy2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                 threshold: float) -> tuple[np.ndarray | None, int]:
    """Rotation between two photos taken from (nearly) one place, from their matched pixels
    ``xy1``, ``xy2`` [M, 2] and intrinsics ``K1``, ``K2`` [3, 3]: the homography a pure
    rotation induces (``x2 ~ K2 M K1^-1 x1``, OpenCV RANSAC at ``threshold`` pixels), brought
    to the nearest rotation. Returns ``(M, inliers)``: ``M = R2^T R1`` of the camera-to-world
    rotations (a bearing of camera 1 in camera 2's axes), or ``(None, 0)`` if no homography
    is found."""
    import cv2

    if len(xy1) < 4:
        return None, 0
    cv2.setRNGSeed(0)  # RANSAC draws from OpenCV's generator: the same photos, the same turn
    H, mask = cv2.findHomography(xy1, xy2, cv2.RANSAC, threshold)
    if H is None:
        return None, 0
    U, _, Vt = np.linalg.svd(np.linalg.inv(K2) @ H @ K1)
    M = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return M, int(mask.sum())


def _essential_turn(xy1: np.ndarray, xy2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                    threshold: float) -> np.ndarray | None:
    """``M = R2^T R1`` from the essential matrix of the matches (OpenCV's five-point RANSAC on
    normalised coordinates, threshold in pixels of camera 1, and its cheirality test), or
    None."""
    import cv2

    if len(xy1) < 5:
        return None
    n1 = (np.linalg.inv(K1) @ np.c_[xy1, np.ones(len(xy1))].T).T[:, :2]
    n2 = (np.linalg.inv(K2) @ np.c_[xy2, np.ones(len(xy2))].T).T[:, :2]
    cv2.setRNGSeed(0)
    E, mask = cv2.findEssentialMat(n1, n2, np.eye(3), cv2.RANSAC, 0.999,
                                   threshold / K1[0, 0])
    if E is None or E.shape != (3, 3):
        return None
    _, R, _, _ = cv2.recoverPose(E, n1, n2, np.eye(3), mask=mask)
    return R


def epipolar_errors(xy1: np.ndarray, xy2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                    M: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per match [M], pixels: the Sampson distance of ``xy1``, ``xy2`` under the relative pose
    ``X2 = M X1 + t`` (camera-1 to camera-2 coordinates); with no baseline (``t`` ~ 0) the
    distance of ``xy2`` from ``xy1`` carried by the rotation alone."""
    h1 = np.c_[xy1, np.ones(len(xy1))]
    h2 = np.c_[xy2, np.ones(len(xy2))]
    if np.linalg.norm(t) < 1e-12:
        q = (K2 @ M @ np.linalg.inv(K1) @ h1.T).T
        return np.linalg.norm(q[:, :2] / q[:, 2:] - xy2, axis=1)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K2).T @ tx @ M @ np.linalg.inv(K1)
    f1, f2 = (F @ h1.T).T, (F.T @ h2.T).T
    num = np.sum(h2 * f1, axis=1) ** 2
    return np.sqrt(num / np.maximum(f1[:, 0] ** 2 + f1[:, 1] ** 2 + f2[:, 0] ** 2
                                    + f2[:, 1] ** 2, 1e-300))


def _across(t: np.ndarray) -> np.ndarray:
    """Two unit vectors [2, 3] orthogonal to ``t`` [3] and to each other."""
    u = t / np.linalg.norm(t)
    a = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(u, a)])


def _refine_turn(xy1: np.ndarray, xy2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                 M: np.ndarray, t: np.ndarray, threshold: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The rotation ``M`` [3, 3] and the baseline ``t`` [3] whose direction, refined together
    with it (its length held: the matches cannot see it), fits the matches best (Cauchy loss on
    :func:`epipolar_errors`, scale a quarter of ``threshold``: false matches barely pull),
    starting from the given ones. With no baseline (``t`` ~ 0) only the rotation is
    refined."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    length = float(np.linalg.norm(t))
    free = length > 1e-12
    across = _across(t) if free else None

    def pose(v):
        if not free:
            return Rotation.from_rotvec(v).as_matrix() @ M, t
        d = t / length + v[3:] @ across
        return Rotation.from_rotvec(v[:3]).as_matrix() @ M, length * d / np.linalg.norm(d)

    fit = least_squares(lambda v: epipolar_errors(xy1, xy2, K1, K2, *pose(v)),
                        np.zeros(5 if free else 3), loss="cauchy", f_scale=0.25 * threshold)
    return pose(fit.x)


def best_turn(xy1: np.ndarray, xy2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
              M0: np.ndarray, t: np.ndarray, threshold: float, free_baseline: bool = False
              ) -> tuple[np.ndarray, int, str]:
    """The rotation ``M = R2^T R1`` between two photos that their matches (pixels [M, 2])
    support best, with the camera-1 centre at ``t`` in camera 2's axes as given (``X2 = M X1
    + t``).

    The starts are the given rotation ``M0``, the pure rotation of their homography
    (:func:`turn_between`: photos from one place) and the rotation of their essential matrix
    (photos a few centimetres apart at close range, where a homography leaves parallax
    unexplained). The start with the most matches within ``threshold`` pixels
    (:func:`epipolar_errors`) under the given baseline wins, ties to the lower median, and the
    given one on equal terms; it is then refined to the rotation whose errors over all matches
    are least (robust soft-L1 loss, the baseline held). The count of matches it then explains,
    the support of the given baseline, is what decides whether, and to which photo, an image
    is turned (:func:`_place_untied`), with either setting below.

    With the baseline held, centres a few centimetres off let the turn about the axis across
    it slide along the epipolar lines, which it barely changes, to where the baseline's own
    error is absorbed: it can end degrees off. With ``free_baseline``
    (``poses.turn_baseline: refined``) the rotation returned is instead that of
    :func:`_free_turn` (the baseline's direction fitted with it), and the start it came from.
    The count stays the held fit's: three parameters, so that a pair of a handful of matches
    does not pass by the freedom of the baseline's direction.

    Returns ``(M, support, "given" | "homography" | "essential")``: the start the rotation was
    refined from."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    found = [("given", M0), ("homography", turn_between(xy1, xy2, K1, K2, threshold)[0]),
             ("essential", _essential_turn(xy1, xy2, K1, K2, threshold))]
    best = None
    for how, M in found:
        if M is None:
            continue
        e = epipolar_errors(xy1, xy2, K1, K2, M, t)
        key = (int((e < threshold).sum()), -float(np.median(e)))
        if best is None or key > best[0]:
            best = (key, M, how)
    (n, _), M, how = best
    if n >= 5:  # then the rotation that fits those matches best, the baseline held
        fit = least_squares(lambda v: epipolar_errors(
            xy1, xy2, K1, K2, Rotation.from_rotvec(v).as_matrix() @ M, t), np.zeros(3),
            loss="soft_l1", f_scale=0.5 * threshold)
        M = Rotation.from_rotvec(fit.x).as_matrix() @ M
        n = int((epipolar_errors(xy1, xy2, K1, K2, M, t) < threshold).sum())
    if free_baseline and len(xy1) >= 5:
        M, how = _free_turn(xy1, xy2, K1, K2, found, t, threshold)
    return M, n, how


def _free_turn(xy1: np.ndarray, xy2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
               found: list, t: np.ndarray, threshold: float) -> tuple[np.ndarray, str]:
    """The rotation of :func:`best_turn`'s ``free_baseline``: each start of ``found`` (``(how,
    M or None)``) refined together with the baseline's direction (:func:`_refine_turn`); the
    one with the most matches within ``threshold`` under its own refined baseline wins, ties
    to the lower median, and the earlier start on equal terms. Only the rotation is returned
    (with its start): the caller keeps the given centre, since a short baseline's direction is
    what the matches fix least."""
    best = None
    for how, M in found:
        if M is None:
            continue
        R, tt = _refine_turn(xy1, xy2, K1, K2, M, t, threshold)
        e = epipolar_errors(xy1, xy2, K1, K2, R, tt)
        key = (int((e < threshold).sum()), -float(np.median(e)))
        if best is None or key > best[0]:
            best = (key, R, how)
    return best[1], best[2]


def common_turn(before: list[np.ndarray], after: list[np.ndarray]) -> np.ndarray:
    """The mean (scipy's chordal L2 mean) of the world-frame rotations ``R_after R_before^T``
    [3, 3] that took each camera-to-world pose of ``before`` to the same camera's ``after``:
    what all corrections share (a head camera mounted a few degrees off, a yaw error of the
    robot's map)."""
    from scipy.spatial.transform import Rotation

    turns = [a[:3, :3] @ b[:3, :3].T for a, b in zip(after, before)]
    return Rotation.from_matrix(np.stack(turns)).mean().as_matrix()


def _place_untied(loose: list[str], placed: dict[str, np.ndarray], cams: dict[str, Camera],
                  matches, min_matches: int, threshold: float,
                  turn: np.ndarray | None = None, free_baseline: bool = False
                  ) -> tuple[dict, dict, list]:
    """Poses for the images bundle adjustment could not tie to the others (camera-to-world
    [4, 4], in ``placed``'s frame): each is turned to agree with the placed image whose matches
    support a turn best (at least ``min_matches`` of them, :func:`best_turn`: an image that
    shares matches but no triangulated points was taken from about the same place, e.g. the
    same waypoint on the other visit; the given turn may win; ``free_baseline``: see
    :func:`best_turn`) and moved with it. Images that share
    matches only with other untied ones: the first (capture order, before first) keeps its
    given centre, turned about it by ``turn`` [3, 3] (world frame; the correction the refined
    images share, :func:`common_turn`; None: not turned), and the others are turned to agree
    with it. Returns ``(poses, partners, anchored)``: the new poses, image -> (the image it
    was turned to, which turn won), the images placed the first way."""
    given = {n: cams[n].c2w for n in loose}
    placed = dict(placed)
    partners, kept = {}, []
    left = list(loose)
    scored = {}  # (u, p) -> best_turn: it reads the given poses only, so once per pair
    while left:
        best = None
        for u in left:
            for p in placed:
                if (u, p) not in matches:
                    continue
                if (u, p) not in scored:
                    Ru, Rp = cams[u].c2w[:3, :3], cams[p].c2w[:3, :3]
                    t = Rp.T @ (cams[u].center - cams[p].center)  # u's centre in p's axes
                    scored[(u, p)] = best_turn(*matches[(u, p)], cams[u].K, cams[p].K,
                                               Rp.T @ Ru, t, threshold, free_baseline)
                M, k, how = scored[(u, p)]
                if k >= min_matches and (best is None or k > best[2]):
                    best = (u, p, k, M, how)
        if best is None:  # nothing left shares enough with a placed image: anchor the first
            u = left[0]
            placed[u] = given[u].copy()
            if turn is not None:
                placed[u][:3, :3] = turn @ given[u][:3, :3]
            kept.append(u)
            left.remove(u)
            continue
        u, p, _, M, how = best
        Rp, Rp0 = placed[p][:3, :3], cams[p].c2w[:3, :3]
        c2w = np.eye(4)
        c2w[:3, :3] = Rp @ M
        c2w[:3, 3] = placed[p][:3, 3] + Rp @ Rp0.T @ (cams[u].center - cams[p].center)
        placed[u] = c2w
        partners[u] = (p, how)
        left.remove(u)
    return {n: placed[n] for n in loose}, partners, kept


def _adjust(rec, db: Path, root: Path, work: Path, opts: PosesOptions, n_images: int,
            scale: float, wide: float, strict: float, num_threads: int):
    """Bundle adjustment of poses and points from a model triangulated at ``wide`` pixels:
    each round adjusts, drops observations beyond the round's threshold, halves it (down to
    ``strict``) and triangulates the matches the new poses now explain. Returns the model."""
    import pycolmap

    err, k = wide, 0
    level = pycolmap.logging.minloglevel
    while True:
        pycolmap.bundle_adjustment(rec, bundle_options(err, num_threads, refine_intrinsics=False))
        pycolmap.logging.minloglevel = level  # bundle_adjustment leaves it at INFO
        pycolmap.ObservationManager(rec).filter_all_points3D(err, 1.5)
        if err <= strict:
            return rec
        err = max(strict, err / 2)
        k += 1
        rec = triangulate(rec, db, root, work / f"tri_{k}", opts, n_images, scale,
                          err / strict, clear=False)


def _map_back(rec, refined: list[str], given: dict[str, np.ndarray], by_name) -> float:
    """Move the model (in place) by the similarity that takes the adjusted poses of
    ``refined`` onto their given ones (:func:`_back_to_given`); returns its scale."""
    import pycolmap

    adjusted = [_c2w_of(by_name[n]) for n in refined]
    fixed = [given[n] for n in refined]
    reach = orbit_radius(np.stack([g[:3, 3] for g in fixed]))
    a, g = _spread(adjusted), _spread(fixed)
    if rec.num_points3D() and a > 1e-12:  # how far the points lie from the cameras
        xyz = np.array([p.xyz for p in rec.points3D.values()])
        reach = float(np.median([np.linalg.norm(xyz - c[:3, 3], axis=1).mean()
                                 for c in adjusted])) * g / a  # in the given frame's units
    s, R, t = _back_to_given(adjusted, fixed, reach)
    rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t))
    return float(s)


def refine_known_poses(rec, db: Path, root: Path, work: Path, cams: dict[str, Camera],
                       opts: PosesOptions, scale: float, num_threads: int = -1
                       ) -> tuple[object, dict[str, Camera], dict]:
    """Refine roughly known poses by bundle adjustment and map them back into their frame.

    Args:
        rec: ``pycolmap.Reconstruction`` holding every image at its given pose, no points
            (:func:`gdiff.sfm.known._known_reconstruction`).
        db: the COLMAP database with the images' verified matches.
        root: folder of the photos as named in ``db``.
        work: scratch folder (one model folder per triangulation is written into it).
        cams: the given camera per image name (pinhole, camera-to-world).
        opts: ``known_max_error`` (the error the given poses may cause, as a fraction of the
            longer image side: the first triangulation's threshold), ``max_reproj_error``
            (the final one, extraction pixels), ``min_num_matches`` (points an image needs to
            be refined), ``turn_baseline`` (how an untied image's turn is fitted,
            :func:`best_turn`).
        scale: full-resolution pixels per extraction pixel.

    Returns:
        ``(rec, cams, info)``: the refined model (points triangulated at ``max_reproj_error``),
        the cameras with refined poses, and ``info``: ``refined`` (image names),
        ``paired`` (image -> (the image it was turned to agree with, which turn won), see
        :func:`_place_untied`), ``anchored`` (untied images given the refined images' common
        correction, ``common_turn_deg``), ``given`` (all images, kept as given, when fewer than
        two could be refined), ``rotation_deg`` /
        ``centre`` (median correction over the refined images; centre in the given frame's
        units), ``centre_frac`` (the same over the median distance of the given centres from
        their centroid), ``scale`` (of the similarity back into the given frame),
        ``points_first`` (triangulated at the wide threshold before any refinement).
    """
    import pycolmap

    names = list(cams)
    strict = opts.max_reproj_error * scale
    side = max(max(c.width, c.height) for c in cams.values())
    wide = max(strict, opts.known_max_error * side)
    given = {n: cams[n].c2w for n in names}
    rec = triangulate(rec, db, root, work / "tri_wide", opts, len(names), scale,
                      wide / strict, clear=True)
    first = int(rec.num_points3D())
    info = {"refined": [], "paired": {}, "anchored": [], "given": [], "points_first": first,
            "common_turn_deg": 0.0, "rotation_deg": 0.0, "centre": 0.0, "centre_frac": 0.0,
            "scale": 1.0}
    rec = _adjust(rec, db, root, work, opts, len(names), scale, wide, strict, num_threads)
    by_name = {im.name: im for im in rec.images.values()}
    refined = [n for n in names if n in by_name
               and by_name[n].num_points3D >= opts.min_num_matches]
    loose = [n for n in names if n not in refined]
    info["refined"] = refined
    if len(refined) < 2:  # nothing ties the images together: every pose stays as given
        for n in names:
            _set_pose(rec, by_name[n], given[n])
        info.update(refined=[], given=names)
        rec = triangulate(rec, db, root, work / "tri_given", opts, len(names), scale, 1.0,
                          clear=True)
    else:
        s = _map_back(rec, refined, given, by_name)
        new = {n: _c2w_of(by_name[n]) for n in refined}
        turn = common_turn([given[n] for n in refined], [new[n] for n in refined])
        if loose:  # turned to agree with a photo from the same place (see module)
            poses, info["paired"], info["anchored"] = _place_untied(
                loose, new, cams, _pair_matches(db), opts.min_num_matches, strict, turn,
                free_baseline=opts.turn_baseline == "refined")
            for n, c2w in poses.items():
                new[n] = c2w
                _set_pose(rec, by_name[n], c2w)
        info["common_turn_deg"] = float(rotation_angle_deg(turn))
        pycolmap.ObservationManager(rec).filter_all_points3D(strict, 1.5)
        rot = [angle_between_deg(new[n], given[n]) for n in refined]
        ctr = [float(np.linalg.norm(new[n][:3, 3] - given[n][:3, 3])) for n in refined]
        radius = orbit_radius(np.stack([given[n][:3, 3] for n in names]))
        info.update(rotation_deg=float(np.median(rot)), centre=float(np.median(ctr)),
                    centre_frac=float(np.median(ctr)) / radius if radius > 0 else 0.0,
                    scale=float(s))
        cams = {n: Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, new[n], image=c.image,
                          set=c.set, time=c.time, dist=c.dist) for n, c in cams.items()}
    rec.update_point_3d_errors()
    log.info("known poses refined: %d points at %.1f px first, %d at %.1f px after bundle "
             "adjustment; %d images refined (median correction %.2f deg, %.3g = %.1f %% of the "
             "camera spread); %d tied to the others by fewer than %d points%s%s",
             first, wide, rec.num_points3D(), strict, len(info["refined"]), info["rotation_deg"],
             info["centre"], 100 * info["centre_frac"], len(loose), opts.min_num_matches,
             "".join(f"; {n} turned to agree with {m} ({how} turn; "
                     f"{angle_between_deg(cams[n].c2w, cams[m].c2w):.2f} deg between them, "
                     f"{angle_between_deg(given[n], given[m]):.2f} as given)"
                     for n, (m, how) in info["paired"].items()),
             "".join(f"; {n} turned by the refined images' common correction "
                     f"({info['common_turn_deg']:.2f} deg)" for n in info["anchored"])
             + (f"; all {len(names)} kept as given: too few points tie any two images"
                if info["given"] else ""))
    return rec, cams, info
