"""The ``caption`` stage: the source's own description, or a template when there is none."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

from egosim.pipeline.records import ClipsRecord
from egosim.pipeline.stage import ClipStage, ConfigError, StageConfig
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.captions import CAPTIONS


@dataclasses.dataclass(frozen=True)
class CaptionConfig(StageConfig):
    """Parameters of ``caption``."""

    template: str = "A first-person video of two hands manipulating objects on a table."  # fallback
    prefix: str = ""  # prepended to every prompt (e.g. a style tag), empty for none
    prefer_source: bool = True  # use the clip's own text when it has one

    def __post_init__(self) -> None:
        if not self.template.strip():
            raise ConfigError(f"template must not be empty, got {self.template!r}")


class CaptionStage(ClipStage):
    """Write a text prompt per clip."""

    name = "caption"
    description = "a text prompt per clip: the source description or a template"
    config_class = CaptionConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    output = CAPTIONS
    backends = ("source",)
    # What process reads of the clip (the executor decodes nothing else): its own text.
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = {"clips": ("text",)}
    config: CaptionConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """The clip's own text (when wanted and present) or the template, with the prefix."""
        clip = ClipsRecord.of(rows["clips"])
        own = (clip.text or "").strip()
        use_source = self.config.prefer_source and bool(own)
        text = own if use_source else self.config.template
        if self.config.prefix:
            text = f"{self.config.prefix.strip()} {text}"
        return {
            "clip_id": clip.clip_id,
            "text": text,
            "origin": "source" if use_source else "template",
        }
