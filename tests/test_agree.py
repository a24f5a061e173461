"""gdiff.compare.agree: where the two visits' photos agree, matched by flow on the pixel's ray."""

import cv2
import numpy as np

from gdiff.cameras import Camera
from gdiff.compare.agree import agreeing, nearest_photos, photos_agree, ray_segment_distance
from gdiff.compare.photos import KeyPhoto

W, H, F, Z = 160, 120, 100.0, 2.0


def _texture(seed=0, w=W + 40, h=H):
    """A smooth random texture (linear RGB, float32 [h, w, 3]) the flow can lock onto."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((h, w, 3)).astype(np.float32), (0, 0), 2.0)
    t = (t - t.min()) / (t.max() - t.min())
    return (0.05 + 0.8 * t).astype(np.float32)


def _camera(x=0.0):
    c2w = np.eye(4)
    c2w[0, 3] = x
    return Camera(W, H, F, F, W / 2, H / 2, c2w)


def _key(photo, x=0.0, time=0):
    return KeyPhoto(time, _camera(x), np.full((H, W), Z, np.float32), photo, ("p", 0))


def _plane_photo(tex, x):
    """The textured plane z = Z (texture column c at world x = (c - 20 - W/2) Z / F) seen
    from a camera at (x, 0, 0) looking down +z: a shift of F x / Z pixels."""
    shift = F * x / Z
    cols = np.arange(W, dtype=np.float32) + 20 + shift
    rows = np.arange(H, dtype=np.float32)
    mx, my = np.meshgrid(cols, rows)
    return cv2.remap(tex, mx, my, cv2.INTER_LINEAR)


def test_ray_segment_distance_on_and_off_the_ray():
    a, b = _camera(0.0), _camera(0.1)
    depth = np.full((H, W), Z)
    col, row = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    # a static point at the rendered depth: 5 px to the left in b, on its ray's image
    on = np.stack([col - F * 0.1 / Z, row], -1)
    assert np.abs(ray_segment_distance(a, b, depth, on)).max() < 1e-6
    # farther (up to infinity: no shift) is on the segment too; 3 px down is off it by 3
    assert np.abs(ray_segment_distance(a, b, depth, np.stack([col, row], -1))).max() < 1e-6
    off = ray_segment_distance(a, b, depth, np.stack([col - 5, row + 3], -1))
    assert np.allclose(off, 3.0, atol=1e-6)
    # nearer than half the depth is off the segment (the near end: 10 px to the left)
    nearer = ray_segment_distance(a, b, depth, np.stack([col - 14, row], -1))
    assert np.allclose(nearer, 4.0, atol=1e-6)
    # the same camera: the ray's image is the pixel itself
    same = ray_segment_distance(a, a, depth, np.stack([col + 2, row], -1))
    assert np.allclose(same, 2.0, atol=1e-6)


def test_photos_of_an_unchanged_plane_agree_an_added_patch_does_not():
    tex = _texture(0)
    own = _plane_photo(tex, 0.0)
    other = _plane_photo(tex, 0.1)  # the other visit, 10 cm to the right
    agree = photos_agree(_key(own), _key(other, 0.1, 1))
    assert agree is not None
    inner = np.zeros((H, W), bool)
    inner[10:-10, 15:-15] = True
    assert agree[inner].mean() > 0.8
    # an object added at the own visit: a flat red square the other photo does not have
    added = own.copy()
    added[40:80, 60:100] = (0.7, 0.05, 0.05)
    agree = photos_agree(_key(added), _key(other, 0.1, 1))
    assert agree[44:76, 64:96].mean() < 0.05
    assert agree[inner & ~np.pad(np.ones((56, 56), bool), ((32, 32), (52, 52)))].mean() > 0.7


def test_a_moved_object_does_not_agree_off_its_ray():
    """Both visits from the same place; a textured object moved 8 px down: the flow follows
    it, but a static point's match cannot leave the pixel, so it does not agree."""
    tex = _texture(1)
    obj = _texture(2, 30, 30) * np.float32(1.2)
    before = _plane_photo(tex, 0.0)
    after = before.copy()
    before[40:70, 60:90] = obj
    after[48:78, 60:90] = obj
    agree = photos_agree(_key(before), _key(after, 0.0, 1))
    assert agree is not None
    assert agree[50:66, 66:84].mean() < 0.1  # the object's core, where it overlaps itself
    assert agree[90:110, 20:140].mean() > 0.8  # the plane away from it


