"""The splat files' vertex is the reference 3D Gaussian splatting layout (Kerbl et al. 2023's
training code, SH degree 3), read back with plyfile rather than physmorph's reader: 62 float32
properties in the reference order, the normals and the higher SH coefficients (f_rest) zero. The
SIBR viewer refuses a file without f_rest and Unity's importer expects the 62-float vertex."""

import numpy as np
from plyfile import PlyData

from physmorph.reports.export.splats import DEFAULT_RGB, RENDER_OPACITY, SH_C0, read_splats, write_splats

# The reference layout, spelled out (gaussian_model.py's construct_list_of_attributes for SH degree 3).
REFERENCE = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(45)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
SIGMA0 = 0.4


def _small_splats(tmp_path):  # (path, x [N, 3], F [N, 3, 3]) of a few stretched, rotated Gaussians
    rng = np.random.default_rng(5)
    x = rng.normal(size=(7, 3))
    F = np.eye(3) + 0.3 * rng.normal(size=(7, 3, 3))
    return write_splats(tmp_path / "small.ply", x, F, SIGMA0), x, F


def test_the_vertex_is_the_reference_layout_of_62_float32(tmp_path):
    assert len(REFERENCE) == 62 and len(set(REFERENCE)) == 62
    path, x, _ = _small_splats(tmp_path)
    ply = PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"] and not ply.text and ply.byte_order == "<"
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == REFERENCE
    assert [p.val_dtype for p in vertex.properties] == ["f4"] * 62  # PLY type float (32 bits)
    assert vertex.data.dtype.names == tuple(REFERENCE)
    assert all(vertex.data.dtype[k] == np.dtype("<f4") for k in REFERENCE)
    assert vertex.data.dtype.itemsize == 62 * 4 and vertex.count == len(x)
    for k in ["nx", "ny", "nz"] + [f"f_rest_{i}" for i in range(45)]:
        assert np.all(vertex.data[k] == 0.0), k


def test_the_reference_layout_keeps_what_the_viewers_draw(tmp_path):
    """Means, flat colour, opacity and covariance read back as written, by plyfile and by read_splats."""
    path, x, F = _small_splats(tmp_path)
    v = PlyData.read(str(path))["vertex"].data
    np.testing.assert_allclose(np.stack([v[k] for k in "xyz"], axis=1), x, atol=1e-6)
    rgb = 0.5 + SH_C0 * np.stack([v[f"f_dc_{i}"].astype(np.float64) for i in range(3)], axis=1)
    np.testing.assert_allclose(rgb, np.broadcast_to(DEFAULT_RGB, (len(x), 3)), atol=1e-6)
    np.testing.assert_allclose(1.0 / (1.0 + np.exp(-v["opacity"].astype(np.float64))), RENDER_OPACITY, atol=1e-6)
    back = read_splats(path)
    expected = SIGMA0 ** 2 * F @ np.swapaxes(F, 1, 2)
    rel = np.linalg.norm(back["cov"] - expected, axis=(1, 2)) / np.linalg.norm(expected, axis=(1, 2))
    assert rel.max() <= 1e-5 and np.allclose(back["x"], x, atol=1e-6)
