"""EXR read/write: exact channel dtypes and values, frame sRGB<->linear conversion."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from gdiff.errors import SceneError
from gdiff.exr import FRAME_COMPRESSIONS, read_exr, read_frame, write_exr, write_frame
from gdiff.io import srgb_to_linear


def _exr_header_channels(path):
    """Parse the channel list of an EXR file directly from its bytes (OpenEXR file layout:
    magic, version, then attributes name\\0 type\\0 size value ... terminated by \\0)."""
    data = open(path, "rb").read()
    assert struct.unpack("<I", data[:4])[0] == 20000630  # EXR magic number
    pos, chans = 8, {}
    while data[pos] != 0:
        name_end = data.index(b"\0", pos)
        name = data[pos:name_end].decode()
        type_end = data.index(b"\0", name_end + 1)
        typ = data[name_end + 1:type_end].decode()
        size = struct.unpack("<i", data[type_end + 1:type_end + 5])[0]
        value = data[type_end + 5:type_end + 5 + size]
        if name == "channels":
            assert typ == "chlist"
            p = 0
            while value[p] != 0:
                e = value.index(b"\0", p)
                cname = value[p:e].decode()
                pixel_type = struct.unpack("<i", value[e + 1:e + 5])[0]
                chans[cname] = {0: "UINT", 1: "HALF", 2: "FLOAT"}[pixel_type]
                p = e + 1 + 16
        pos = type_end + 5 + size
    return chans


def test_exr_roundtrip_exact_dtypes(tmp_path):
    rng = np.random.default_rng(0)
    H, W = 7, 11
    chans = {
        "R": rng.random((H, W)).astype(np.float16),
        "G": (rng.random((H, W)) * 40).astype(np.float16),
        "B": rng.random((H, W)).astype(np.float16),
        "A": rng.random((H, W)).astype(np.float16),
        "Z": (rng.random((H, W)) * 100).astype(np.float32),
        "id": rng.integers(0, 2**32 - 1, (H, W), dtype=np.uint32),
    }
    m = np.arange(16, dtype=np.float32).reshape(4, 4)
    write_exr(tmp_path / "f.exr", chans, attributes={"worldToCamera": m, "gdiff_path": "p1"})
    back, header = read_exr(tmp_path / "f.exr", with_header=True)
    assert set(back) == set(chans)
    for k, v in chans.items():
        assert back[k].dtype == v.dtype, k
        assert np.array_equal(back[k], v), k  # lossless (ZIP) and exact
    assert np.array_equal(header["worldToCamera"], m) and header["gdiff_path"] == "p1"
    # the file itself declares the pixel types, as any EXR reader sees them
    assert _exr_header_channels(tmp_path / "f.exr") == {
        "A": "HALF", "B": "HALF", "G": "HALF", "R": "HALF", "Z": "FLOAT", "id": "UINT"}
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files left


def test_exr_float64_and_int_conversion_and_errors(tmp_path):
    z = np.linspace(0, 1, 12).reshape(3, 4)
    write_exr(tmp_path / "a.exr", {"Z": z, "n": np.arange(12).reshape(3, 4)})
    b = read_exr(tmp_path / "a.exr")
    assert b["Z"].dtype == np.float32 and np.allclose(b["Z"], z)
    assert b["n"].dtype == np.uint32 and np.array_equal(b["n"], np.arange(12).reshape(3, 4))
    with pytest.raises(ValueError, match="shape"):
        write_exr(tmp_path / "b.exr", {"R": np.zeros((3, 4), np.float16),
                                       "G": np.zeros((4, 3), np.float16)})
    with pytest.raises(ValueError, match="uint32"):
        write_exr(tmp_path / "b.exr", {"n": -np.ones((2, 2), np.int64)})
    with pytest.raises(SceneError, match="not found"):
        read_exr(tmp_path / "missing.exr")
    (tmp_path / "bad.exr").write_bytes(b"not an exr at all")
    with pytest.raises(SceneError, match="cannot be read"):
        read_exr(tmp_path / "bad.exr")


def test_frame_roundtrip_linear_on_disk(tmp_path):
    rng = np.random.default_rng(1)
    H, W = 9, 13
    rgb = rng.random((H, W, 3)).astype(np.float32)
    alpha = rng.random((H, W, 1)).astype(np.float32)
    depth = (1 + 5 * rng.random((H, W))).astype(np.float32)
    write_frame(tmp_path / "00000.exr", rgb, alpha, depth)
    raw = read_exr(tmp_path / "00000.exr")
    assert {k: v.dtype for k, v in raw.items()} == {
        "R": np.float16, "G": np.float16, "B": np.float16, "A": np.float16, "Z": np.float32}
    # on disk: linear values (half precision)
    lin = srgb_to_linear(rgb)
    assert np.allclose(raw["G"].astype(np.float32), lin[..., 1], rtol=1e-3, atol=1e-4)
    assert np.array_equal(raw["Z"], depth)
    rgb2, a2, d2 = read_frame(tmp_path / "00000.exr")
    assert rgb2.dtype == a2.dtype == d2.dtype == np.float32
    assert rgb2.shape == (H, W, 3) and a2.shape == (H, W) and d2.shape == (H, W)
    # half precision on linear values: within 1/255 of the sRGB input everywhere
    assert np.abs(rgb2 - rgb).max() < 1.0 / 255.0
    assert np.abs(a2 - alpha[..., 0]).max() < 1e-3
    assert np.array_equal(d2, depth)


def test_read_frame_requires_all_channels(tmp_path):
    write_exr(tmp_path / "x.exr", {"R": np.zeros((2, 2), np.float16)})
    with pytest.raises(SceneError, match="lacks channel"):
        read_frame(tmp_path / "x.exr")


@pytest.fixture(scope="module")
def rendered_frame(synth_tiny_scene):
    """A ground-truth render of the tiny synthetic scene: sRGB colour, alpha, z-depth."""
    cam = synth_tiny_scene.cameras("before")[0]
    r = synth_tiny_scene.render(cam, "before", supersample=1)
    alpha = np.ones(r["depth"].shape, np.float32)
    alpha[:, :7] = np.linspace(0, 1, 7, dtype=np.float32)  # a soft edge, as a render has
    return r["rgb"].astype(np.float32), alpha, r["depth"].astype(np.float32)


@pytest.mark.parametrize("compression", sorted(FRAME_COMPRESSIONS))
def test_frame_compressions_read_back_within_stored_precision(tmp_path, rendered_frame,
                                                              compression):
    rgb, alpha, depth = rendered_frame
    write_frame(tmp_path / "none.exr", rgb, alpha, depth, compression="none")
    write_frame(tmp_path / "c.exr", rgb, alpha, depth, compression=compression.upper(),
                dwa_level=45.0)
    ref, c = read_exr(tmp_path / "none.exr"), read_exr(tmp_path / "c.exr", with_header=True)
    ch, header = c
    # alpha (half) and depth (float32) are bit-exact with every frame compression
    assert ch["A"].dtype == np.float16 and np.array_equal(ch["A"], ref["A"])
    assert ch["Z"].dtype == np.float32 and np.array_equal(ch["Z"], ref["Z"])
    assert np.array_equal(ch["Z"], depth)
    rgb2, _, _ = read_frame(tmp_path / "c.exr")
    if FRAME_COMPRESSIONS[compression]:  # lossless: the stored half colour exactly
        assert all(np.array_equal(ch[k], ref[k]) for k in "RGB")
    else:  # DWA: close to the stored colour (mean well below one 8-bit step)
        err = np.abs(np.clip(rgb2, 0, 1) - np.clip(rgb, 0, 1))
        assert err.mean() < 0.5 / 255 and np.quantile(err, 0.99) < 3 / 255, err.max()
    assert str(header["compression"]).upper().endswith(
        "NO_COMPRESSION" if compression == "none" else f"{compression.upper()}_COMPRESSION")
    if compression != "none":
        assert (tmp_path / "c.exr").stat().st_size < (tmp_path / "none.exr").stat().st_size


def test_frame_compression_sizes_rank(tmp_path, rendered_frame):
    """Lossy colour (DWA) is smaller than the lossless codecs on a rendered frame."""
    rgb, alpha, depth = rendered_frame
    size = {}
    for c in ("zip", "piz", "dwaa"):
        write_frame(tmp_path / f"{c}.exr", rgb, alpha, depth, compression=c)
        size[c] = (tmp_path / f"{c}.exr").stat().st_size
    assert size["dwaa"] < min(size["zip"], size["piz"])
    with pytest.raises(ValueError, match="compression must be one of"):
        write_frame(tmp_path / "x.exr", rgb, alpha, depth, compression="pxr24")
