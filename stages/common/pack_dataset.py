"""Read pack shards as an indexable dataset of :class:`~egosim.model.TrainingSample`.

``PackDataset(paths)`` accepts shard files, folders of shards, or a run folder (its ``pack/``
step folder is used). It indexes ``(shard, row group)`` pairs up front and decodes a sample when
it is asked for, so memory holds one clip at a time unless ``cache=True`` (the default: ``tiny``
training revisits the same few clips hundreds of times). The cache keeps decoded samples up to
:data:`CACHE_BUDGET_BYTES` of video and decodes the rest on each access, so a large pack (or one
rank of a many-rank run, which reads only its own samples) never holds the whole data set.

It lives in ``stages/common`` because several stages and commands read pack shards (``train``,
``egosim simulate`` and ``evaluate``), and a stage never imports another stage.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from egosim.model.conditioning import TrainingSample
from egosim.pipeline.shards import ShardReader, find_shards
from egosim.schemas.pack import PACK
from egosim.stages.common.packed import sample_from_pack_row

CACHE_BUDGET_BYTES = 1 << 30  # decoded video bytes the sample cache may hold (1 GiB)


def find_pack_shards(paths: Iterable[str | Path]) -> list[Path]:
    """Pack shard files under ``paths``: files, folders of shards, or run folders with pack/."""
    return find_shards(paths, "pack")


class PackDataset:
    """Indexable pack samples: ``len(ds)``, ``ds[i]`` -> TrainingSample, ``ds.clip_ids``."""

    def __init__(self, paths: Iterable[str | Path] | str | Path, cache: bool = True) -> None:
        if isinstance(paths, str | Path):
            paths = [paths]
        self.shards = find_pack_shards(paths)
        self.cache = cache
        self._index: list[tuple[Path, int]] = []
        self.clip_ids: list[str] = []
        self.sizes: list[tuple[int, int, int]] = []  # (T, H, W) of each sample
        for shard in self.shards:
            with ShardReader(shard, PACK) as reader:  # raises on a non-pack shard
                groups = reader.row_group_of()
                sizes = zip(
                    reader.read_column("clip_id"),
                    reader.read_column("num_frames"),
                    reader.read_column("height"),
                    reader.read_column("width"),
                    strict=True,
                )
                for clip_id, t, h, w in sizes:
                    self._index.append((shard, groups[clip_id]))
                    self.clip_ids.append(clip_id)
                    self.sizes.append((int(t), int(h), int(w)))
        self._cached: dict[int, TrainingSample] = {}
        self._cached_bytes = 0  # decoded video bytes held by _cached

    def __len__(self) -> int:
        return len(self._index)

    def row(self, i: int) -> dict:
        """The raw pack row ``i`` (encoded columns)."""
        shard, group = self._index[i]
        with ShardReader(shard, PACK) as reader:
            return reader.read_row_group(group)[0]

    def __getitem__(self, i: int) -> TrainingSample:
        if not -len(self) <= i < len(self):
            raise IndexError(f"pack sample {i} out of range ({len(self)} samples)")
        i %= len(self)
        if i in self._cached:
            return self._cached[i]
        sample = sample_from_pack_row(self.row(i))
        t, h, w = self.sizes[i]
        size = 3 * t * h * w * 3  # target, scene and skeleton videos, uint8 RGB
        if self.cache and self._cached_bytes + size <= CACHE_BUDGET_BYTES:
            self._cached[i] = sample
            self._cached_bytes += size
        return sample
