"""The splat files a viewer opens: the INRIA 3DGS PLY byte for byte, the compact ``.splat``,
and clear errors for files that are not splats."""

from __future__ import annotations

import math
import struct

import numpy as np
import open3d as o3d
import pytest
import torch

from protocol.errors import UserError
from reconstructor.errors import SplatFormatError
from reconstructor.splats.gaussians import SH_C0, Gaussians
from reconstructor.splats.ply import read_ply, read_splat, write_ply, write_splat

INRIA_DEGREE_0 = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
]  # fmt: skip


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    return Gaussians(
        means_m=torch.randn(n, 3, generator=g) * 2,
        quats_wxyz=torch.randn(n, 4, generator=g),
        log_scales=torch.rand(n, 3, generator=g) * 4 - 6,
        opacity_logits=torch.randn(n, generator=g) * 3,
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.randn(n, k, 3, generator=g) * 0.3,
    )


def header_and_body(data: bytes) -> tuple[list[str], bytes]:
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end].decode("ascii").splitlines(), data[end:]


def bits(t: torch.Tensor) -> np.ndarray:
    return t.detach().numpy().astype(np.float32).view(np.uint32)


@pytest.mark.parametrize("degree", [0, 3])
def test_ply_round_trip_is_bit_exact(tmp_path, degree):
    g = random_gaussians(64, degree)
    back = read_ply(write_ply(tmp_path / "s.ply", g))
    assert back.sh_degree == degree and back.num == 64
    for name, tensor in g.parameters_dict().items():
        got = back.parameters_dict()[name]
        assert got.dtype == torch.float32 and got.shape == tensor.shape, name
        assert np.array_equal(bits(got), bits(tensor)), name


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_header_lists_exactly_the_inria_properties(tmp_path, degree):
    path = write_ply(tmp_path / "s.ply", random_gaussians(5, degree))
    lines, body = header_and_body(path.read_bytes())
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "comment egosurg gaussian splats, format 1" in lines
    assert "element vertex 5" in lines
    props = [line.split() for line in lines if line.startswith("property")]
    assert all(p[1] == "float" for p in props)
    n_rest = 3 * ((degree + 1) ** 2 - 1)
    expected = [*INRIA_DEGREE_0[:9], *(f"f_rest_{i}" for i in range(n_rest)), *INRIA_DEGREE_0[9:]]
    assert [p[2] for p in props] == expected
    assert len(body) == 5 * 4 * len(expected)


def test_one_vertex_byte_for_byte(tmp_path):
    """Vertex 2's 62 floats packed with struct from the model, in the INRIA order: f_rest is
    channel-major (all of red's 15 coefficients, then green's, then blue's)."""
    g = random_gaussians(4, 3, seed=7)
    path = write_ply(tmp_path / "s.ply", g)
    _, body = header_and_body(path.read_bytes())
    i, k = 2, 15
    values = [float(v) for v in g.means_m[i]] + [0.0, 0.0, 0.0]
    values += [float(v) for v in g.sh_dc[i]]
    values += [float(g.sh_rest[i, j, c]) for c in range(3) for j in range(k)]
    values += [float(g.opacity_logits[i])] + [float(v) for v in g.log_scales[i]]
    values += [float(v) for v in g.quats_wxyz[i]]
    stride = 4 * len(values)
    assert len(values) == 62
    assert body[i * stride : (i + 1) * stride] == struct.pack("<62f", *values)


def test_ascii_ply_with_extra_properties_reads(tmp_path):
    lines = [
        "ply",
        "format ascii 1.0",
        "comment made by another tool",
        "element vertex 2",
        *(f"property float {p}" for p in INRIA_DEGREE_0[:9]),
        *(f"property float f_rest_{i}" for i in range(9)),  # degree 1: K = 3 per channel
        "property uchar red",  # ignored
        *(f"property float {p}" for p in INRIA_DEGREE_0[9:]),
        "end_header",
        "1 2 3 0 0 0 0.1 0.2 0.3 7 8 9 10 11 12 13 14 15 255 -2 -3 -4 -5 1 0 0 0",
        "4 5 6 0 0 0 0.4 0.5 0.6 0 0 0 0 0 0 0 0 0 0 0.5 -1 -1 -1 0.5 0.5 0.5 0.5",
    ]
    path = tmp_path / "a.ply"
    path.write_text("\n".join(lines) + "\n")
    g = read_ply(path)
    assert g.sh_degree == 1 and g.num == 2
    assert g.means_m[1].tolist() == [4.0, 5.0, 6.0]
    # channel-major in the file: red's 3 coefficients, then green's, then blue's
    assert g.sh_rest[0].tolist() == [[7.0, 10.0, 13.0], [8.0, 11.0, 14.0], [9.0, 12.0, 15.0]]
    assert g.opacity_logits.tolist() == [-2.0, 0.5]
    assert g.quats_wxyz[1].tolist() == [0.5, 0.5, 0.5, 0.5]


def test_big_endian_ply_reads(tmp_path):
    g = random_gaussians(6, 1, seed=9)
    lines, body = header_and_body(write_ply(tmp_path / "le.ply", g).read_bytes())
    lines[1] = "format binary_big_endian 1.0"
    swapped = np.frombuffer(body, "<f4").astype(">f4").tobytes()
    path = tmp_path / "be.ply"
    path.write_bytes(("\n".join(lines) + "\n").encode() + swapped)
    back = read_ply(path)
    for name, tensor in g.parameters_dict().items():
        assert np.array_equal(bits(back.parameters_dict()[name]), bits(tensor)), name


