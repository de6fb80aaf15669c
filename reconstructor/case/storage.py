"""Compact storage of a warm-started case: each chain's keyframe once, each later timestamp as
its changes to the one before (docs/case.md, "Compact storage").

Warm start keeps Gaussians in order: timestamp t+1's model is t's Gaussians that were kept (in
t's order) followed by the ones seeded new. So t+1 is stored as

- ``alive``: which of t's rows it kept (a bit per row, ``np.packbits``);
- ``diff``: for the kept rows, the change of each quantised value since t (mostly zero);
- ``new``: the seeded rows, quantised in full.

A keyframe has no parent: every row is ``new``. Values are quantised on a fixed grid per
parameter (``QuantSteps``); a value is re-sent only when it moved more than one step from the
value its parent stores (closed loop: the comparison is against what a reader decodes, so the
error never grows along a chain), so every stored value is within one step of the trained one.
Quaternions are normalised first (the rotation is the same; viewers want unit length). Integer
tables are zigzag-coded, split into byte planes and compressed with zlib, where the many zeros
and small changes cost almost nothing.

File (``models/<name>.npz``, a NumPy ``.npz`` read with ``allow_pickle=False``): ``meta`` (UTF-8
JSON: ``format`` ``egosurg-splat-store``, ``format_version``, ``n``, ``sh_degree``, ``steps``
per column, ``parent`` ``{model, xxh3_64, bytes, n}`` or null, and ``points`` ``{n, step_m}``
when the file holds them), ``alive``, ``diff``, ``new``, and optionally ``points``.
The child names its parent's checksum, so a parent that was redone or damaged is found.

``points`` are what the timestamp's stereo pairs observed (``depth/evidence.py``: every
occupied 2 cm cell of stereo's own points, no filled ones, no cap; cases made before
2026-11-29 hold the training cloud instead: filled and capped), on a ``POINTS_STEP_M`` grid,
sorted, packed like ``new``: the observed geometry, which a warm model carries forward and
training moves, so the sterile-field tool reads these (``load_points``). ``points_noise``, in
the same order, is each point's depth change per pixel of disparity (``evidence.Observed.
m_per_px``) on a ``NOISE_STEP_M`` grid (``meta.points.noise_step_m``; absent in older cases:
``load_evidence`` gives None). ``points_seen_by``, in the same order, is each point's bitmask
of the stereo cameras that saw its cell (``evidence.Observed.seen_by``; bit ``i`` is
``meta.points.cameras[i]``, the left sensors' names ``SN<serial>``; absent in older cases:
``load_observation`` gives None). A reader that does not know them ignores them (same format
version).

``load_model(case, entry)`` reads any done entry (a compact file, or the full PLY of older
cases) after checking its checksum and its parents'; replay and ``egosurg case export`` use it.

A sealed session's case stores each model as ``models/<name>.npz.sealed``: the same file,
sealed for the session's recipients (``protocol.sealing.derived``, role ``model``, bound to
``<name>``) in memory before it is written. Every function here takes the case's ``seal``
(``reconstructor/case/sealing.py``); the index's checksum is over the sealed bytes, so it is
checked without a key, and a parent is named by its sealed file's checksum.
"""

from __future__ import annotations

import io
import json
import logging
import zipfile
import zlib
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from threading import Lock
from typing import Any

import numpy as np
import torch

from protocol.durable import atomic_write_bytes
from protocol.sealing import SealedPayloadError
from protocol.sealing.derived import DerivedSeal, is_sealed_file
from reconstructor.case.index import Entry, checksum_file
from reconstructor.errors import CaseStorageError
from reconstructor.splats import ply
from reconstructor.splats.gaussians import Gaussians

log = logging.getLogger(__name__)

