"""The HDF5 datasets a session file is made of, for ``protocol.session.write``: ``Blob``, an
append-only byte dataset written one whole chunk at a time through the file's ``ChunkSink``;
``CameraWriter``, one camera's frame tables and its two blobs; and the helpers that create the
tables and blobs and append a flush's rows with low-level calls (``docs/session.md``, layout).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import h5py
import numpy as np
import xxhash

from protocol.session.chunk_sink import DIRECT_ALIGN_BYTES, ChunkSink
from protocol.session.format import (
    FRAME_COLUMNS,
    TABLE_CHUNK_ROWS,
    CameraInfo,
    SessionWriteError,
)

_MIN_BLOB_GROWTH = 4 << 20
_MAX_BLOB_GROWTH = 64 << 20
_MAX_LENGTH = int(np.iinfo(np.uint32).max)


class Blob:
    """An append-only byte dataset, written one whole chunk at a time; its extent is a capacity.

    A chunk is assembled in a buffer lent by the file's ``ChunkSink``; when it is full, the
    sink writes it at the chunk's place in the file from its own thread. The dataset allocates
    its chunks when it grows (``H5D_ALLOC_TIME_EARLY``), so HDF5 knows that place before the
    bytes exist. ``flush`` writes what the unfinished last chunk gained since its last flush, in
    whole disk blocks (zeros past the data); the chunk is written whole when it fills, with the
    same leading bytes, so what a reader may already see never changes. (Writing the whole
    chunk at every flush cost 1 MiB per camera side and flush: 40 MiB/s more disk writes at the
    full rig with a flush every 0.2 s.)
    """

    def __init__(self, ds: h5py.Dataset, sink: ChunkSink) -> None:
        self.ds = ds
        self.sink = sink
        self.chunk = int(ds.chunks[0])
        self.capacity = 0  # the dataset's extent
        self.logical_end = 0  # bytes appended
        self.chunk_start = 0  # where the buffer's chunk starts in the dataset
        self.buffer: np.ndarray | None = None  # the unfinished chunk, lent by the sink
        self.fill = 0  # bytes of data in the buffer
        self.flushed = 0  # bytes of the buffer's chunk already written by a flush
        self.zero_from = 0  # buffer[max(fill, zero_from):] is all zeros

    def append(self, data: Any) -> tuple[int, int, int]:
        """Append one image; (offset, length, XXH3-64 of its bytes)."""
        src = np.frombuffer(data, dtype=np.uint8)
        n = src.size
        if n > _MAX_LENGTH:
            raise ValueError(f"an image of {n} bytes is larger than the 4 GiB a row can hold")
        # ~8 us for a 0.5 MB JPEG, ~0.25 ms for a 7 MB raw HD1200 image (docs/session.md)
        digest = xxhash.xxh3_64_intdigest(src.data)
        offset = self.logical_end
        chunk, pos = self.chunk, 0
        while pos < n:
            if self.buffer is None:
                self.buffer = self.sink.take_buffer()
                self.zero_from = chunk  # old contents
                self.flushed = 0
            step = min(n - pos, chunk - self.fill)
            self.buffer[self.fill : self.fill + step] = src[pos : pos + step]
            self.fill += step
            pos += step
            self.logical_end += step
            if self.fill == chunk:
                self.sink.submit(self.buffer, self._file_offset())
                self.buffer = None
                self.chunk_start += chunk
                self.fill = 0
        return offset, n, digest

    def reserve(self, n: int) -> memoryview | None:
        """The next ``n`` bytes of the unfinished chunk, to be filled in place and then
        ``commit``-ted (a sealed image is encrypted straight into it); None when they do not
        fit in what is left of the chunk (``append`` a copy instead)."""
        if self.buffer is None:
            if n > self.chunk:
                return None
            self.buffer = self.sink.take_buffer()
            self.zero_from = self.chunk  # old contents
            self.flushed = 0
        if n > self.chunk - self.fill:
            return None
        return memoryview(self.buffer)[self.fill : self.fill + n]  # type: ignore[arg-type]

    def commit(self, n: int) -> tuple[int, int, int]:
        """Keep the ``n`` bytes written into ``reserve(n)``: (offset, length, XXH3-64), as
        ``append`` returns for the same bytes."""
        assert self.buffer is not None and n <= self.chunk - self.fill
        digest = xxhash.xxh3_64_intdigest(self.buffer[self.fill : self.fill + n].data)
        offset = self.logical_end
        self.fill += n
        self.logical_end += n
        if self.fill == self.chunk:
            self.sink.submit(self.buffer, self._file_offset())
            self.buffer = None
            self.chunk_start += self.chunk
            self.fill = 0
        return offset, n, digest

    def flush_partial(self) -> None:
        """Write the unfinished chunk (call after ``sink.drain()``), then flush the dataset."""
        # (the last block again even with nothing new: a failing disk shows at every flush)
        if self.fill and self.buffer is not None:
            if self.zero_from > self.fill:  # no stale bytes of an earlier chunk in the file
                self.buffer[self.fill : self.zero_from] = 0
            self.zero_from = self.fill
            # whole blocks, as direct I/O needs (the buffer is page-aligned, so is its slice)
            start = self.flushed // DIRECT_ALIGN_BYTES * DIRECT_ALIGN_BYTES
            end = min(_round_up(self.fill, DIRECT_ALIGN_BYTES), self.chunk)
            if end > start:
                self.sink.write_now(self.buffer[start:end], self._file_offset() + start)
            self.flushed = self.fill
        self.ds.flush()

    def _file_offset(self) -> int:
        """Where the current chunk lives in the file, growing the dataset if it must."""
        end = self.chunk_start + self.chunk
        if end > self.capacity:
            # Growth allocates the chunks in the file at once (on disk only once written), so it
            # is bounded: at most _MAX_BLOB_GROWTH stays unused past the end of a recording.
            step = min(max(self.capacity // 8, _MIN_BLOB_GROWTH), _MAX_BLOB_GROWTH)
            self.capacity = _round_up(max(end, self.capacity + step), self.chunk)
            self.ds.resize((self.capacity,))
        info = self.ds.id.get_chunk_info_by_coord((self.chunk_start,))
        if info.byte_offset is None:
            raise SessionWriteError(
                f"{self.ds.name}: HDF5 did not allocate the chunk at {self.chunk_start}"
            )
        return int(info.byte_offset)


class CameraWriter:
    def __init__(
        self,
        group: h5py.Group,
        info: CameraInfo,
        blob_chunk_bytes: int,
        sink: ChunkSink,
        columns: dict[str, type[np.generic]] = FRAME_COLUMNS,
    ) -> None:
        self.info = info
        self.columns = columns  # FRAME_COLUMNS, or SEALED_FRAME_COLUMNS in a sealed session
        self.tables = {name: create_table(group, name, dtype) for name, dtype in columns.items()}
        self.left = Blob(_create_blob(group, "left_bytes", blob_chunk_bytes), sink)
        self.right = Blob(_create_blob(group, "right_bytes", blob_chunk_bytes), sink)
        self.pending: list[tuple[int, ...]] = []
        self.rows = 0  # appended
        self.rows_in_file = 0
        self.missing_frames = 0
        self.gap_records = 0


def _round_up(n: int, multiple: int) -> int:
    return -(-n // multiple) * multiple


def create_table(group: h5py.Group, name: str, dtype: type[np.generic] | np.dtype) -> h5py.Dataset:
    return group.create_dataset(
        name, shape=(0,), maxshape=(None,), chunks=(TABLE_CHUNK_ROWS,), dtype=dtype
    )


def _create_blob(group: h5py.Group, name: str, chunk_bytes: int) -> h5py.Dataset:
    """An extendable byte dataset whose chunks are allocated in the file as it grows (so their
    place is known before they are written) and never filled by HDF5 (the writer fills them)."""
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk((chunk_bytes,))
    dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
    dcpl.set_fill_time(h5py.h5d.FILL_TIME_NEVER)
    space = h5py.h5s.create_simple((0,), (h5py.h5s.UNLIMITED,))
    h5py.h5d.create(group.id, name.encode(), h5py.h5t.NATIVE_UINT8, space, dcpl=dcpl)
    return group[name]


def append_rows(ds: h5py.Dataset, start: int, end: int, values: np.ndarray) -> None:
    """Grow a table to ``end`` rows and write ``values`` (its dtype) into rows ``start:end``.

    Low-level calls: for a flush's few rows, h5py's slicing costs more than the write.
    """
    dsid = ds.id
    dsid.set_extent((end, *values.shape[1:]))
    fspace = dsid.get_space()
    fspace.select_hyperslab((start,) + (0,) * (values.ndim - 1), values.shape)
    dsid.write(h5py.h5s.create_simple(values.shape), fspace, np.ascontiguousarray(values))


def append_table_rows(
    tables: Mapping[str, h5py.Dataset],
    columns: Mapping[str, Any],
    start: int,
    rows: Sequence[Sequence[Any]],
) -> None:
    """Write ``rows`` (tuples in ``columns``' order) column by column into ``tables`` from row
    ``start``, each column as its dtype in ``columns``; then flush every table."""
    if rows:
        end = start + len(rows)
        for (name, dtype), col in zip(columns.items(), zip(*rows, strict=True), strict=True):
            append_rows(tables[name], start, end, np.asarray(col, dtype=dtype))
    for ds in tables.values():
        ds.flush()
