"""Sealed images wherever they fall in the byte dataset's chunks: the writer seals an image
straight into the chunk buffer when it fits there, and through a side buffer when it crosses a
chunk boundary or is larger than a chunk. Every case must store the same documented payload:
read back whole with the identity, clean under ``verify`` (the checksums cover the ciphertext),
and opened by the third-party unsealer from plain h5py."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from protocol.sealing import OVERHEAD_BYTES, generate_identity
from protocol.session import CameraInfo, SessionReader, SessionWriter
from tests.protocol import spec_unsealer

T0_NS = 1_770_000_000_000_000_000
CHUNK_BYTES = 64 << 10
SERIAL = 7
CAMERA = CameraInfo(
    camera_serial=SERIAL,
    node_id="orin-a",
    resolution="HD1200",
    width=1920,
    height=1200,
    fps_nominal=30.0,
    encoding="jpeg",
)


def _jpeg(rng: np.random.Generator, size: int) -> bytes:
    return b"\xff\xd8" + rng.bytes(size) + b"\xff\xd9"


@pytest.fixture(scope="module")
def site():
    return generate_identity("site-chunks")


def test_images_in_a_chunk_across_chunks_and_larger_than_one_open_as_documented(tmp_path, site):
    rng = np.random.default_rng(5)
    # sizes chosen so that images fill a chunk exactly, fit, cross a boundary, and exceed one
    sizes = [100, 3000, CHUNK_BYTES - 3100 - 3 * (4 + OVERHEAD_BYTES), 5000, 20_000, 7000, 1]
    sizes += [int(s) for s in rng.integers(1, 3 * CHUNK_BYTES, 40)]
    written = []
    path = tmp_path / "chunks.h5"
    with SessionWriter(
        path,
        session_name="chunks",
        case_metadata={"patient": "Jane Doe"},
        cameras=[CAMERA],
        tolerance_ns=1,
        software_version="test",
        started_unix_ns=T0_NS,
        blob_chunk_bytes=CHUNK_BYTES,
        recipients=[site.recipient],
    ) as w:
        for row, size in enumerate(sizes):
            pair = (_jpeg(rng, size), _jpeg(rng, max(1, size // 3)))
            w.append_frame(
                SERIAL,
                left=pair[0],
                right=pair[1],
                capture_unix_ns=T0_NS + row,
                host_receive_unix_ns=0,
                recorder_receive_unix_ns=0,
                frame_index=row,
                seq=row,
                ptp_offset_ns=0,
                ptp_locked=True,
            )
            written.append(pair)
            if row % 4 == 3:  # flushes write the unfinished chunk between in-place seals
                w.flush()
    with SessionReader(path, identity=site) as r:
        assert r.verify() == []
        for row, pair in enumerate(written):
            assert r.frame_bytes(SERIAL, row) == pair
    with h5py.File(path, "r") as f:
        uid, key = spec_unsealer.unwrap(f["sealing/key_block"][:].tobytes(), site.text())
        g = f[f"cameras/{SERIAL}"]
        for side, k in (("left", 0), ("right", 1)):
            blob = g[f"{side}_bytes"][:].tobytes()
            for row, pair in enumerate(written):
                o, n = int(g[f"{side}_offset"][row]), int(g[f"{side}_length"][row])
                assert n == len(pair[k]) + OVERHEAD_BYTES
                opened = spec_unsealer.open_payload(
                    key,
                    uid,
                    blob[o : o + n],
                    field="image",
                    camera_serial=SERIAL,
                    row=int(g["sealed_row"][row]),
                    side=k,
                    capture_unix_ns=int(g["capture_unix_ns"][row]),
                )
                assert opened == pair[k]
