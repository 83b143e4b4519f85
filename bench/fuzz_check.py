"""Fuzz ``egosim check``: corrupt small shards at random and classify what check says.

Each case copies a clean shard (a synthetic clips shard, or a rejects shard), damages it in one
of several ways (bit flips anywhere or in the footer, truncation, a zeroed block, appended bytes)
and runs :func:`egosim.pipeline.check.check_shard` on it. The ground truth is what plain pyarrow
decodes from the damaged file without any verification: when it cannot decode it, or decodes
rows or provenance that differ from the clean file, the content changed.

- crash: check raised (it must never);
- false accept: check found nothing although the decoded content changed (it must never);
- clean reject: check reported at least one violation;
- benign accept: check found nothing and the decoded content is unchanged (e.g. a flipped bit
  in padding or in statistics no reader uses).

Long version (several hundred cases)::

    .venv/bin/python -m bench.fuzz_check --cases 400

The test suite runs a few seconds of it (``tests/test_trust.py``).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from egosim.pipeline.check import check_shard
from egosim.pipeline.shards import SHARD_META_KEY, ShardWriter
from egosim.schemas import REJECTS

KINDS = ("bit_flip", "footer_flip", "truncate", "zero_block", "append")  # corruption kinds


@dataclass
class FuzzResult:
    """Counts of each outcome, and a few examples of the bad ones."""

    cases: int = 0  # corrupted files checked
    crashes: int = 0  # check raised
    false_accepts: int = 0  # check found nothing although decoded content changed
    clean_rejects: int = 0  # check reported a violation
    benign_accepts: int = 0  # check found nothing and decoded content is unchanged
    examples: list[str] = field(default_factory=list)  # descriptions of crashes/false accepts

    def line(self) -> str:
        """One summary line."""
        return (
            f"{self.cases} cases: {self.crashes} crashes, {self.false_accepts} false accepts, "
            f"{self.clean_rejects} clean rejects, {self.benign_accepts} benign accepts"
        )


def make_shards(folder: Path) -> list[Path]:
    """A small synthetic clips shard (2 clips, 9 frames, 32x48) and a rejects shard."""
    from egosim.pipeline.clip_io import write_clips
    from egosim.world import WorldConfig, render_clip

    folder.mkdir(parents=True, exist_ok=True)
    clips = folder / "clips.parquet"
    configs = [WorldConfig(seed=s, height=32, width=48, num_frames=9) for s in (0, 1)]
    write_clips(clips, [render_clip(c) for c in configs], stage="fuzz")
    rejects = folder / "rejects.parquet"
    with ShardWriter(rejects, REJECTS, stage="fuzz") as writer:
        for i in range(3):
            writer.write_row(
                {
                    "step": "ingest",
                    "stage": "ingest",
                    "shard": "shard-00000.parquet",
                    "clip_id": f"video:/data/{i}.mp4",
                    "reason": f"reason {i}",
                    "input_fingerprint": f"{i:020d}",
                }
            )
    return [clips, rejects]


def decoded(path: Path) -> tuple[Any, ...] | None:
    """What plain pyarrow decodes (rows and provenance, no verification); None if it cannot."""
    try:
        f = pq.ParquetFile(path)
        meta = (f.schema_arrow.metadata or {}).get(SHARD_META_KEY)
        return (meta, f.schema_arrow.names, f.read().to_pylist())
    except Exception:  # any failure means: this content cannot be decoded
        return None


def corrupt(data: bytes, kind: str, rng: np.random.Generator) -> bytes:
    """``data`` damaged in the way ``kind`` names."""
    buf = bytearray(data)
    n = len(buf)
    if kind == "bit_flip":
        for _ in range(int(rng.integers(1, 9))):
            i = int(rng.integers(0, n))
            buf[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == "footer_flip":  # the footer: thrift metadata, schema, provenance, hashes
        lo = max(0, n - max(64, n // 10))
        i = int(rng.integers(lo, n - 8))  # leave the length and the PAR1 magic alone
        buf[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == "truncate":
        return bytes(buf[: int(rng.integers(0, n))])
    elif kind == "zero_block":
        i = int(rng.integers(0, n))
        size = int(rng.integers(1, 4097))
        buf[i : i + size] = bytes(len(buf[i : i + size]))
    elif kind == "append":
        buf += rng.integers(0, 256, int(rng.integers(1, 256)), dtype=np.uint8).tobytes()
    else:
        raise ValueError(f"unknown corruption kind {kind!r}")
    return bytes(buf)


def fuzz(
    cases: int, seed: int = 0, seconds: float | None = None, folder: Path | None = None
) -> FuzzResult:
    """Run up to ``cases`` corruptions (stopping after ``seconds`` when given)."""
    rng = np.random.default_rng(seed)
    own = folder is None
    work = Path(tempfile.mkdtemp(prefix="egosim-fuzz-")) if folder is None else folder
    result = FuzzResult()
    try:
        clean = make_shards(work / "clean")
        originals = {p: (p.read_bytes(), decoded(p)) for p in clean}
        for p in clean:
            if check_shard(p):
                raise RuntimeError(f"clean shard {p} fails check: {check_shard(p)}")
        start = time.perf_counter()
        for case in range(cases):
            if seconds is not None and time.perf_counter() - start > seconds:
                break
            source = clean[case % len(clean)]
            data, truth = originals[source]
            kind = KINDS[int(rng.integers(0, len(KINDS)))]
            target = work / f"case-{case:05d}.parquet"
            target.write_bytes(corrupt(data, kind, rng))
            result.cases += 1
            try:
                problems = check_shard(target)
            except Exception as exc:  # counting crashes is the point
                result.crashes += 1
                result.examples.append(f"case {case} ({kind}, {source.name}): crash {exc!r}")
                target.unlink()
                continue
            changed = decoded(target) != truth
            if problems:
                result.clean_rejects += 1
            elif changed:
                result.false_accepts += 1
                result.examples.append(f"case {case} ({kind}, {source.name}): false accept")
            else:
                result.benign_accepts += 1
            target.unlink()
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)
    return result


def main() -> None:
    """Command line: ``python -m bench.fuzz_check --cases 400 [--seed 0]``."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=400, help="corrupted files to check")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the corruptions")
    args = parser.parse_args()
    t0 = time.perf_counter()
    result = fuzz(args.cases, args.seed)
    print(f"{result.line()} ({time.perf_counter() - t0:.1f} s)")
    for example in result.examples[:20]:
        print("  " + example)
    raise SystemExit(1 if result.crashes or result.false_accepts else 0)


if __name__ == "__main__":
    main()