STORE_FORMAT = "egosurg-splat-store"
STORE_FORMAT_VERSION = 1
SUFFIX = ".npz"
SEALED_SUFFIX = ".npz.sealed"  # a sealed session's case: the same file, sealed
POINTS_STEP_M = 2.0**-8  # 3.9 mm: the sterile tool's voxels are 5 cm
NOISE_STEP_M = 2.0**-9  # 2 mm of depth per pixel (0.4 mm at 0.2 px): 0.05-0.5 m/px in a room
_MAX_INFLATE_RATIO = 1032  # deflate's most: a stream of N bytes inflates to at most ~1032 N
_CACHE_SIZE = 4  # decoded models kept: a chain is read forward, each from the one before


@dataclass(frozen=True, kw_only=True)
class QuantSteps:
    """The grid step of each parameter; every stored value is within one step of the trained
    one. Chosen so that the error is far below what a render shows (measured in docs/case.md):
    0.24 mm of position (a pixel is about 8 mm at 3 m at SVGA), 0.8 % of scale, 0.002 of
    opacity, 0.3 of a grey level of colour. Half these steps cost 12 % more bytes for no
    measurable PSNR (BENCHMARKS.md)."""

    position_m: float = 2.0**-12
    quat: float = 2.0**-10  # of a unit quaternion: about 2e-3 rad of rotation
    log_scale: float = 2.0**-7
    opacity_logit: float = 2.0**-7  # sigmoid's slope is at most 1/4
    sh_dc: float = 2.0**-8  # colour = 0.5 + 0.282 sh_dc: 1.1e-3 per step
    sh_rest: float = 2.0**-7

    def columns(self, sh_degree: int) -> np.ndarray:
        """(C,) the step of each column of a quantised table (``_columns`` order)."""
        k = 3 * ((sh_degree + 1) ** 2 - 1)
        return np.array(
            [self.position_m] * 3 + [self.quat] * 4 + [self.log_scale] * 3
            + [self.opacity_logit] + [self.sh_dc] * 3 + [self.sh_rest] * k
        )  # fmt: skip


@dataclass(frozen=True)
class Stored:
    """A stored model as its integer grid values, (N, C) int64 in ``_columns`` order."""

    q: np.ndarray
    sh_degree: int
    steps: np.ndarray  # (C,)

    @property
    def num(self) -> int:
        return len(self.q)

    def gaussians(self) -> Gaussians:
        v = (self.q * self.steps).astype(np.float32)
        n, k = len(v), (self.sh_degree + 1) ** 2 - 1
        t = torch.from_numpy
        return Gaussians(
            means_m=t(v[:, 0:3].copy()),
            quats_wxyz=t(v[:, 3:7].copy()),
            log_scales=t(v[:, 7:10].copy()),
            opacity_logits=t(v[:, 10].copy()),
            sh_dc=t(v[:, 11:14].copy()),
            sh_rest=t(v[:, 14:].reshape(n, 3, k).transpose(0, 2, 1).copy()),
        )


def _columns(g: Gaussians) -> np.ndarray:
    """(N, C) float64: means, unit quaternion, log scales, opacity logit, sh_dc, sh_rest
    (channel-major, as the PLY holds it)."""
    u = ply.unit_quaternions(g)
    p = {k: v.detach().cpu().double().numpy() for k, v in u.parameters_dict().items()}
    n = len(p["means_m"])
    rest = p["sh_rest"].transpose(0, 2, 1).reshape(n, -1)
    parts = [p["means_m"], p["quats_wxyz"], p["log_scales"], p["opacity_logits"][:, None]]
    return np.concatenate([*parts, p["sh_dc"], rest], axis=1)


def encode(
    g: Gaussians,
    parent: Stored | None = None,
    alive: np.ndarray | None = None,
    steps: QuantSteps | None = None,
) -> Stored:
    """The model on the grid. With a parent, ``g``'s first ``alive.sum()`` rows are the
    parent's kept rows (warm start's order); their values stay the parent's unless they moved
    more than one step."""
    values = _columns(g)
    step = (steps or QuantSteps()).columns(g.sh_degree)
    q = np.rint(values / step).astype(np.int64)
    if parent is not None and alive is not None:
        kept = int(alive.sum())
        ref = parent.q[alive]
        hold = np.abs(values[:kept] - ref * step) <= step
        q[:kept] = np.where(hold, ref, q[:kept])
    return Stored(q=q, sh_degree=g.sh_degree, steps=step)


