"""The procedural synthetic egocentric world: textured scenes, a head camera, articulated hands.

:func:`render_clip` turns a :class:`WorldConfig` into a fully annotated
:class:`egosim.pipeline.records.Clip`.
"""

from egosim.world.clip import render_clip
from egosim.world.config import WorldConfig, WorldConfigError

__all__ = ["WorldConfig", "WorldConfigError", "render_clip"]