def test_splat_file_layout_order_and_precision(tmp_path):
    g = random_gaussians(300, 0, seed=3)
    path = write_splat(tmp_path / "s.splat", g)
    data = path.read_bytes()
    assert len(data) == 32 * 300
    recs = [struct.unpack("<3f3f4B4B", data[o : o + 32]) for o in range(0, len(data), 32)]
    pos = np.array([r[0:3] for r in recs], np.float32)
    # match records back to the model by their exact float32 positions
    index = {tuple(p): i for i, p in enumerate(g.means_m.numpy())}
    order = [index[tuple(p)] for p in pos]
    assert sorted(order) == list(range(300))

    scales = np.exp(g.log_scales.numpy().astype(np.float64))
    alpha = 1 / (1 + np.exp(-g.opacity_logits.numpy().astype(np.float64)))
    key = scales.prod(axis=1) * alpha
    assert np.all(np.diff(key[order]) <= 1e-12 * key.max())  # biggest, most opaque first

    got_scale = np.array([r[3:6] for r in recs])
    np.testing.assert_allclose(got_scale, scales[order], rtol=1e-6)
    rgba = np.array([r[6:10] for r in recs]) / 255.0
    rgb = np.clip(0.5 + SH_C0 * g.sh_dc.numpy()[order], 0, 1)
    assert np.abs(rgba[:, :3] - rgb).max() <= 0.5 / 255 + 1e-9
    assert np.abs(rgba[:, 3] - alpha[order]).max() <= 0.5 / 255 + 1e-9
    q = g.quats_wxyz.numpy()[order].astype(np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    got_q = (np.array([r[10:14] for r in recs]) - 128) / 128
    assert np.abs(got_q - q).max() <= 1 / 128 + 1e-9  # clipping at 255 costs up to 1/128

    back = read_splat(path)
    assert back.num == 300 and back.sh_degree == 0
    np.testing.assert_array_equal(back.means_m.numpy(), pos)
    np.testing.assert_allclose(back.colors().numpy(), rgba[:, :3], atol=1e-6)


def test_point_cloud_ply_is_not_a_splat_file(tmp_path):
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.random.default_rng(0).uniform(size=(10, 3)))
    pcd.colors = o3d.utility.Vector3dVector(np.full((10, 3), 0.5))
    path = tmp_path / "cloud.ply"
    assert o3d.io.write_point_cloud(path, pcd)
    with pytest.raises(SplatFormatError) as exc:
        read_ply(path)
    msg = str(exc.value)
    assert "cloud.ply" in msg and "not a Gaussian splat PLY" in msg
    assert "f_dc_0" in msg and "opacity" in msg and "rot_3" in msg
    assert "red" in msg  # what the file does have
    assert isinstance(exc.value, UserError) and isinstance(exc.value, ValueError)


def test_other_bad_files_say_what_is_wrong(tmp_path):
    splat = write_splat(tmp_path / "s.splat", random_gaussians(3, 0))
    with pytest.raises(SplatFormatError, match=r"s\.splat: not a PLY file"):
        read_ply(splat)
    with pytest.raises(SplatFormatError, match="no such splat file"):
        read_ply(tmp_path / "missing.ply")

    good = write_ply(tmp_path / "g.ply", random_gaussians(10, 1)).read_bytes()
    cut = tmp_path / "cut.ply"
    cut.write_bytes(good[:-50])
    with pytest.raises(SplatFormatError, match="after 9 of 10 splats; it was cut short"):
        read_ply(cut)

    lines, body = header_and_body(good)
    odd = tmp_path / "odd.ply"  # drop f_rest_8: 8 coefficients are not 3 x ((d+1)^2 - 1)
    kept = [line for line in lines if line != "property float f_rest_8"]
    odd.write_bytes(("\n".join(kept) + "\n").encode() + body)
    with pytest.raises(SplatFormatError, match="8 f_rest properties"):
        read_ply(odd)

    with pytest.raises(SplatFormatError, match="not a whole number of 32-byte splats"):
        read_splat(cut)


def test_empty_model_round_trips(tmp_path):
    g = random_gaussians(0, 0)
    assert read_ply(write_ply(tmp_path / "e.ply", g)).num == 0
    assert write_splat(tmp_path / "e.splat", g).stat().st_size == 0
    assert math.isclose(SH_C0, 0.28209479, rel_tol=1e-8)


def test_the_fused_point_cloud_file_reads_back_in_open3d(tmp_path):
    import open3d as o3d

    from reconstructor.splats.ply import write_points_ply

    rng = np.random.default_rng(1)
    points, colours = rng.normal(size=(500, 3)).astype(np.float32), rng.random((500, 3))
    cloud = o3d.io.read_point_cloud(str(write_points_ply(tmp_path / "points.ply", points, colours)))
    assert np.array_equal(np.asarray(cloud.points, np.float32), points)
    np.testing.assert_allclose(np.asarray(cloud.colors), colours, atol=0.5 / 255 + 1e-6)
