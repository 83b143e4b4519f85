"""The stage API: a frozen config, declared input and output schemas, one entry point per clip.

Two kinds of stage (see docs/design.md):

- :class:`SourceStage` (``ingest``) turns *units* (input files, generated-clip seeds) into rows.
  It lists its units from the run's ``--input``; the runner deals units out to shards.
- :class:`ClipStage` maps one clip to one output row. It may read several input shards
  (roles, each with a declared schema); rows are joined by ``clip_id`` within the shard index.
  ``optional_inputs`` are roles a workflow may connect or leave out (e.g. cleaned poses that
  replace the clip's own); ``process`` gets only the roles that are connected. ``columns``
  declares, per role, the columns ``process`` reads: the executor reads only those from the
  Parquet shard (a role left out is read whole).

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

    # input role -> the columns ``process`` reads of it; the executor reads only those (plus
    # ``clip_id``) and hands ``process`` a :class:`DeclaredRow`. A role left out is read whole.
    # Checked against the role's schema when the stage is registered (:func:`check_columns`).
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = {}

    @classmethod
    def read_columns(cls, role: str) -> list[str] | None:
        """The columns the executor reads of ``role``, in schema order; None = every column.

        ``clip_id`` (the join key) is always among them; a role without a declaration, or one
        whose declaration names every column, is read whole (and its rows hash-verified).
        """
        declared = cls.columns.get(role)
        if declared is None:
            return None
        names = cls.input_schemas()[role].column_names
        wanted = {"clip_id", *declared}
        if wanted.issuperset(names):
            return None
        return [name for name in names if name in wanted]

    @abstractmethod
    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Return the output row for one clip given its row in every input role."""


class UndeclaredColumnError(StageError, LookupError):
    """A stage read a column of an input role that its ``columns`` declaration leaves out."""


class DeclaredRow(dict[str, Any]):
    """One input row holding only the columns a stage declared (see ``ClipStage.columns``).

    Reading (``row[k]``, ``row.get(k)``) a column of the role's schema that was not read raises
    :class:`UndeclaredColumnError` naming the stage, role and column, so a declaration that
    misses a column fails loudly instead of reading as null. ``k in row`` is False for such a
    column (helpers such as ``clip_from_row`` treat an absent optional column like null).
    """

    def __init__(
        self, values: Mapping[str, Any], stage: str, role: str, schema_columns: tuple[str, ...]
    ) -> None:
        super().__init__(values)
        self.stage = stage  # stage name, for the error message
        self.role = role  # input role of this row
        self.schema_columns = schema_columns  # every column of the role's schema

    def _undeclared(self, key: object) -> UndeclaredColumnError | None:
        if key in self.schema_columns and not dict.__contains__(self, key):
            return UndeclaredColumnError(
                f"stage {self.stage!r} reads column {key!r} of input role {self.role!r}, which "
                f"its `columns` declaration leaves out (declared: {sorted(self)})"
            )
        return None

    def __getitem__(self, key: str) -> Any:
        error = self._undeclared(key)
        if error is not None:
            raise error
        return dict.__getitem__(self, key)

    def get(self, key: str, default: Any = None) -> Any:
        """``row[key]`` when present, else ``default`` (an undeclared schema column raises)."""
        error = self._undeclared(key)
        if error is not None:
            raise error
        return dict.get(self, key, default)


def join_columns(*declarations: Mapping[str, tuple[str, ...]]) -> dict[str, tuple[str, ...]]:
    """Merge column declarations role by role (order kept, duplicates dropped).

    For a stage that reads its own columns plus those a shared helper reads, e.g.
    ``join_columns({"clips": ("video",)}, CAMERA_COLUMNS)``.
    """
    merged: dict[str, tuple[str, ...]] = {}
    for declaration in declarations:
        for role, names in declaration.items():
            merged[role] = tuple(dict.fromkeys((*merged.get(role, ()), *names)))
    return merged


