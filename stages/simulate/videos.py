"""Write each generated clip of ``simulation`` shards as an MP4 (the post-step of ``simulate``).

The runner writes shards only; ``egosim simulate`` calls :func:`write_videos` on the shards the
run made, so the files a person opens (``OUT/videos/<clip_id>.mp4``) come from the shards as
they are on disk, also for shards a re-run skipped. The stored MP4 bytes are copied as they are:
decoding and encoding them again would lose quality and give the same frame size (an odd size is
padded to even either way, as H.264 4:2:0 needs).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from egosim.pipeline.shards import ShardReader
from egosim.schemas.ids import path_under, validate_id
from egosim.schemas.pack import SIMULATION


def write_videos(shards: Iterable[Path], folder: Path) -> list[Path]:
    """Write ``folder/<clip_id>.mp4`` for every row of the ``simulation`` shards; returns them.

    Clip ids are checked (:func:`~egosim.schemas.ids.validate_id`) and every path stays under
    ``folder`` (:func:`~egosim.schemas.ids.path_under`).
    """
    written = []
    for shard in shards:
        with ShardReader(shard, SIMULATION) as reader:
            for row in reader.iter_rows():
                path = path_under(folder, f"{validate_id(row['clip_id'])}.mp4")
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(row["video"])  # already an H.264 MP4 at the row's fps
                written.append(path)
    return written