def test_pairs_too_far_apart_say_nothing():
    tex = _texture(0)
    own = _plane_photo(tex, 0.0)
    # unrelated content: no consistent matches on any ray, or none at all
    other = _plane_photo(_texture(5), 0.0)
    got = photos_agree(_key(own), _key(other, 0.0, 1))
    assert got is None or got.mean() < 0.05
    # poses that disagree with the photos: the other camera is said to be 1 m up, the photo
    # was taken 10 cm to the right (its matches lie 50 px off every ray's image)
    lied = Camera(W, H, F, F, W / 2, H / 2, np.array(
        [[1, 0, 0, 0.1], [0, 1, 0, -1.0], [0, 0, 1, 0], [0, 0, 0, 1]], float))
    far = KeyPhoto(1, lied, np.full((H, W), Z, np.float32), _plane_photo(tex, 0.1), ("p", 1))
    assert photos_agree(_key(own), far) is None
    assert not agreeing(_key(own), [far]).any()
    # with a pair that does agree, the union keeps it
    near = _key(_plane_photo(tex, 0.1), 0.1, 1)
    assert agreeing(_key(own), [far, near]).mean() > 0.7


def test_nearest_photos_by_place_and_direction():
    own = _key(_texture(0)[:, :W], 0.0)
    turned = np.eye(4)
    turned[:3, :3] = cv2.Rodrigues(np.array([0.0, np.radians(60), 0.0]))[0]
    views = [_key(own.photo, x, 1) for x in (0.8, 0.1, 0.3, -0.05)]
    views.append(KeyPhoto(1, Camera(W, H, F, F, W / 2, H / 2, turned), own.depth, own.photo))
    got = nearest_photos(own, views, n=3)
    assert [v.camera.center[0] for v in got] == [-0.05, 0.1, 0.3]  # nearest first
    assert all(v is not views[4] for v in nearest_photos(own, views, n=5))  # turned 60 deg away


def test_where_the_depth_is_trusted_a_match_must_lie_at_it():
    """The other visit 20 cm to the right (the plane shifts 10 px); a textured object moved
    6 px to the left between the visits, along its pixels' rays' images: as if it stood at
    5/8 of its depth. Where the rendered depth is not trusted that is a static point nearer
    than drawn (it agrees); where both times' photos agree on the depth it is not."""
    tex = _texture(1)
    obj = _texture(3, 30, 30) * np.float32(1.2)
    own = _plane_photo(tex, 0.0)
    other = _plane_photo(tex, 0.2)
    own[40:70, 60:90] = obj
    other[40:70, 44:74] = obj  # static it would stand at 50:80
    core = (slice(48, 62), slice(68, 82))
    loose = photos_agree(_key(own), _key(other, 0.2, 1))
    assert loose[core].mean() > 0.8
    trusted = np.ones((H, W), bool)
    tight = photos_agree(_key(own), _key(other, 0.2, 1), trusted=trusted)
    assert tight[core].mean() < 0.1
    assert tight[90:110, 20:140].mean() > 0.8  # the plane, at its depth, still agrees
    a, b = _camera(0.0), _camera(0.1)
    col, row = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    at_inf = np.stack([col, row], -1)
    assert np.allclose(ray_segment_distance(a, b, np.full((H, W), Z), at_inf, 0.95, 1.05),
                       5.0 / 1.05, atol=1e-6)  # from the far end: 5 / 1.05 px