def check_columns(cls: type[ClipStage]) -> None:
    """Raise :class:`StageError` listing every declared role or column the schemas lack."""
    schemas = cls.input_schemas()
    problems: list[str] = []
    for role, names in cls.columns.items():
        if role not in schemas:
            problems.append(f"role {role!r} is not an input role (roles: {sorted(schemas)})")
            continue
        if isinstance(names, str):
            problems.append(f"role {role!r} must list column names, got the string {names!r}")
            continue
        known = schemas[role].column_names
        problems += [
            f"role {role!r} has no column {name!r} in schema {schemas[role].name!r}"
            for name in names
            if name not in known
        ]
    if problems:
        raise StageError(f"stage {cls.name!r} columns: " + "; ".join(problems))


_REGISTRY: dict[str, type[Stage]] = {}


def register_stage(cls: type[Stage]) -> type[Stage]:
    """Add a stage class to the registry; refuses a name that is taken or bad ``columns``."""
    if cls.name in _REGISTRY:
        raise StageError(
            f"stage name {cls.name!r} is already registered by {_REGISTRY[cls.name].__module__}"
        )
    if issubclass(cls, ClipStage):
        check_columns(cls)
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


def build_config(config_class: type[Any], params: Mapping[str, Any], where: str) -> Any:
    """Build a frozen config dataclass from ``params``, converting values to the field types.

    ``params`` holds YAML values or ``k=v`` strings; a nested dataclass field takes a mapping
    (``lora: {rank: 8}``) or dotted keys (``lora.rank=8``). Every unknown name and every value
    that does not convert is reported in one :class:`ConfigError` that quotes the bad value; the
    config's own ``__post_init__`` checks run after that.
    """
    problems: list[str] = []
    values = _config_values(config_class, params, "", problems)
    if problems:
        raise ConfigError(f"{where}: " + "; ".join(problems))
    try:
        return config_class(**values)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def _config_values(
    config_class: type[Any], params: Mapping[str, Any], prefix: str, problems: list[str]
) -> dict[str, Any]:
    """Converted field values of ``config_class`` from ``params``; problems are appended."""
    hints = typing.get_type_hints(config_class)
    fields = {f.name for f in dataclasses.fields(config_class)}
    grouped: dict[str, Any] = {}
    for key, raw in params.items():
        head, dot, rest = str(key).partition(".")
        if head not in fields:
            problems.append(f"unknown parameter {prefix + str(key)!r} (known: {sorted(fields)})")
        elif not dot:
            grouped[head] = raw
        elif not _is_config_class(hints[head]):
            problems.append(f"parameter {prefix + head!r} has no fields, got {prefix + key!r}")
        else:
            nested = grouped.setdefault(head, {})
            if isinstance(nested, Mapping):
                grouped[head] = {**nested, rest: raw}
            else:
                problems.append(f"parameter {prefix + head!r} is given whole and by field")
    values: dict[str, Any] = {}
    for name, raw in grouped.items():
        annotation = hints[name]
        if _is_config_class(annotation) and isinstance(raw, Mapping):
            inner: list[str] = []
            sub = _config_values(annotation, raw, f"{prefix}{name}.", inner)
            problems += inner
            if not inner:
                try:
                    values[name] = annotation(**sub)
                except (TypeError, ValueError) as exc:
                    problems.append(f"parameter {prefix + name!r}: {exc}")
            continue
        try:
            values[name] = coerce(raw, annotation)
        except (TypeError, ValueError) as exc:
            problems.append(f"parameter {prefix + name!r}: {exc}")
    return values


def _is_config_class(annotation: Any) -> bool:
    return isinstance(annotation, type) and dataclasses.is_dataclass(annotation)


_TRUE = ("true", "1", "yes", "on")
_FALSE = ("false", "0", "no", "off")