def write_model(
    path: Path,
    g: Gaussians,
    *,
    parent: Stored | None = None,
    parent_ref: dict[str, Any] | None = None,
    alive: np.ndarray | None = None,
    steps: QuantSteps | None = None,
    points_m: np.ndarray | None = None,
    points_noise: np.ndarray | None = None,
    points_seen_by: np.ndarray | None = None,
    points_cameras: tuple[str, ...] | list[str] | None = None,
    seal: DerivedSeal | None = None,
) -> Stored:
    """Store ``g`` at ``path`` (atomically), as changes to ``parent`` when given (with
    ``parent_ref`` = the parent's ``{model, xxh3_64, bytes}`` and ``alive`` = which of the
    parent's rows ``g`` kept, in order, as its first rows), with the timestamp's fused points
    ``points_m`` (M, 3) when given (and ``points_noise`` (M,), each one's metres of depth per
    pixel of disparity, when known; and ``points_seen_by`` (M,), each one's bitmask of the
    cameras ``points_cameras`` that saw it, when known); sealed with ``seal`` (a sealed
    session's; the path then ends ``SEALED_SUFFIX``) in memory, so no plaintext reaches the
    disk. Returns what a reader decodes."""
    if parent is not None:
        if alive is None or parent_ref is None or len(alive) != parent.num:
            raise ValueError("a delta needs the parent's reference and one alive flag per row")
        if int(alive.sum()) > g.num or parent.sh_degree != g.sh_degree:
            raise ValueError("the model does not start with the parent's kept rows")
    stored = encode(g, parent, alive, steps)
    kept = int(alive.sum()) if parent is not None and alive is not None else 0
    meta = {
        "format": STORE_FORMAT,
        "format_version": STORE_FORMAT_VERSION,
        "n": stored.num,
        "sh_degree": stored.sh_degree,
        "steps": stored.steps.tolist(),
        "parent": None if parent is None else {**(parent_ref or {}), "n": parent.num},
    }
    arrays = {
        "alive": np.packbits(alive) if alive is not None else np.zeros(0, np.uint8),
        "diff": _pack(stored.q[:kept] - parent.q[alive]) if parent is not None else _pack(None),
        "new": _pack(stored.q[kept:]),
    }
    if points_m is not None:
        grid, order = _points_grid(points_m)
        meta["points"] = {"n": len(grid), "step_m": POINTS_STEP_M}
        arrays["points"] = _pack(grid)
        if points_noise is not None:
            noise = np.asarray(points_noise, np.float64).reshape(-1)
            if len(noise) != len(np.asarray(points_m).reshape(-1, 3)):
                raise ValueError("points_noise needs one value per point")
            q = np.rint(noise[order] / NOISE_STEP_M).astype(np.int64)
            meta["points"]["noise_step_m"] = NOISE_STEP_M
            arrays["points_noise"] = _pack(q[:, None])
        if points_seen_by is not None:
            masks = np.asarray(points_seen_by).reshape(-1)
            cameras = list(points_cameras or ())
            if len(masks) != len(np.asarray(points_m).reshape(-1, 3)):
                raise ValueError("points_seen_by needs one mask per point")
            if not cameras or len(cameras) > 31 or (masks.size and masks.max() >> len(cameras)):
                raise ValueError("points_seen_by needs the cameras its bits name (at most 31)")
            meta["points"]["cameras"] = cameras
            arrays["points_seen_by"] = _pack(masks[order].astype(np.int64)[:, None])
    arrays = {"meta": np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for key, value in arrays.items():
            # a fixed entry time (np.savez stamps the clock): the same model, the same bytes
            with zf.open(zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0)), "w") as f:
                np.lib.format.write_array(f, value, allow_pickle=False)
    data = buf.getvalue()
    if seal is not None:
        data = seal.seal("model", model_name(path.name), data)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, data)
    return stored


