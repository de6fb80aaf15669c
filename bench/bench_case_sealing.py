"""A sealed session's case against a plaintext one: what sealing the models and cached depth
costs (docs/case.md, "Sealed cases").

Two tables, each with the plaintext case as the reference, measured in the same run:

1. Model storage: a model of ``--gaussians`` Gaussians (a keyframe, and a warm timestamp stored
   as its changes) written with ``storage.write_model`` and read back with ``load_model``,
   plaintext and sealed for one recipient; MB/s of the files and the sealed/plaintext ratio.
2. ``egosurg reconstruct --every`` on the same sets of the intraoperative sim (tiny config),
   once from a plaintext session and once from its copy sealed for one recipient, alternating
   ``--repeats`` times, each with a fresh case folder and depth cache; median wall seconds and
   the ratio.

    .venv/bin/python bench/bench_case_sealing.py --sets 4 --repeats 2 --gaussians 200000
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from protocol.sealing import generate_identity
from protocol.sealing.keyfiles import write_identity
from protocol.session import SessionReader, SessionWriter
from protocol.session.derived import derived_seal
from reconstructor.case import storage
from reconstructor.case.index import Entry, checksum_file
from reconstructor.splats.gaussians import Gaussians
from sim.eval_set import EvalSetSpec, write_eval_set

REPO = Path(__file__).resolve().parents[1]
TINY = (
    "train_max_width_px = 96\n[stereo]\nmatch_scale = 0.25\n[fill]\nenabled = false\n"
    "[fusion]\nmax_points = 20000\n[train]\nwarmup_steps = 3\nrefine_steps = 0\n"
    "[auxiliary]\nenabled = false\n"
)


def random_gaussians(n: int, seed: int) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means_m=torch.randn(n, 3, generator=g) * 2,
        quats_wxyz=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 4,
        opacity_logits=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.randn(n, 15, 3, generator=g) * 0.1,
    )


def sealed_copy(source: Path, target: Path, recipient) -> None:
    """``source``'s frames and sets, byte for byte, in a session sealed for ``recipient``."""
    with SessionReader(source) as reader:
        sets, serials = reader.sets(), reader.info.camera_serials
        tables = {s: reader.frame_table(s) for s in serials}
        with SessionWriter(
            target, session_name="bench-sealed", case_metadata={},
            cameras=list(reader.info.cameras), tolerance_ns=reader.info.tolerance_ns,
            software_version="bench", started_unix_ns=reader.info.started_unix_ns,
            recipients=[recipient],
        ) as writer:  # fmt: skip
            for k in range(len(sets.set_unix_ns)):
                members = []
                for column, serial in enumerate(serials):
                    row = int(sets.members[k, column])
                    left, right = reader.frame_bytes(serial, row)
                    t = tables[serial]
                    members.append(writer.append_frame(
                        serial, left=left, right=right,
                        capture_unix_ns=int(t["capture_unix_ns"][row]), host_receive_unix_ns=0,
                        recorder_receive_unix_ns=0, frame_index=int(t["frame_index"][row]),
                        seq=0, ptp_offset_ns=0, ptp_locked=True,
                    ))  # fmt: skip
                writer.append_set(int(sets.set_unix_ns[k]), members, int(sets.spread_ns[k]))
            writer.close(time.time_ns())


