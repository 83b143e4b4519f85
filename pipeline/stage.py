"""The stage API: a frozen config, declared input and output schemas, one entry point per clip.

Two kinds of stage (see docs/design.md):

- :class:`SourceStage` (``ingest``) turns *units* (input files, generated-clip seeds) into rows.
  It lists its units from the run's ``--input``; the runner deals units out to shards.
- :class:`ClipStage` maps one clip to one output row. It may read several input shards
  (roles, each with a declared schema); rows are joined by ``clip_id`` within the shard index.
  ``optional_inputs`` are roles a workflow may connect or leave out (e.g. cleaned poses that
  replace the clip's own); ``process`` gets only the roles that are connected.

A stage raises :class:`ClipRejected` (or any exception) for a clip it cannot process; the
executor records it in the rejects table and goes on. Stages never import Dask: the executor
tells them nothing but the rows, and the runner owns scheduling.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from typing import Any, ClassVar

from egosim.schemas import ShardSchema


class StageError(Exception):
    """Base class of stage problems reported to the user."""


class ConfigError(StageError, ValueError):
    """Stage parameters are unknown or invalid; the message lists every problem."""


class ClipRejected(StageError):  # noqa: N818 (a verdict on a clip, not a failure)
    """A stage cannot process one clip (or input unit); goes to the rejects table."""


@dataclasses.dataclass(frozen=True)
class StageConfig:
    """Base of every stage config: frozen, every field with a default and a comment."""


class Stage(ABC):
    """Base class of every stage. Subclasses set the class attributes below."""

    name: ClassVar[str]  # registry name, also the default step name
    description: ClassVar[str]  # one line for `egosim stages`
    config_class: ClassVar[type[StageConfig]] = StageConfig  # frozen parameters dataclass
    inputs: ClassVar[Mapping[str, ShardSchema]] = {}  # input role -> schema it must have
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {}  # roles a workflow may leave out
    output: ClassVar[ShardSchema]  # schema of the output shard
    backends: ClassVar[tuple[str, ...]] = ()  # backend names (first = default)
    version: ClassVar[int] = 1  # bump when outputs change for the same params (re-runs)
    gpu: ClassVar[bool] = False  # True when the stage wants a GPU worker by default

    def __init__(self, config: StageConfig | None = None) -> None:
        self.config = config if config is not None else self.config_class()
        if not isinstance(self.config, self.config_class):
            raise ConfigError(
                f"stage {self.name!r} needs a {self.config_class.__name__}, "
                f"got {type(self.config).__name__}"
            )

    @classmethod
    def input_schemas(cls) -> dict[str, ShardSchema]:
        """Every input role, required first, then optional, with its schema."""
        return {**cls.inputs, **cls.optional_inputs}

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> Stage:
        """Build the stage from a parameter mapping (YAML values or ``k=v`` strings)."""
        return cls(build_config(cls.config_class, params, where=f"stage {cls.name!r}"))

    def params(self) -> dict[str, Any]:
        """The resolved parameters, as stored in shard metadata and fingerprints."""
        return dataclasses.asdict(self.config)


class SourceStage(Stage):
    """A stage that creates clips from outside data (files, recordings, generated worlds)."""

    @abstractmethod
    def list_units(self, source: str | None) -> list[str]:
        """List the input units (files or generated-clip specs) under ``source``."""

    def unit_fingerprint(self, unit: str) -> str:
        """What identifies a unit's content for re-run checks (default: the unit string)."""
        return unit

    @abstractmethod
    def process_unit(self, unit: str) -> Iterator[dict[str, Any]]:
        """Yield the output rows made from one unit; raise to reject the unit."""

    def units_per_shard(self) -> int:
        """How many units go to one shard (a config field ``units_per_shard`` when present)."""
        return int(getattr(self.config, "units_per_shard", 1))


class ClipStage(Stage):
    """A stage that maps one clip (joined over its input roles) to one output row."""

    @abstractmethod
    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Return the output row for one clip given its row in every input role."""


_REGISTRY: dict[str, type[Stage]] = {}


def register_stage(cls: type[Stage]) -> type[Stage]:
    """Add a stage class to the registry; refuses a name that is already taken."""
    if cls.name in _REGISTRY:
        raise StageError(
            f"stage name {cls.name!r} is already registered by {_REGISTRY[cls.name].__module__}"
        )
    _REGISTRY[cls.name] = cls
    return cls


def registered_stages() -> dict[str, type[Stage]]:
    """Every registered stage by name (imports the built-in stages first)."""
    import egosim.stages  # noqa: F401  (registers the built-in stages)

    return dict(_REGISTRY)


def get_stage(name: str) -> type[Stage]:
    """Look a stage up by name; raises :class:`StageError` listing the known names."""
    stages = registered_stages()
    if name not in stages:
        raise StageError(f"unknown stage {name!r}; known stages: {sorted(stages)}")
    return stages[name]


def build_config(
    config_class: type[StageConfig], params: Mapping[str, Any], where: str
) -> StageConfig:
    """Build a frozen config from ``params``, converting strings to the field types.

    Every unknown name and every unconvertible value is reported in one :class:`ConfigError`;
    the config's own ``__post_init__`` checks run after that.
    """
    hints = typing.get_type_hints(config_class)
    known = {f.name for f in dataclasses.fields(config_class)}
    problems = [
        f"unknown parameter {k!r} (known: {sorted(known)})" for k in params if k not in known
    ]
    values: dict[str, Any] = {}
    for key, raw in params.items():
        if key not in known:
            continue
        try:
            values[key] = coerce(raw, hints[key])
        except (TypeError, ValueError) as exc:
            problems.append(f"parameter {key!r}: {exc}")
    if problems:
        raise ConfigError(f"{where}: " + "; ".join(problems))
    try:
        return config_class(**values)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def coerce(value: Any, annotation: Any) -> Any:
    """Convert ``value`` (often a string from the command line) to ``annotation``."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        is_none = value is None or (isinstance(value, str) and value.lower() in ("none", "null"))
        if is_none and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return coerce(value, arg)
            except (TypeError, ValueError) as exc:
                errors.append(str(exc))
        raise ValueError("; ".join(errors))
    if origin is typing.Literal:
        if value not in args:
            raise ValueError(f"must be one of {list(args)}, got {value!r}")
        return value
    if origin is tuple:
        items = value.split(",") if isinstance(value, str) else list(value)
        inner = args[0] if args else str
        return tuple(coerce(v, inner) for v in items)
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "false", "0", "no"):
            return value.lower() in ("true", "1", "yes")
        raise ValueError(f"expected a boolean, got {value!r}")
    if annotation is int:
        if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
            raise ValueError(f"expected an integer, got {value!r}")
        return int(value)
    if annotation is float:
        return float(value)
    if annotation is str:
        if not isinstance(value, str | int | float):
            raise ValueError(f"expected a string, got {value!r}")
        return str(value)
    return value
