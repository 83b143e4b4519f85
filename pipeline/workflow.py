"""Workflow YAML: steps that chain stages; checked as a whole before anything runs.

Format::

    name: dataset            # workflow name
    inputs: {pack: pack}     # optional: shards the run is given (name -> schema), not made here
    steps:
      ingest:                # step name (unique)
        stage: ingest        # registered stage (defaults to the step name)
        params: {source: synthetic}
      pose_clean:
        stage: pose_clean
        inputs: {clips: ingest}    # role -> upstream step or workflow input (a bare name fills
                                   # the one role)
        resources: {GPU: 1}        # Dask worker resources this step needs

Every problem (unknown keys, unknown stages or parameters, missing or unknown input roles,
schema mismatches between connected steps, cycles, step names that break the identifier rule of
:mod:`egosim.schemas.ids`) is collected into one :class:`WorkflowError`.

Resource bounds: a workflow file is at most :data:`MAX_WORKFLOW_BYTES`; once loaded, its data
counted with every YAML alias expanded (as anything that walks it would see it) is at most
:data:`MAX_WORKFLOW_VALUES` values and :data:`MAX_WORKFLOW_CHARS` characters of strings, so
nested aliases ("billion laughs") are refused in milliseconds instead of exhausting memory.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from egosim.pipeline.stage import (
    ConfigError,
    SourceStage,
    StageError,
    build_config,
    config_to_data,
    get_stage,
)
from egosim.schemas import SCHEMAS
from egosim.schemas.ids import id_problems

MAX_WORKFLOW_BYTES = 1 << 20  # largest workflow file read (1 MiB)
MAX_WORKFLOW_VALUES = 100_000  # most values (keys included) once aliases are expanded
MAX_WORKFLOW_CHARS = 10_000_000  # most string characters once aliases are expanded

WORKFLOW_KEYS = {"name", "description", "inputs", "steps"}
STEP_KEYS = {"stage", "params", "inputs", "resources"}


class WorkflowError(StageError):
    """A workflow file is invalid; the message lists every problem found."""


@dataclass(frozen=True)
class Step:
    """One step of a workflow."""

    name: str  # step name, unique within the workflow
    stage: str  # registered stage name
    params: dict[str, Any] = field(default_factory=dict)  # resolved parameters: every field
    inputs: dict[str, str] = field(default_factory=dict)  # role -> upstream step name
    resources: dict[str, float] = field(default_factory=dict)  # Dask resources, e.g. GPU: 1


@dataclass(frozen=True)
class Workflow:
    """A checked workflow: steps in an order where every step follows its inputs."""

    name: str  # workflow name
    steps: tuple[Step, ...]  # topologically ordered
    inputs: dict[str, str] = field(default_factory=dict)  # given shards: name -> schema name

    def step(self, name: str) -> Step:
        """The step called ``name``."""
        return next(s for s in self.steps if s.name == name)

    def to_dict(self) -> dict[str, Any]:
        """The resolved workflow as YAML-ready data (saved next to run outputs)."""
        return {
            "name": self.name,
            **({"inputs": dict(self.inputs)} if self.inputs else {}),
            "steps": {
                s.name: {
                    "stage": s.stage,
                    "params": s.params,
                    "inputs": s.inputs,
                    "resources": s.resources,
                }
                for s in self.steps
            },
        }


def load_workflow(path: Path, overrides: Sequence[str] = ()) -> Workflow:
    """Read, override (``step.param=value``) and check a workflow file."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_WORKFLOW_BYTES + 1)
        if len(raw) > MAX_WORKFLOW_BYTES:
            raise WorkflowError(f"{path}: workflow file is larger than {MAX_WORKFLOW_BYTES} bytes")
        data = yaml.safe_load(raw.decode("utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise WorkflowError(f"{path}: cannot read workflow ({exc})") from exc
    check_expanded_size(data, str(path))
    return parse_workflow(data, overrides, where=str(path))


def check_expanded_size(
    data: Any,
    where: str,
    max_values: int = MAX_WORKFLOW_VALUES,
    max_chars: int = MAX_WORKFLOW_CHARS,
) -> None:
    """Raise :class:`WorkflowError` if ``data`` with aliases expanded exceeds the bounds.

    YAML aliases make shared (even self-referencing) objects; this walk visits a shared object
    once per reference, as printing or hashing it would, and stops at the first bound crossed,
    so its cost is bounded by ``max_values`` whatever the input.
    """
    values, chars = 0, 0
    stack = [data]
    while stack:
        item = stack.pop()
        values += 1
        if isinstance(item, str | bytes):
            chars += len(item)
        elif isinstance(item, Mapping):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, list | tuple | set):
            stack.extend(item)
        if values > max_values or chars > max_chars:
            raise WorkflowError(
                f"{where}: workflow expands to more than {max_values} values or {max_chars} "
                "characters (nested YAML aliases?)"
            )


def parse_workflow(data: Any, overrides: Sequence[str] = (), where: str = "workflow") -> Workflow:
    """Check workflow data (as loaded from YAML) and return a :class:`Workflow`."""
    problems: list[str] = []
    if not isinstance(data, Mapping) or not isinstance(data.get("steps"), Mapping):
        raise WorkflowError(f"{where}: a workflow is a mapping with a 'steps' mapping")
    problems += [f"unknown workflow key {k!r}" for k in data if k not in WORKFLOW_KEYS]
    raw_steps: dict[str, dict[str, Any]] = {}
    for name, body in data["steps"].items():
        # Step names become folder names under --out: the identifier rule applies.
        problems += [f"step {name!r}: {p}" for p in id_problems(name, "step name")]
        if not isinstance(body, Mapping):
            problems.append(f"step {name!r}: expected a mapping, got {body!r}")
            continue
        problems += [f"step {name!r}: unknown key {k!r}" for k in body if k not in STEP_KEYS]
        raw_steps[str(name)] = {
            "stage": body.get("stage", name),
            "params": dict(body.get("params") or {}),
            "inputs": body.get("inputs") or {},
            "resources": dict(body.get("resources") or {}),
        }
    inputs = _check_workflow_inputs(data.get("inputs") or {}, raw_steps, problems)
    problems += _apply_overrides(raw_steps, overrides)
    steps = {n: _check_step(n, b, problems) for n, b in raw_steps.items()}
    _check_edges(steps, inputs, problems)
    order = _topological_order(steps, problems)
    if problems:
        raise WorkflowError(f"{where}: {len(problems)} problem(s):\n  - " + "\n  - ".join(problems))
    name = str(data.get("name", Path(where).stem))
    return Workflow(name=name, steps=tuple(order), inputs=inputs)


def _check_workflow_inputs(
    raw: Any, steps: Mapping[str, Any], problems: list[str]
) -> dict[str, str]:
    """The workflow's given inputs (name -> schema name), checked."""
    if not isinstance(raw, Mapping):
        problems.append(f"workflow inputs must map a name to a schema name, got {raw!r}")
        return {}
    inputs: dict[str, str] = {}
    for name, schema in raw.items():
        found = [f"input {name!r}: {p}" for p in id_problems(name, "input name")]
        if name in steps:
            found.append(f"input {name!r}: a step has the same name")
        if str(schema) not in SCHEMAS:
            found.append(f"input {name!r}: unknown schema {schema!r} (known: {sorted(SCHEMAS)})")
        problems += found
        if not found:
            inputs[str(name)] = str(schema)
    return inputs


def _apply_overrides(steps: dict[str, dict[str, Any]], overrides: Sequence[str]) -> list[str]:
    problems = []
    for item in overrides:
        key, sep, value = item.partition("=")
        step, dot, param = key.partition(".")
        if not sep or not dot:
            problems.append(f"override {item!r} is not step.param=value")
        elif step not in steps:
            problems.append(f"override {item!r} names unknown step {step!r}")
        else:
            steps[step]["params"][param] = value
    return problems


def _check_step(name: str, body: dict[str, Any], problems: list[str]) -> Step:
    stage_name = str(body["stage"])
    inputs = body["inputs"]
    try:
        stage_cls = get_stage(stage_name)
    except StageError as exc:
        problems.append(f"step {name!r}: {exc}")
        return Step(name, stage_name, body["params"], {}, body["resources"])
    if isinstance(inputs, str | list):
        names = [inputs] if isinstance(inputs, str) else list(inputs)
        roles = list(stage_cls.inputs)
        if len(names) != len(roles):
            problems.append(f"step {name!r}: stage {stage_name!r} takes inputs {roles}")
            inputs = {}
        else:
            inputs = dict(zip(roles, names, strict=True))
    params = body["params"]
    try:
        # Every field, typed, defaults included: what the run saves and its tasks use.
        params = config_to_data(
            build_config(stage_cls.config_class, params, where=f"step {name!r}")
        )
    except ConfigError as exc:
        problems.append(str(exc))
    resources = body["resources"]
    if stage_cls.gpu and "GPU" not in resources:
        resources = {**resources, "GPU": 1}
    return Step(name, stage_name, params, dict(inputs), resources)


def _check_edges(steps: dict[str, Step], inputs: Mapping[str, str], problems: list[str]) -> None:
    for step in steps.values():
        try:
            stage_cls = get_stage(step.stage)
        except StageError:
            continue
        expected = stage_cls.input_schemas()
        for role, upstream in step.inputs.items():
            if role not in expected:
                problems.append(
                    f"step {step.name!r}: unknown input role {role!r} "
                    f"(stage {step.stage!r} takes {list(expected)})"
                )
            elif upstream in inputs:
                if inputs[upstream] != expected[role].name:
                    problems.append(
                        f"step {step.name!r}: input {role!r} needs schema "
                        f"{expected[role].name!r} but workflow input {upstream!r} is "
                        f"{inputs[upstream]!r}"
                    )
            elif upstream not in steps:
                problems.append(
                    f"step {step.name!r}: input {role!r} names unknown step {upstream!r}"
                )
            else:
                try:
                    produced = get_stage(steps[upstream].stage).output
                except StageError:
                    continue
                if (
                    produced.name != expected[role].name
                    or produced.version != expected[role].version
                ):
                    problems.append(
                        f"step {step.name!r}: input {role!r} needs schema "
                        f"{expected[role].name!r} v{expected[role].version} but step "
                        f"{upstream!r} writes {produced.name!r} v{produced.version}"
                    )
        missing = [r for r in stage_cls.inputs if r not in step.inputs]
        if missing and not issubclass(stage_cls, SourceStage):
            problems.append(f"step {step.name!r}: missing inputs for roles {missing}")


def _topological_order(steps: dict[str, Step], problems: list[str]) -> list[Step]:
    order: list[Step] = []
    state: dict[str, int] = {}  # 1 = visiting, 2 = done

    def visit(name: str, path: tuple[str, ...]) -> None:
        if state.get(name) == 2 or name not in steps:
            return
        if state.get(name) == 1:
            problems.append(f"cycle between steps: {' -> '.join((*path, name))}")
            return
        state[name] = 1
        for upstream in steps[name].inputs.values():
            visit(upstream, (*path, name))
        state[name] = 2
        order.append(steps[name])

    for name in steps:
        visit(name, ())
    return order