def model_name(file_name: str) -> str:
    """The timestamp a model file is of (``t00012.000`` of ``t00012.000.npz.sealed``): the
    name a sealed model is bound to."""
    for suffix in (SEALED_SUFFIX, SUFFIX, ".ply"):
        if file_name.endswith(suffix):
            return file_name[: -len(suffix)]
    return file_name


def _source(path: Path, seal: DerivedSeal | None) -> Path | io.BytesIO:
    """What to read a model file from: the file, or (in a sealed case) its opened bytes. A
    sealed file in a plaintext case, or a plaintext one in a sealed case, is refused."""
    with path.open("rb") as f:
        sealed = is_sealed_file(f.read(4))
    if seal is None:
        if sealed:
            raise CaseStorageError(
                f"{path} is sealed (a sealed session's case): open the case with --identity "
                "FILE; if its case.json no longer names the recipients, restore it"
            )
        return path
    if not sealed:
        raise CaseStorageError(
            f"{path} is not sealed, but its case's session is; rerun the case's reconstruct "
            "command, which redoes it sealed"
        )
    try:
        return io.BytesIO(seal.open("model", model_name(path.name), path.read_bytes(), str(path)))
    except SealedPayloadError as exc:
        raise CaseStorageError(str(exc)) from None


def _points_grid(points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((M, 3) int64 grid values of the finite points, sorted (neighbours pack into small
    numbers), (M,) which input point each row is)."""
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    finite = np.nonzero(np.isfinite(pts).all(axis=1))[0]
    grid = np.rint(pts[finite] / POINTS_STEP_M).astype(np.int64)
    order = np.lexsort(grid.T[::-1]) if len(grid) else np.zeros(0, np.int64)
    grid = grid[order]
    if len(grid):
        grid[1:, 0] = np.diff(grid[:, 0])  # x is sorted: store its steps
    return grid, finite[order]


def load_points(
    case: Path | str, entry: Entry, seal: DerivedSeal | None = None
) -> np.ndarray | None:
    """(M, 3) float64: the observed points stored with a done entry, after checking its
    checksum; None for a model stored without them (a PLY, or a case made before they were
    stored)."""
    evidence = load_evidence(case, entry, seal)
    return None if evidence is None else evidence[0]


def load_evidence(
    case: Path | str, entry: Entry, seal: DerivedSeal | None = None
) -> tuple[np.ndarray, np.ndarray | None] | None:
    """((M, 3) float64 points, (M,) float64 metres of depth per pixel of disparity or None
    where the case did not store them) of a done entry, after checking its checksum; None for
    a model stored without points."""
    seen = load_observation(case, entry, seal)
    return None if seen is None else (seen.points_m, seen.m_per_px)


@dataclass(frozen=True)
class StoredEvidence:
    """What a done entry stores of what its stereo pairs saw (``depth/evidence.py``):
    ``points_m`` (M, 3) float64; ``m_per_px`` (M,) float64 or None; ``seen_by`` (M,) uint32
    bitmask of ``cameras`` (bit ``i`` is ``cameras[i]``) or None where the case did not store
    them (made before they were kept: unknown, not "no camera")."""

    points_m: np.ndarray
    m_per_px: np.ndarray | None
    seen_by: np.ndarray | None
    cameras: tuple[str, ...]


def stores_seen_by(case: Path | str, entry: Entry, seal: DerivedSeal | None = None) -> bool:
    """Whether a done entry's points carry their cameras (``points_seen_by``): reads only the
    file's ``meta``, after checking its checksum."""
    folder = Path(case)
    if entry.status != "done" or not is_compact(entry):
        return False
    path = _checked(folder, entry.model, entry.xxh3_64, entry.bytes, entry.name)
    try:
        meta = json.loads(_read_arrays(_source(path, seal), ("meta",))["meta"].tobytes())
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as exc:
        raise CaseStorageError(
            f"{path}: its header cannot be read ({exc}); rerun the case's reconstruct "
            "command, which redoes damaged timestamps"
        ) from None
    return bool((meta.get("points") or {}).get("cameras"))


def load_observation(
    case: Path | str, entry: Entry, seal: DerivedSeal | None = None
) -> StoredEvidence | None:
    """The evidence stored with a done entry, after checking its checksum; None for a model
    stored without points."""
    folder = Path(case)
    if entry.status != "done" or not is_compact(entry):
        return None
    path = _checked(folder, entry.model, entry.xxh3_64, entry.bytes, entry.name)
    source = _source(path, seal)  # no identity, or not a recipient's: said as such
    try:
        z = _read_arrays(source, ("meta", "points", "points_noise", "points_seen_by"))
        meta = json.loads(z["meta"].tobytes())
        info = meta.get("points")
        if info is None:
            return None
        n = int(info["n"])
        grid = _unpack(z["points"], n, 3)
        noise = None
        if "noise_step_m" in info:
            noise = _unpack(z["points_noise"], n, 1)[:, 0] * float(info["noise_step_m"])
        cameras = tuple(str(c) for c in info.get("cameras") or ())
        seen_by = None
        if cameras:
            masks = _unpack(z["points_seen_by"], n, 1)[:, 0]
            if masks.size and (masks.min() < 0 or masks.max() >> len(cameras)):
                raise ValueError(f"a camera mask names more than its {len(cameras)} cameras")
            seen_by = masks.astype(np.uint32)
    except (OSError, ValueError, KeyError, TypeError, zlib.error, zipfile.BadZipFile) as exc:
        raise CaseStorageError(
            f"{path}: its stored points cannot be read ({exc}); rerun the case's reconstruct "
            "command, which redoes damaged timestamps"
        ) from None
    grid[:, 0] = np.cumsum(grid[:, 0])
    return StoredEvidence(grid * float(info["step_m"]), noise, seen_by, cameras)


def _pack(table: np.ndarray | None) -> np.ndarray:
    """(N, C) int64 -> zigzag uint32, one byte plane after another, zlib; small magnitudes
    of either sign become runs of zero bytes."""
    if table is None or table.size == 0:
        return np.zeros(0, np.uint8)
    z = ((table << 1) ^ (table >> 63)).astype(np.uint32)
    planes = np.ascontiguousarray(z.T).view(np.uint8).reshape(-1, 4).T
    return np.frombuffer(zlib.compress(planes.tobytes(), 6), np.uint8)


def _unpack(blob: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """The inverse of ``_pack``. The size is the file's claim (``meta``), so it is checked
    before anything is allocated: deflate expands at most ~1032 times, and the stream must
    inflate to exactly ``rows * cols * 4`` bytes (a damaged or crafted file cannot make the
    reader allocate or inflate more than that)."""
    if rows < 0 or cols < 0:
        raise ValueError(f"a table of {rows} x {cols} values")
    if rows * cols == 0:
        return np.zeros((rows, cols), np.int64)
    size = rows * cols * 4
    if size > _MAX_INFLATE_RATIO * blob.size + 64:
        raise ValueError(f"{blob.size} compressed bytes cannot hold the {size} the file claims")
    inflater = zlib.decompressobj()
    data = inflater.decompress(blob.tobytes(), size)
    if len(data) != size or not inflater.eof or inflater.unconsumed_tail:
        raise ValueError(f"the packed table inflates to other than the {size} bytes it claims")
    raw = np.frombuffer(data, np.uint8)
    z = np.ascontiguousarray(raw.reshape(4, -1).T).view(np.uint32).reshape(cols, rows).T
    z = z.astype(np.int64)
    return (z >> 1) ^ -(z & 1)


def _read_arrays(path: Path | io.BytesIO, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The named uint8 arrays of a model file (``points``, ``points_noise`` and
    ``points_seen_by`` may be absent). Every entry must be stored uncompressed in the zip, as
    ``write_model`` writes it, and hold the bytes its header claims, checked before reading: a
    file cannot make the reader allocate more than its own size."""
    out: dict[str, np.ndarray] = {}
    with zipfile.ZipFile(path) as zf:
        for key in keys:
            try:
                info = zf.getinfo(f"{key}.npy")
            except KeyError:
                if key in ("points", "points_noise", "points_seen_by"):
                    continue
                raise
            if info.compress_type != zipfile.ZIP_STORED:
                raise ValueError(f"{key}.npy is compressed in the zip; models store it plain")
            with zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, _fortran, dtype = np.lib.format.read_array_header_1_0(f)
                else:
                    shape, _fortran, dtype = np.lib.format.read_array_header_2_0(f)
                if dtype != np.uint8 or len(shape) != 1:
                    raise ValueError(f"{key}.npy holds {dtype} {shape}, not bytes")
                if shape[0] > info.file_size:
                    raise ValueError(f"{key}.npy claims {shape[0]} bytes in {info.file_size}")
                data = f.read(shape[0])
                if len(data) != shape[0]:
                    raise ValueError(f"{key}.npy is cut short")
            out[key] = np.frombuffer(data, np.uint8)
    return out


def _read_file(
    path: Path, seal: DerivedSeal | None
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    source = _source(path, seal)
    try:
        arrays = _read_arrays(source, ("meta", "alive", "diff", "new"))
        meta = json.loads(arrays["meta"].tobytes())
    except (OSError, ValueError, KeyError, zlib.error, zipfile.BadZipFile) as exc:
        raise CaseStorageError(
            f"{path} cannot be read as a stored model ({exc}); rerun the case's reconstruct "
            "command, which redoes damaged timestamps"
        ) from None
    if not isinstance(meta, dict):
        raise CaseStorageError(f"{path}: its meta is not a JSON object; rerun the case's "
                               "reconstruct command, which redoes damaged timestamps")  # fmt: skip
    if meta.get("format") != STORE_FORMAT or meta.get("format_version") != STORE_FORMAT_VERSION:
        raise CaseStorageError(
            f"{path} is stored as {meta.get('format')} {meta.get('format_version')}; this egosurg "
            f"reads {STORE_FORMAT} {STORE_FORMAT_VERSION}: use the egosurg version that wrote it"
        )
    parent = meta.get("parent")
    missing = [k for k in ("n", "steps", "sh_degree", "parent") if k not in meta]
    if parent is not None and not (
        isinstance(parent, dict)
        and isinstance(parent.get("model"), str)
        and isinstance(parent.get("xxh3_64"), str)
        and isinstance(parent.get("bytes"), int)
    ):
        missing.append("parent's model, xxh3_64 and bytes")
    if missing:
        raise CaseStorageError(
            f"{path}: its meta lacks {', '.join(missing)}; rerun the case's reconstruct "
            "command, which redoes damaged timestamps"
        )
    return meta, arrays


_cache: OrderedDict[tuple[str, str, int, int, bool], Stored] = OrderedDict()
_cache_lock = Lock()


def _checked(folder: Path, model: str, xxh3: str, size: int, name: str) -> Path:
    path = folder / model
    if not path.is_file():
        raise CaseStorageError(
            f"{path} ({name}) is missing; rerun the case's reconstruct command to redo it"
        )
    if checksum_file(path) != (xxh3, size):
        raise CaseStorageError(
            f"{path} ({name}) fails its checksum: it is damaged or cut short; rerun the case's "
            "reconstruct command, which redoes it and the timestamps stored as changes to it"
        )
    return path


def load_stored(
    folder: Path,
    model: str,
    xxh3: str,
    size: int,
    name: str = "",
    seal: DerivedSeal | None = None,
) -> Stored:
    """A compact model and, through its parents, everything it is stored against; each file
    is checked against the checksum that names it (the index's, or its child's), and in a
    sealed case opened with ``seal`` (its identity)."""
    folder = Path(folder)
    chain: list[tuple[tuple[str, str, int, int, bool], dict[str, Any], dict[str, np.ndarray]]]
    chain = []
    ref: tuple[str, str, int] | None = (model, xxh3, size)
    base: Stored | None = None
    while ref is not None:
        path = folder / ref[0]
        try:  # a file rewritten or damaged since it was decoded has another mtime
            mtime_ns = path.stat().st_mtime_ns
        except OSError:
            mtime_ns = -1
        # opened with a seal or not: a plaintext read of a sealed file must fail, not hit
        key = (str(path.resolve()), ref[1], ref[2], mtime_ns, seal is not None)
        with _cache_lock:
            base = _cache.get(key)
        if base is not None:
            break
        path = _checked(folder, *ref, name or Path(ref[0]).stem)
        meta, arrays = _read_file(path, seal)
        chain.append((key, meta, arrays))
        parent = meta["parent"]
        ref = None if parent is None else (parent["model"], parent["xxh3_64"], parent["bytes"])
        name = ""
        if len(chain) > 100_000:
            raise CaseStorageError(f"{folder / model}: its parents form a loop; redo the case")
    for key, meta, arrays in reversed(chain):
        try:
            n, cols = int(meta["n"]), len(meta["steps"])
            steps = np.asarray(meta["steps"], dtype=np.float64)
            if meta["parent"] is None:
                q = _unpack(arrays["new"], n, cols)
            else:
                assert base is not None
                alive = np.unpackbits(arrays["alive"], count=base.num).astype(bool)
                kept = int(alive.sum())
                diff = _unpack(arrays["diff"], kept, cols)
                q = np.concatenate([base.q[alive] + diff, _unpack(arrays["new"], n - kept, cols)])
        except (ValueError, KeyError, TypeError, zlib.error) as exc:
            raise CaseStorageError(
                f"{key[0]} does not decode ({exc}); rerun the case's reconstruct command"
            ) from None
        q.setflags(write=False)
        base = Stored(q=q, sh_degree=int(meta["sh_degree"]), steps=steps)
        with _cache_lock:
            _cache[key] = base
            while len(_cache) > _CACHE_SIZE:
                _cache.popitem(last=False)
    assert base is not None
    return base


def is_compact(entry: Entry) -> bool:
    return entry.model.endswith((SUFFIX, SEALED_SUFFIX))


def load_model(case: Path | str, entry: Entry, seal: DerivedSeal | None = None) -> Gaussians:
    """The model of a done entry, compact or a full PLY (older cases), after checking it and
    the files it is stored against (opened with ``seal`` in a sealed case); one clear error
    line otherwise."""
    folder = Path(case)
    if entry.status != "done" or not entry.model:
        raise CaseStorageError(
            f"{entry.name} is {entry.status}; rerun the case's reconstruct command to make it"
        )
    if is_compact(entry):
        stored = load_stored(folder, entry.model, entry.xxh3_64, entry.bytes, entry.name, seal)
        return stored.gaussians()
    path = _checked(folder, entry.model, entry.xxh3_64, entry.bytes, entry.name)
    _source(path, seal)  # a sealed case holds no PLY: refused in one line
    return ply.read_ply(path)


def entry_is_intact(folder: Path, entry: Entry, seal: DerivedSeal | None = None) -> bool:
    """True when a done entry's file, and every file it is stored against, is there with the
    checksum that names it, and (in a sealed case, ``seal``) is sealed and opens where it is
    (a resume redoes the rest)."""
    try:
        if is_compact(entry):
            load_stored(folder, entry.model, entry.xxh3_64, entry.bytes, entry.name, seal)
        else:
            _source(_checked(folder, entry.model, entry.xxh3_64, entry.bytes, entry.name), seal)
    except CaseStorageError:
        return False
    return entry.status == "done"
