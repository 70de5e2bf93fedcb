"""INRIA .ply: exact round trips at every SH degree, and agreement with plyfile (an independent PLY library)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from virgi_ns.errors import InputError
from virgi_ns.gaussians import Gaussians
from virgi_ns.io import load_splat, save_ply


def _plyfile():
    """plyfile, the independent reader and writer (a test dependency: an install without the test extras skips
    only the tests that use it)."""
    return pytest.importorskip("plyfile")


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Gaussians(r(n, 3) * 3, r(n, 3) - 4, r(n, 4), r(n) * 2, r(n, (degree + 1) ** 2, 3))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_write_then_read_is_exact(tmp_path, degree):
    g = random_gaussians(257, degree, seed=degree)
    save_ply(g, tmp_path / "a.ply")
    h = load_splat(tmp_path / "a.ply")
    assert h.sh_degree == degree and len(h) == 257
    for name in ("means", "scales", "quats", "opacities", "sh"):
        assert torch.equal(getattr(g, name), getattr(h, name)), name


def test_written_file_matches_inria_layout_read_by_plyfile(tmp_path):
    g = random_gaussians(50, 2)
    save_ply(g, tmp_path / "a.ply")
    v = _plyfile().PlyData.read(str(tmp_path / "a.ply"))["vertex"].data
    np.testing.assert_array_equal(v["x"], g.means[:, 0].numpy())
    np.testing.assert_array_equal(v["rot_0"], g.quats[:, 0].numpy())  # w first
    np.testing.assert_array_equal(v["opacity"], g.opacities.numpy())
    np.testing.assert_array_equal(v["f_dc_1"], g.sh[:, 0, 1].numpy())
    # f_rest is channel-major: 8 red coefficients, then 8 green, then 8 blue
    np.testing.assert_array_equal(v["f_rest_0"], g.sh[:, 1, 0].numpy())
    np.testing.assert_array_equal(v["f_rest_9"], g.sh[:, 2, 1].numpy())
    np.testing.assert_array_equal(v["f_rest_23"], g.sh[:, 8, 2].numpy())


def _plyfile_write(path, cols: dict[str, np.ndarray], byte_order: str = "<") -> None:
    arr = np.empty(len(next(iter(cols.values()))), dtype=[(k, v.dtype.str) for k, v in cols.items()])
    for k, v in cols.items():
        arr[k] = v
    plyfile = _plyfile()
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")], byte_order=byte_order).write(str(path))


def _inria_cols(n: int, degree: int, dtype=np.float32) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * ((degree + 1) ** 2 - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return {k: rng.normal(size=n).astype(dtype) for k in names}


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_reads_file_written_by_plyfile_with_extra_properties(tmp_path, byte_order):
    cols = _inria_cols(20, 3)
    cols = {"nx": np.zeros(20, np.float32), **cols, "filter_3D": np.ones(20, np.float32)}
    _plyfile_write(tmp_path / "a.ply", cols, byte_order)
    g = load_splat(tmp_path / "a.ply")
    assert g.sh_degree == 3
    np.testing.assert_array_equal(g.means[:, 2].numpy(), cols["z"])
    np.testing.assert_array_equal(g.quats[:, 3].numpy(), cols["rot_3"])
    np.testing.assert_array_equal(g.sh[:, 15, 0].numpy(), cols["f_rest_14"])  # last red coefficient
    np.testing.assert_array_equal(g.sh[:, 1, 1].numpy(), cols["f_rest_15"])  # first green coefficient


def test_double_properties_are_accepted(tmp_path):
    cols = _inria_cols(5, 1, np.float64)
    _plyfile_write(tmp_path / "a.ply", cols)
    g = load_splat(tmp_path / "a.ply")
    assert g.dtype == torch.float32
    np.testing.assert_allclose(g.opacities.numpy(), cols["opacity"], rtol=1e-6)


def test_mesh_ply_is_refused_naming_missing_properties(tmp_path):
    _plyfile_write(tmp_path / "mesh.ply", {k: np.zeros(3, np.float32) for k in ("x", "y", "z", "red")})
    with pytest.raises(InputError, match="lack f_dc_0"):
        load_splat(tmp_path / "mesh.ply")


def test_odd_f_rest_count_is_refused(tmp_path):
    cols = _inria_cols(4, 0)
    cols.update({f"f_rest_{i}": np.zeros(4, np.float32) for i in range(4)})
    _plyfile_write(tmp_path / "a.ply", cols)
    with pytest.raises(InputError, match="f_rest"):
        load_splat(tmp_path / "a.ply")


def test_nan_rows_are_counted_or_dropped(tmp_path):
    g = random_gaussians(10, 0)
    g.means[3, 1] = float("nan")
    g.sh[7, 0, 2] = float("inf")
    save_ply(g, tmp_path / "a.ply")
    with pytest.raises(InputError, match=r"2 of 10 Gaussians hold NaN or Inf values \(rows 3, 7\)"):
        load_splat(tmp_path / "a.ply")
    h = load_splat(tmp_path / "a.ply", drop_invalid=True)
    keep = [i for i in range(10) if i not in (3, 7)]
    assert torch.equal(h.means, g.means[keep])


@pytest.mark.parametrize("fmt", ["ply", "compressed", "spz2", "spz3", "spz4"])
def test_empty_and_tiny_scenes_round_trip_to_writable_tensors(fmt):
    from virgi_ns.io import decode_splat
    from virgi_ns.io.compressed_ply import compressed_ply_bytes
    from virgi_ns.io.ply import inria_ply_bytes
    from virgi_ns.io.spz import spz_bytes

    encode = {"ply": inria_ply_bytes, "compressed": compressed_ply_bytes, "spz2": lambda g: spz_bytes(g, 2),
              "spz3": lambda g: spz_bytes(g, 3), "spz4": lambda g: spz_bytes(g, 4)}[fmt]
    for n in (0, 1):
        h = decode_splat(encode(random_gaussians(n, 1)))
        assert len(h) == n and h.sh_degree == 1
        for name in ("means", "scales", "quats", "opacities", "sh"):
            getattr(h, name).add_(1.0)  # not a view of a read-only file buffer
