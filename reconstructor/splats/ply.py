"""Gaussian splat files: the INRIA 3DGS PLY that viewers read, and the compact ``.splat``.

**PLY** (format version ``PLY_FORMAT_VERSION``, written by ``write_ply``)::

    ply
    format binary_little_endian 1.0
    comment egosurg gaussian splats, format 1
    comment written by egosurg <version>
    element vertex <N>
    property float x            (then y z nx ny nz f_dc_0 f_dc_1 f_dc_2)
    property float f_rest_0     (... f_rest_<3K-1>, only for SH degree > 0)
    property float opacity      (then scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3)
    end_header
    <N records of float32, little endian, in that order>

Values are raw model parameters: opacity as a logit, scales as natural logs, the quaternion as
w, x, y, z (not normalised, unless ``unit_quats``: files for viewers and case models are
written with unit quaternions); normals are zero. ``f_rest`` is channel-major: the K coefficients of
red, then those of green, then blue (3DGS's ``features_rest.transpose(1, 2).flatten(1)``).
``read_ply`` reads any PLY with this vertex layout (any SH degree; binary little/big endian or
ascii; other properties and elements are ignored).

**.splat** (antimatter15's web viewer format, written by ``write_splat``): no header, 32 bytes
per splat: position 3 × float32, exp(scale) 3 × float32, RGBA 4 × uint8 (colour of the SH dc
term and sigmoid(opacity), × 255, rounded and clipped), rotation 4 × uint8 (w x y z of
q / ‖q‖ · 128 + 128, rounded and clipped). Splats are sorted by decreasing
exp(scale_0 + scale_1 + scale_2) · sigmoid(opacity) (volume times opacity), as antimatter15's
``convert.py`` does, so a viewer that streams the file shows the big, opaque splats first.
(gsplat's exporter sorts by Morton code instead; viewers re-sort by depth every frame, so either
order renders the same once loaded.)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

from protocol import __version__
from reconstructor.errors import SplatFormatError
from reconstructor.splats.gaussians import SH_C0, Gaussians

log = logging.getLogger(__name__)

PLY_FORMAT_VERSION = 1
SPLAT_RECORD_BYTES = 32
BASE_PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
TAIL_PROPERTIES = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
REQUIRED = tuple(p for p in BASE_PROPERTIES + TAIL_PROPERTIES if p not in ("nx", "ny", "nz"))
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
MAX_HEADER_LINES = 10_000


def ply_property_names(sh_degree: int) -> list[str]:
    """The vertex properties of an INRIA splat PLY of this SH degree, in file order."""
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return [*BASE_PROPERTIES, *(f"f_rest_{i}" for i in range(n_rest)), *TAIL_PROPERTIES]


def write_ply(path: Path | str, gaussians: Gaussians, *, unit_quats: bool = False) -> Path:
    """The INRIA PLY; ``unit_quats`` writes each quaternion scaled to length 1 (what a file
    for viewers must hold: training leaves lengths of 0.74-1.06, and viewers assume 1)."""
    p = Path(path)
    g = _numpy(unit_quaternions(gaussians) if unit_quats else gaussians)
    n = len(g["means_m"])
    k = g["sh_rest"].shape[1]
    rest = g["sh_rest"].transpose(0, 2, 1).reshape(n, 3 * k)  # (N, K, 3) -> channel-major
    normals = np.zeros((n, 3), np.float32)
    opacity = g["opacity_logits"][:, None]
    parts = [g["means_m"], normals, g["sh_dc"], rest, opacity, g["log_scales"], g["quats_wxyz"]]
    table = np.concatenate(parts, axis=1).astype("<f4")
    names = ply_property_names(gaussians.sh_degree)
    properties = [f"property float {name}" for name in names]
    comment = f"egosurg gaussian splats, format {PLY_FORMAT_VERSION}"
    _write_binary(p, [comment], n, properties, np.ascontiguousarray(table).tobytes())
    log.info("wrote %d splats (SH degree %d) to %s", n, gaussians.sh_degree, p)
    return p


def write_points_ply(path: Path | str, points_m: np.ndarray, colours: np.ndarray) -> Path:
    """A coloured point cloud as binary PLY (x, y, z float; red, green, blue uchar), the form
    open3d, CloudCompare and MeshLab read. ``colours`` are in 0..1."""
    p = Path(path)
    n = len(points_m)
    table = np.empty(n, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    table["xyz"] = points_m
    table["rgb"] = np.clip(np.rint(np.asarray(colours, np.float32) * 255), 0, 255)
    properties = [f"property float {a}" for a in "xyz"]
    properties += [f"property uchar {c}" for c in ("red", "green", "blue")]
    _write_binary(p, [], n, properties, table.tobytes())
    return p


def _write_binary(
    path: Path, comments: list[str], count: int, properties: list[str], body: bytes
) -> None:
    """A binary little-endian PLY of one ``vertex`` element: header, then ``body``."""
    header = [
        "ply",
        "format binary_little_endian 1.0",
        *(f"comment {c}" for c in comments),
        f"comment written by egosurg {__version__}",
        f"element vertex {count}",
        *properties,
        "end_header",
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(body)


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type); type "list" for list properties


def read_ply(path: Path | str) -> Gaussians:
    p = Path(path)
    try:
        f = p.open("rb")
    except FileNotFoundError:
        raise SplatFormatError(f"{p}: no such splat file") from None
    with f:
        fmt, elements = _read_header(f, p)
        table = _read_vertices(f, p, fmt, elements)
    names = list(table.dtype.names or ())
    missing = [name for name in REQUIRED if name not in names]
    if missing:
        raise SplatFormatError(
            f"{p}: not a Gaussian splat PLY: its vertices lack {', '.join(missing)} (they have "
            f"{', '.join(names)}). A plain point cloud is not a splat file; export the splats "
            "(egosurg writes them with reconstructor.splats.ply.write_ply)"
        )
    rest = sorted(int(n[7:]) for n in names if n.startswith("f_rest_") and n[7:].isdigit())
    k, extra = divmod(len(rest), 3)
    if extra or rest != list(range(len(rest))) or not _is_square(k + 1):
        raise SplatFormatError(
            f"{p}: {len(rest)} f_rest properties do not form 3 x ((d+1)^2 - 1) SH coefficients "
            "numbered from f_rest_0; the file is damaged or not an INRIA splat PLY"
        )
    n = len(table)

    def cols(*keys: str) -> torch.Tensor:
        out = np.zeros((n, len(keys)), np.float32)
        for i, key in enumerate(keys):
            out[:, i] = table[key]
        return torch.from_numpy(out)

    sh_rest = cols(*(f"f_rest_{i}" for i in rest)).reshape(n, 3, k).transpose(1, 2)
    return Gaussians(
        means_m=cols("x", "y", "z"),
        quats_wxyz=cols("rot_0", "rot_1", "rot_2", "rot_3"),
        log_scales=cols("scale_0", "scale_1", "scale_2"),
        opacity_logits=cols("opacity")[:, 0].contiguous(),
        sh_dc=cols("f_dc_0", "f_dc_1", "f_dc_2"),
        sh_rest=sh_rest.contiguous(),
    )


def _read_header(f: BinaryIO, path: Path) -> tuple[str, list[_Element]]:
    first = f.readline(16).rstrip(b"\r\n")
    if first != b"ply":
        raise SplatFormatError(
            f"{path}: not a PLY file (it starts with {first[:8]!r}, a PLY starts with 'ply'); "
            "give a Gaussian splat .ply"
        )
    fmt = ""
    elements: list[_Element] = []
    for _ in range(MAX_HEADER_LINES):
        raw = f.readline(4096)
        if not raw:
            break
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            if not fmt:
                raise SplatFormatError(f"{path}: PLY header has no 'format' line")
            return fmt, elements
        try:
            if words[0] == "format":
                fmt = words[1]
                if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                    raise SplatFormatError(f"{path}: unknown PLY format {fmt!r}")
            elif words[0] == "element":
                elements.append(_Element(words[1], int(words[2]), []))
            elif words[0] == "property":
                if words[1] == "list":
                    elements[-1].properties.append((words[4], "list"))
                else:
                    elements[-1].properties.append((words[2], _PLY_TYPES[words[1]]))
        except (IndexError, KeyError, ValueError):
            raise SplatFormatError(
                f"{path}: malformed PLY header line {raw.decode('ascii', 'replace').strip()!r}"
            ) from None
    raise SplatFormatError(f"{path}: PLY header has no 'end_header' line; the file is damaged")


def _read_vertices(f: BinaryIO, path: Path, fmt: str, elements: list[_Element]) -> np.ndarray:
    skip_records = 0
    skip_bytes = 0
    for el in elements:
        lists = [name for name, kind in el.properties if kind == "list"]
        if el.name == "vertex":
            if lists:
                raise SplatFormatError(
                    f"{path}: vertex property {lists[0]!r} is a list; a splat PLY has none"
                )
            order = "<" if fmt != "binary_big_endian" else ">"
            dtype = np.dtype([(name, order + kind) for name, kind in el.properties])
            return _read_table(f, path, fmt, dtype, el.count, skip_records, skip_bytes)
        if lists and fmt != "ascii":
            raise SplatFormatError(
                f"{path}: element {el.name!r} with list properties comes before the vertices; "
                "write the vertex element first"
            )
        skip_records += el.count
        skip_bytes += el.count * sum(np.dtype(kind).itemsize for _, kind in el.properties)
    raise SplatFormatError(f"{path}: PLY has no 'vertex' element, so it holds no splats")


def _read_table(
    f: BinaryIO, path: Path, fmt: str, dtype: np.dtype, n: int, skip_lines: int, skip_bytes: int
) -> np.ndarray:
    if fmt == "ascii":
        lines = f.read().decode("ascii", errors="replace").splitlines()[skip_lines:]
        rows = [line.split() for line in lines[:n]]
        if len(rows) < n or any(len(r) != len(dtype.names or ()) for r in rows):
            raise SplatFormatError(f"{path}: ascii PLY has fewer or shorter vertex lines than {n}")
        values = np.asarray(rows, dtype=np.float64)
        table = np.empty(n, dtype=dtype)
        for i, name in enumerate(dtype.names or ()):
            table[name] = values[:, i]
        return table
    f.seek(skip_bytes, 1)
    data = f.read(n * dtype.itemsize)
    if len(data) != n * dtype.itemsize:
        raise SplatFormatError(
            f"{path}: file ends after {len(data) // max(dtype.itemsize, 1)} of {n} splats; it "
            "was cut short (copy it again)"
        )
    return np.frombuffer(data, dtype=dtype, count=n)


def write_splat(path: Path | str, gaussians: Gaussians) -> Path:
    """The ``.splat`` file (see the module docstring for the layout and the sort order)."""
    p = Path(path)
    g = _numpy(gaussians)
    n = len(g["means_m"])
    opacity = 1.0 / (1.0 + np.exp(-g["opacity_logits"].astype(np.float64)))
    size = np.exp(g["log_scales"].astype(np.float64).sum(axis=1))
    order = np.argsort(-size * opacity, kind="stable")
    rgb = 0.5 + SH_C0 * g["sh_dc"].astype(np.float64)
    rgba = np.concatenate([rgb, opacity[:, None]], axis=1)
    q = g["quats_wxyz"].astype(np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    rec = np.empty(n, dtype=SPLAT_DTYPE)
    rec["position"] = g["means_m"]
    rec["scale"] = np.exp(g["log_scales"].astype(np.float64))
    rec["rgba"] = np.clip(np.rint(rgba * 255.0), 0, 255)
    rec["rot"] = np.clip(np.rint(q * 128.0 + 128.0), 0, 255)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(rec[order].tobytes())
    log.info("wrote %d splats to %s", n, p)
    return p


SPLAT_DTYPE = np.dtype(
    [("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)]
)


def read_splat(path: Path | str) -> Gaussians:
    """A ``.splat`` file back as Gaussians (SH degree 0; colour, opacity and rotation keep only
    their 8-bit precision)."""
    p = Path(path)
    data = p.read_bytes()
    if len(data) % SPLAT_RECORD_BYTES:
        raise SplatFormatError(
            f"{p}: {len(data)} bytes is not a whole number of 32-byte splats; not a .splat file"
        )
    rec = np.frombuffer(data, dtype=SPLAT_DTYPE)
    rgba = rec["rgba"].astype(np.float64) / 255.0
    alpha = np.clip(rgba[:, 3], 0.5 / 255, 1 - 0.5 / 255)
    f32 = torch.float32
    return Gaussians(
        means_m=torch.as_tensor(rec["position"].copy(), dtype=f32),
        quats_wxyz=torch.as_tensor((rec["rot"].astype(np.float64) - 128.0) / 128.0, dtype=f32),
        log_scales=torch.as_tensor(np.log(rec["scale"].astype(np.float64)), dtype=f32),
        opacity_logits=torch.as_tensor(np.log(alpha / (1 - alpha)), dtype=f32),
        sh_dc=torch.as_tensor((rgba[:, :3] - 0.5) / SH_C0, dtype=f32),
        sh_rest=torch.zeros((len(rec), 0, 3), dtype=f32),
    )


def unit_quaternions(gaussians: Gaussians) -> Gaussians:
    """The same Gaussians with each quaternion scaled to length 1 (the rotation is unchanged;
    a zero quaternion becomes the identity)."""
    q = gaussians.quats_wxyz.detach()
    norm = q.norm(dim=1, keepdim=True)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype, device=q.device)
    unit = torch.where(norm > 1e-12, q / norm.clamp_min(1e-12), identity)
    return Gaussians(**{**gaussians.parameters_dict(), "quats_wxyz": unit})


def _numpy(g: Gaussians) -> dict[str, np.ndarray]:
    return {k: v.detach().cpu().to(torch.float32).numpy() for k, v in g.parameters_dict().items()}


def _is_square(v: int) -> bool:
    return math.isqrt(v) ** 2 == v
