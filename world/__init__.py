"""The procedural synthetic egocentric world: textured scenes, a head camera, articulated hands.

:func:`render_clip` turns a :class:`WorldConfig` into a fully annotated
:class:`egosim.pipeline.records.Clip`.

A library, not a stage: the ingest stage's synthetic source, ``egosim synth``, the tests and the
benchmarks call it. It builds on pipeline's data layer only (geometry, records, media, the EgoDex
format) and imports no stage; ``tests/test_import_contracts.py`` holds it to that.
"""

from egosim.world.clip import render_clip
from egosim.world.config import WorldConfig, WorldConfigError

__all__ = ["WorldConfig", "WorldConfigError", "render_clip"]