def storage_table(n: int, root: Path, seal, repeats: int) -> None:
    """Write and read one model ``repeats`` times each way, alternating (after one untimed
    round: imports and the allocator's first growth are not sealing's cost)."""
    key = random_gaussians(n, 0)
    times: dict[str, tuple[list[float], list[float]]] = {"plaintext": ([], []), "sealed": ([], [])}
    sizes: dict[str, int] = {}
    for r in range(repeats + 1):
        for label, s in (("plaintext", None), ("sealed", seal)):
            folder = root / f"models-{label}"
            suffix = storage.SUFFIX if s is None else storage.SEALED_SUFFIX
            path = folder / f"t{r:05d}.000{suffix}"
            t0 = time.perf_counter()
            storage.write_model(path, key, seal=s)
            write_s = time.perf_counter() - t0
            digest, size = checksum_file(path)
            entry = Entry(name=path.name, t_s=0.0, set_index=0, model=path.name, xxh3_64=digest,
                          bytes=size, status="done")  # fmt: skip
            storage._cache.clear()  # a cold read: the file, not the decoded cache
            t0 = time.perf_counter()
            storage.load_model(folder, entry, s)
            read_s = time.perf_counter() - t0
            sizes[label] = size
            if r:
                times[label][0].append(write_s)
                times[label][1].append(read_s)
    print(f"\nModel storage, {n} Gaussians (SH degree 3), median of {repeats}, alternating")
    print("| model | file MB | write s | write MB/s | read s | read MB/s |")
    print("|---|---|---|---|---|---|")
    med = {k: (statistics.median(w), statistics.median(r)) for k, (w, r) in times.items()}
    for label, (w, r) in med.items():
        mb = sizes[label] / 1e6
        print(f"| {label} | {mb:.2f} | {w:.3f} | {mb / w:.0f} | {r:.3f} | {mb / r:.0f} |")
    (w0, r0), (w1, r1) = med["plaintext"], med["sealed"]
    print(f"sealed / plaintext: write {w1 / w0:.2f}x, read {r1 / r0:.2f}x")
    # the sealing alone, on the same bytes: a fresh data key wrapped per file, AES-256-GCM,
    # the xxh3 trailer; and opening (unwrap, checksum, decrypt)
    plain = (root / "models-plaintext" / f"t{repeats:05d}.000{storage.SUFFIX}").read_bytes()
    seals, opens = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        raw = seal.seal("model", "t1", plain)
        seals.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        seal.open("model", "t1", raw, "bench")
        opens.append(time.perf_counter() - t0)
    mb = len(plain) / 1e6
    s_s, o_s = statistics.median(seals), statistics.median(opens)
    print(f"sealing alone: seal {s_s * 1e3:.1f} ms ({mb / s_s:.0f} MB/s), open "
          f"{o_s * 1e3:.1f} ms ({mb / o_s:.0f} MB/s) per {mb:.2f} MB model")  # fmt: skip


def reconstruct_s(session: Path, config: Path, out: Path, env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "protocol.cli", "reconstruct", str(session), "--config",
         str(config), "--every", "0.0667s", "--out", str(out / "case"), "--depth-cache",
         str(out / "depth")],
        cwd=REPO, env=env, capture_output=True, text=True,
    )  # fmt: skip
    if done.returncode != 0:
        raise SystemExit(done.stderr[-2000:])
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sets", type=int, default=4, help="sets of the sim (15 fps, from 2.0 s)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--gaussians", type=int, default=200_000)
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench_case_sealing_"))
    site = generate_identity("bench-site")
    _, identity_path = write_identity(site, root / "keys")
    spec = EvalSetSpec(phases=("intraoperative",), sets=args.sets, eval_sets=(0,), instants=1,
                       view_size_px=(64, 40))  # fmt: skip
    write_eval_set(root / "es", spec)
    plain = root / "es" / "intraoperative" / "session.h5"
    sealed = root / "sealed" / "session.h5"
    sealed.parent.mkdir()
    (sealed.parent / "calibration.toml").write_bytes(
        (plain.parent / "calibration.toml").read_bytes()
    )
    sealed_copy(plain, sealed, site.recipient)
    with SessionReader(sealed) as reader:
        seal = derived_seal(reader, site)
    storage_table(args.gaussians, root, seal, max(5, args.repeats))

    config = root / "tiny.toml"
    config.write_text(TINY)
    env = {k: v for k, v in os.environ.items() if k != "EGOSURG_IDENTITY"}
    walls: dict[str, list[float]] = {"plaintext": [], "sealed": []}
    for r in range(args.repeats):  # alternating: the machine's load hits both alike
        walls["plaintext"].append(reconstruct_s(plain, config, root / f"p{r}", env))
        keyed = {**env, "EGOSURG_IDENTITY": str(identity_path)}
        walls["sealed"].append(reconstruct_s(sealed, config, root / f"s{r}", keyed))
    cases = len(list((root / "p0" / "case" / "models").iterdir()))
    print(f"\negosurg reconstruct --every 0.0667s, {cases} timestamps (tiny config, warm start, "
          f"depth cache), median of {args.repeats}")  # fmt: skip
    print("| session | wall s | ratio |")
    print("|---|---|---|")
    p = statistics.median(walls["plaintext"])
    for label, w in walls.items():
        m = statistics.median(w)
        print(f"| {label} | {m:.1f} | {m / p:.2f} |")
    print(f"(files under {root})")


if __name__ == "__main__":
    main()
