"""Read ``latents`` shards (the ``encode`` stage) as an indexable dataset of
:class:`~egosim.model.conditioning.LatentSample`, and pick the training data kind of a path.

``LatentsDataset(paths)`` has :class:`~.pack_dataset.PackDataset`'s interface (``len``, ``[i]``,
``clip_ids``, ``sizes`` as pixel ``(T, H, W)``, ``shards``) plus ``latent_sizes`` and
``presets`` (the preset whose encoders made each row: its text/image widths must be the
training preset's). Items are float32 tensors decoded from the stored dtype; ``cache`` keeps the
raw rows (stored bytes, compact) and decodes on each access.

:func:`open_training_data` is what training calls: latents shards (a run folder with an
``encode/`` step, or latents shard files) give a ``LatentsDataset``, pack shards a
``PackDataset``; a mix of both kinds is refused.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import torch

from egosim.model.conditioning import LatentSample
from egosim.pipeline.shards import SHARD_GLOB, STAGE_REJECTS_SUFFIX, ShardReader, find_shards
from egosim.schemas.latents import CONDITION_CHANNELS, LATENT_CHANNELS, LATENTS, decode_tensor
from egosim.schemas.pack import PACK
from egosim.stages.common.pack_dataset import PackDataset

ENCODE_STEP = "encode"  # step folder of the encode stage in a run
PACK_STEP = "pack"  # step folder of the pack stage in a run


class TrainingDataError(ValueError):
    """Training paths hold no shards, shards of another kind, or pack and latents mixed."""


def find_latents_shards(paths: Iterable[str | Path]) -> list[Path]:
    """Latents shard files under ``paths``: files, folders of shards, or runs with ``encode/``."""
    return find_shards(paths, ENCODE_STEP)


def latent_sample_from_row(row: Mapping[str, Any]) -> LatentSample:
    """The :class:`LatentSample` of one latents row (float32 tensors, exact for every dtype)."""
    cid = row.get("clip_id", "?")
    dtype = row["dtype"]
    grid = (int(row["latent_frames"]), int(row["latent_height"]), int(row["latent_width"]))

    def tensor(column: str, shape: tuple[int, ...]) -> torch.Tensor:
        try:
            return torch.from_numpy(decode_tensor(row[column], shape, dtype))
        except ValueError as exc:
            raise TrainingDataError(f"latents row {cid!r} column {column!r}: {exc}") from exc

    text = image = None
    if row.get("text_features") is not None:
        text = tensor("text_features", (int(row["text_length"]), int(row["text_dim"])))
    if row.get("image_features") is not None:
        image = tensor("image_features", (int(row["image_tokens"]), int(row["image_dim"])))
    return LatentSample(
        x0=tensor("x0", (LATENT_CHANNELS, *grid)),
        condition=tensor("condition", (CONDITION_CHANNELS, *grid)),
        prompt=str(row["prompt"]),
        text_embedding=text,
        image_embedding=image,
        clip_id=str(cid),
    )


class LatentsDataset:
    """Indexable latent samples: ``len(ds)``, ``ds[i]`` -> LatentSample, ``ds.clip_ids``."""

    def __init__(self, paths: Iterable[str | Path] | str | Path, cache: bool = True) -> None:
        if isinstance(paths, str | Path):
            paths = [paths]
        self.shards = find_latents_shards(paths)
        self.cache = cache
        self._index: list[tuple[Path, int]] = []
        self.clip_ids: list[str] = []
        self.sizes: list[tuple[int, int, int]] = []  # (T, H, W) pixel size of each sample
        self.latent_sizes: list[tuple[int, int, int]] = []  # (T', h, w) of each sample
        self.presets: list[str] = []  # preset whose encoders made each sample
        columns = ("clip_id", "num_frames", "height", "width", "preset")
        latent_columns = ("latent_frames", "latent_height", "latent_width")
        for shard in self.shards:
            with ShardReader(shard, LATENTS) as reader:  # raises on a non-latents shard
                groups = reader.row_group_of()
                values = {c: reader.read_column(c) for c in (*columns, *latent_columns)}
            for k, clip_id in enumerate(values["clip_id"]):
                self._index.append((shard, groups[clip_id]))
                self.clip_ids.append(clip_id)
                self.sizes.append(tuple(int(values[c][k]) for c in columns[1:4]))  # type: ignore[misc]
                self.latent_sizes.append(tuple(int(values[c][k]) for c in latent_columns))  # type: ignore[misc]
                self.presets.append(str(values["preset"][k]))
        self._rows: dict[int, dict] = {}

    def __len__(self) -> int:
        return len(self._index)

    def row(self, i: int) -> dict:
        """The raw latents row ``i`` (stored bytes; verified against its content hash)."""
        if i in self._rows:
            return self._rows[i]
        shard, group = self._index[i]
        with ShardReader(shard, LATENTS) as reader:
            row = reader.read_row_group(group)[0]
        if self.cache:
            self._rows[i] = row
        return row

    def check_preset(self, name: str) -> None:
        """Raise :class:`TrainingDataError` unless every row's encoders fit training preset
        ``name``: the same VAE, and text / image features of the widths it reads (latents of
        the 1.3B Wan preset fit the 14B one: same VAE, UMT5 and CLIP)."""
        from egosim.model.presets import get_preset

        want = get_preset(name)
        problems = []
        for made_by in sorted(set(self.presets)):
            have = get_preset(made_by)
            why = []
            if have.vae != want.vae:
                why.append(f"VAE {have.vae} vs {want.vae}")
            if have.text.kind != want.text.kind or (
                want.text.kind == "precomputed"
                and have.transformer.text_dim != want.transformer.text_dim
            ):
                why.append(
                    f"text {have.text.kind}/{have.transformer.text_dim} vs "
                    f"{want.text.kind}/{want.transformer.text_dim}"
                )
            if have.transformer.image_dim != want.transformer.image_dim:
                why.append(
                    f"image_dim {have.transformer.image_dim} vs {want.transformer.image_dim}"
                )
            if why:
                clips = [
                    c for c, p in zip(self.clip_ids, self.presets, strict=True) if p == made_by
                ]
                problems.append(
                    f"{len(clips)} clip(s) (e.g. {clips[0]!r}) were encoded for preset "
                    f"{made_by!r}: " + ", ".join(why)
                )
        if problems:
            raise TrainingDataError(
                f"latents do not fit preset {name!r} (re-run encode with preset={name}): "
                + "; ".join(problems)
            )

    def __getitem__(self, i: int) -> LatentSample:
        if not -len(self) <= i < len(self):
            raise IndexError(f"latents sample {i} out of range ({len(self)} samples)")
        return latent_sample_from_row(self.row(i % len(self)))


def _shard_kind(path: Path) -> str:
    """Schema name of one shard file (``pack``, ``latents``, ...), from its metadata."""
    with ShardReader(path) as reader:
        return reader.meta.schema


def _kinds(path: Path) -> set[str]:
    """The shard kinds ``path`` holds for training (a run folder: its encode/ else pack/)."""
    if path.is_file():
        return {_shard_kind(path)}
    if not path.is_dir():
        raise TrainingDataError(f"no training shard or folder at {path}")
    for step, kind in ((ENCODE_STEP, LATENTS.name), (PACK_STEP, PACK.name)):
        if any((path / step).glob(SHARD_GLOB)):
            return {kind}
    shards = sorted(path.glob(SHARD_GLOB))
    return {_shard_kind(p) for p in shards if not p.name.endswith(STAGE_REJECTS_SUFFIX)}


def open_training_data(
    paths: Iterable[str | Path] | str | Path, cache: bool = True
) -> LatentsDataset | PackDataset:
    """The training dataset of ``paths``: :class:`LatentsDataset` when they hold latents shards
    (a run folder with an ``encode/`` step, or latents shard files), else :class:`PackDataset`.

    Raises :class:`TrainingDataError` naming the paths when they hold no shard, a shard of
    another kind, or pack and latents shards together.
    """
    paths = [paths] if isinstance(paths, str | Path) else list(paths)
    kinds: dict[str, list[str]] = {}
    for raw in paths:
        for kind in _kinds(Path(raw)):
            kinds.setdefault(kind, []).append(str(raw))
    if not kinds:
        raise TrainingDataError(
            f"no pack or latents shards under {[str(p) for p in paths]} (expected "
            f"{SHARD_GLOB} files, or a run folder with a pack/ or encode/ step)"
        )
    other = {k: v for k, v in kinds.items() if k not in (LATENTS.name, PACK.name)}
    if other:
        raise TrainingDataError(f"training reads pack or latents shards; found {other}")
    if len(kinds) > 1:
        raise TrainingDataError(
            f"paths mix pack and latents shards ({kinds}): train on one kind (the latents of "
            "an encoded run, or its pack)"
        )
    if LATENTS.name in kinds:
        return LatentsDataset(paths, cache=cache)
    return PackDataset(paths, cache=cache)
