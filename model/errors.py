"""Typed exceptions of the model package (library code never exits or asserts on user input)."""

from __future__ import annotations


class ModelError(Exception):
    """Base class of every problem the model package reports to its caller."""


class UnknownPresetError(ModelError, KeyError):
    """A preset name is not in :data:`egosim.model.presets.PRESETS`."""


class ModelConfigError(ModelError, ValueError):
    """A config field is invalid; the message quotes every bad value."""


class SampleError(ModelError, ValueError):
    """A :class:`TrainingSample` has wrong shapes, dtypes or values; the message lists them all."""


class WeightsMismatchError(ModelError):
    """A weights folder does not match the preset's architecture; names the first bad tensor."""


class CheckpointMismatchError(ModelError):
    """A training checkpoint was written by another preset or another trainable layout."""


class MissingEmbeddingError(ModelError, FileNotFoundError):
    """A precomputed text or image embedding the preset needs is not available."""