def coerce(value: Any, annotation: Any) -> Any:
    """Convert ``value`` (a YAML value or a command-line string) to ``annotation``, strictly.

    Supported: ``int``, ``float``, ``bool``, ``str``, ``Literal[...]``, ``tuple[X, ...]`` and
    ``tuple[X, Y]`` (a comma-separated string or a sequence), ``list[X]``, ``X | None`` (the
    strings ``none``/``null`` give None) and nested config dataclasses (a mapping of fields).
    Raises :class:`ValueError` quoting the value when it does not convert, and
    :class:`TypeError` for a field type outside that list (never returns a value unchanged).
    """
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        return _coerce_union(value, args)
    if origin is typing.Literal:
        for choice in args:
            if value == choice and type(value) is type(choice):
                return choice
            if isinstance(value, str) and not isinstance(choice, str) and value == str(choice):
                return choice
        raise ValueError(f"must be one of {list(args)}, got {value!r}")
    if origin in (tuple, list) or annotation in (tuple, list):
        return _coerce_sequence(value, annotation, origin or annotation, args)
    if _is_config_class(annotation):
        if isinstance(value, annotation):
            return value
        if isinstance(value, Mapping):
            return build_config(annotation, value, where=annotation.__name__)
        raise ValueError(
            f"expected {annotation.__name__} fields (a mapping, or dotted keys such as "
            f"name.field=value), got {value!r}"
        )
    if annotation is bool:
        return _coerce_bool(value)
    if annotation is int:
        return _coerce_int(value)
    if annotation is float:
        return _coerce_float(value)
    if annotation is str:
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise ValueError(f"expected a string, got {value!r}")
        return str(value)
    if annotation is typing.Any:
        return value
    raise TypeError(f"field type {annotation!r} is not supported by the config system")


def _coerce_union(value: Any, args: tuple[Any, ...]) -> Any:
    is_none = value is None or (isinstance(value, str) and value.lower() in ("none", "null"))
    if is_none and type(None) in args:
        return None
    errors = []
    for arg in (a for a in args if a is not type(None)):
        try:
            return coerce(value, arg)
        except ValueError as exc:
            errors.append(str(exc))
    raise ValueError("; ".join(errors))


def _coerce_sequence(value: Any, annotation: Any, kind: type, args: tuple[Any, ...]) -> Any:
    if isinstance(value, str):
        items: list[Any] = [v.strip() for v in value.split(",")] if value.strip() else []
    elif isinstance(value, list | tuple):
        items = list(value)
    else:
        raise ValueError(f"expected a comma-separated list or a sequence, got {value!r}")
    if kind is list:
        inner = args[0] if args else str
        return [coerce(v, inner) for v in items]
    if not args or (len(args) == 2 and args[1] is Ellipsis):
        inner = args[0] if args else str
        return tuple(coerce(v, inner) for v in items)
    if len(items) != len(args):
        raise ValueError(f"expected {len(args)} values, got {value!r}")
    return tuple(coerce(v, a) for v, a in zip(items, args, strict=True))


def _coerce_bool(value: Any) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.lower() in (*_TRUE, *_FALSE):
        return value.lower() in _TRUE
    raise ValueError(f"expected a boolean, got {value!r}")


def _coerce_int(value: Any) -> int:
    if isinstance(value, bool):
        raise ValueError(f"expected an integer, got {value!r}")
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, str):
        try:
            return int(value.strip())
        except ValueError:
            pass
    raise ValueError(f"expected an integer, got {value!r}")


def _coerce_float(value: Any) -> float:
    if isinstance(value, bool):
        raise ValueError(f"expected a number, got {value!r}")
    if isinstance(value, int | float):
        return float(value)
    if isinstance(value, str):
        try:
            return float(value.strip())
        except ValueError:
            pass
    raise ValueError(f"expected a number, got {value!r}")


def config_to_data(config: Any) -> dict[str, Any]:
    """A config as plain YAML/JSON data: every field (defaults included), tuples as lists.

    ``build_config(type(config), config_to_data(config), ...)`` gives ``config`` back.
    """
    return _plain(dataclasses.asdict(config))


def _plain(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value
