"""Shard schemas: one per shard kind, versioned, with column docs and row validators."""

from __future__ import annotations

from egosim.schemas.base import (
    Column,
    RowValidationError,
    SchemaCompatibilityError,
    SchemaError,
    ShardSchema,
    schema_identity,
)
from egosim.schemas.captions import CAPTIONS
from egosim.schemas.clips import CLIPS
from egosim.schemas.depth_camera import DEPTH_CAMERA
from egosim.schemas.hand_mask import HAND_MASK
from egosim.schemas.hands import HANDS
from egosim.schemas.inpaint import INPAINT
from egosim.schemas.keypoints import KEYPOINTS
from egosim.schemas.latents import LATENTS
from egosim.schemas.pack import EVALUATION, PACK, SIMULATION
from egosim.schemas.poses import POSES
from egosim.schemas.rejects import REJECTS
from egosim.schemas.scene import SCENE_CLOUD, SCENE_RENDER
from egosim.schemas.state import STATE

SCHEMAS: dict[str, ShardSchema] = {
    s.name: s
    for s in (
        CLIPS,
        REJECTS,
        CAPTIONS,
        DEPTH_CAMERA,
        POSES,
        SCENE_CLOUD,
        SCENE_RENDER,
        HANDS,
        KEYPOINTS,
        HAND_MASK,
        INPAINT,
        PACK,
        LATENTS,
        SIMULATION,
        EVALUATION,
        STATE,
    )
}


def get_schema(name: str) -> ShardSchema:
    """Return the declared schema called ``name``; raises KeyError listing the known ones."""
    try:
        return SCHEMAS[name]
    except KeyError:
        raise KeyError(f"unknown schema {name!r}; known: {sorted(SCHEMAS)}") from None


__all__ = [
    "CLIPS",
    "DEPTH_CAMERA",
    "POSES",
    "REJECTS",
    "SCHEMAS",
    "Column",
    "RowValidationError",
    "SchemaCompatibilityError",
    "SchemaError",
    "ShardSchema",
    "get_schema",
    "schema_identity",
]
