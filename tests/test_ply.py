"""PLY io: SfM point clouds and Gaussians in the standard 3DGS layout."""

import numpy as np
import pytest
import torch
from plyfile import PlyData

from gdiff.errors import SceneError
from gdiff.splat.gaussians import Gaussians
from gdiff.splat.ply import read_gaussians, read_points, write_gaussians, write_points


def _random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    q = torch.randn(n, 4, generator=g)
    return Gaussians(means=torch.randn(n, 3, generator=g),
                     quats=q / q.norm(dim=-1, keepdim=True),
                     scales=torch.rand(n, 3, generator=g) * 0.1 + 1e-3,
                     opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
                     sh=torch.randn(n, k, 3, generator=g), sh_degree=degree)


@pytest.mark.parametrize("degree, n", [(0, 257), (1, 257), (3, 257), (3, 0)])
def test_gaussians_round_trip(tmp_path, degree, n):
    # n = 0: an empty part (e.g. no Gaussian changed at one time) is still a valid file
    g = _random_gaussians(n, degree)
    path = tmp_path / "g.ply"
    write_gaussians(path, g)
    back = read_gaussians(path)
    assert back.sh_degree == degree
    for name in ("means", "quats", "scales", "opacities", "sh"):
        a, b = getattr(g, name), getattr(back, name)
        assert a.shape == b.shape, name
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5), name


def test_gaussian_ply_has_the_3dgs_layout(tmp_path):
    g = _random_gaussians(5, 3)
    write_gaussians(tmp_path / "g.ply", g)
    ply = PlyData.read(str(tmp_path / "g.ply"))
    assert ply.text is False and ply.byte_order == "<"
    names = [p.name for p in ply["vertex"].properties]
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert names == expected
    assert all(p.val_dtype in ("f4", "float32", "float") for p in ply["vertex"].properties)
    v = ply["vertex"].data
    # stored as logit / log / channel-major rest coefficients
    np.testing.assert_allclose(v["opacity"], torch.logit(g.opacities).numpy(), rtol=1e-4,
                               atol=1e-4)
    np.testing.assert_allclose(v["scale_1"], g.scales[:, 1].log().numpy(), rtol=1e-5)
    np.testing.assert_allclose(v["f_rest_0"], g.sh[:, 1, 0].numpy(), rtol=1e-6)  # red, coeff 1
    np.testing.assert_allclose(v["f_rest_15"], g.sh[:, 1, 1].numpy(), rtol=1e-6)  # green
    np.testing.assert_allclose(v["f_rest_44"], g.sh[:, 15, 2].numpy(), rtol=1e-6)  # blue, 15


def test_points_round_trip_uint8_and_float(tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(100, 3))
    rgb = rng.integers(0, 256, size=(100, 3)).astype(np.uint8)
    write_points(tmp_path / "p.ply", xyz, rgb)
    x2, c2 = read_points(tmp_path / "p.ply")
    np.testing.assert_allclose(x2, xyz, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(c2 * 255, rgb, atol=1e-3)
    write_points(tmp_path / "q.ply", xyz, rgb / 255.0)
    _, c3 = read_points(tmp_path / "q.ply")
    np.testing.assert_allclose(c3, c2, atol=1 / 255)


def test_points_ascii_without_colour(tmp_path):
    path = tmp_path / "a.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                    "property float y\nproperty float z\nend_header\n0 0 0\n1 2 3\n")
    xyz, rgb = read_points(path)
    assert xyz.shape == (2, 3) and np.allclose(rgb, 0.5)


def test_points_errors_name_the_file(tmp_path):
    with pytest.raises(SceneError, match="missing.ply"):
        read_points(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_text("not a ply")
    with pytest.raises(SceneError, match="bad.ply"):
        read_points(bad)
    empty = tmp_path / "empty.ply"
    write_points(empty, np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(SceneError, match="empty"):
        read_points(empty)
