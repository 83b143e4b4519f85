"""Stage registry, config building and workflow checks (every problem reported at once)."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import pytest
import yaml

from egosim.pipeline.stage import (
    ClipStage,
    ConfigError,
    StageConfig,
    StageError,
    build_config,
    coerce,
    get_stage,
    register_stage,
    registered_stages,
)
from egosim.pipeline.workflow import WorkflowError, parse_workflow
from egosim.schemas import CLIPS, REJECTS, ShardSchema


class NeedsRejects(ClipStage):
    """A test stage whose input schema no built-in stage writes (``rejects``)."""

    name = "test_needs_rejects"
    description = "test only"
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"table": REJECTS}
    output = CLIPS

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        raise NotImplementedError


if "test_needs_rejects" not in registered_stages():
    register_stage(NeedsRejects)


@dataclass(frozen=True)
class DemoConfig(StageConfig):
    count: int = 1  # an integer
    ratio: float = 0.5  # a float
    flag: bool = False  # a boolean
    mode: Literal["a", "b"] = "a"  # a choice
    sizes: tuple[int, ...] = ()  # a tuple
    path: str | None = None  # optional


def test_registry_refuses_duplicates_and_unknown_names() -> None:
    with pytest.raises(StageError, match="already registered"):
        register_stage(get_stage("ingest"))
    with pytest.raises(StageError, match="unknown stage 'nope'"):
        get_stage("nope")


def test_build_config_converts_strings_and_reports_all_problems() -> None:
    cfg = build_config(
        DemoConfig,
        {"count": "3", "ratio": "0.25", "flag": "true", "mode": "b", "sizes": "1,2", "path": "x"},
        "demo",
    )
    assert cfg == DemoConfig(3, 0.25, True, "b", (1, 2), "x")
    with pytest.raises(ConfigError) as err:
        build_config(DemoConfig, {"count": "many", "mode": "c", "colour": 1}, "demo")
    message = str(err.value)
    assert "unknown parameter 'colour'" in message
    assert "'count'" in message and "'mode'" in message


def test_ingest_config_checks_values() -> None:
    with pytest.raises(ConfigError, match="num_frames must be >= 1, got -1"):
        get_stage("ingest").from_params({"num_frames": -1})


def test_workflow_reports_every_problem_before_running() -> None:
    data = {
        "name": "bad",
        "colour": "blue",
        "steps": {
            "ingest": {"stage": "ingest", "params": {"fsp": 16}, "retries": 2},
            "ghost": {"stage": "no_such_stage"},
            "table": {"stage": "test_needs_rejects", "inputs": {"table": "ingest"}},
            "orphan": {"stage": "test_needs_rejects", "inputs": {"table": "missing_step"}},
        },
    }
    with pytest.raises(WorkflowError) as err:
        parse_workflow(data, overrides=["ingest.fps=abc", "nostep.x=1"])
    message = str(err.value)
    for expected in (
        "unknown workflow key 'colour'",
        "step 'ingest': unknown key 'retries'",
        "unknown parameter 'fsp'",
        "parameter 'fps'",
        "unknown step 'nostep'",
        "unknown stage 'no_such_stage'",
        "needs schema 'rejects' v1 but step 'ingest' writes 'clips' v5",
        "unknown step 'missing_step'",
    ):
        assert expected in message, expected


def test_workflow_orders_steps_and_applies_overrides() -> None:
    wf = parse_workflow(
        {"steps": {"ingest": {"params": {"fps": 8}}}}, overrides=["ingest.num_frames=9"]
    )
    assert [s.name for s in wf.steps] == ["ingest"]
    params = wf.steps[0].params  # resolved: typed, every field, defaults included
    assert params["fps"] == 8.0 and isinstance(params["fps"], float)
    assert params["num_frames"] == 9 and params["synthetic_count"] == 4
    assert set(params) == {f.name for f in dataclasses.fields(get_stage("ingest").config_class)}


def test_build_config_is_strict_and_nested() -> None:
    from egosim.model.train import TrainConfig

    cfg = build_config(TrainConfig, {"lora.rank": "8", "optim.betas": "0.8, 0.9"}, "train")
    assert cfg.lora.rank == 8 and cfg.optim.betas == (0.8, 0.9)
    assert build_config(TrainConfig, {"optim.lr": "1e-5"}, "train").optim.lr == 1e-5
    assert build_config(TrainConfig, {"lora": {"alpha": 2}}, "train").lora.alpha == 2.0
    for params, expected in (
        ({"lora": "8"}, "parameter 'lora': expected LoRAConfig fields"),
        ({"lora.rnk": "8"}, "unknown parameter 'lora.rnk'"),
        ({"steps.x": "1"}, "parameter 'steps' has no fields"),
        ({"optim.betas": "0.9"}, "expected 2 values, got '0.9'"),
        ({"steps": "2.5"}, "expected an integer, got '2.5'"),
        ({"optim.lr": "fast"}, "expected a number, got 'fast'"),
        ({"optim.lr": True}, "expected a number, got True"),
        ({"lr": "1e-4"}, "unknown parameter 'lr'"),
        ({"finetune": ["full"]}, "expected a string, got ['full']"),
        ({"ema_decay": "x"}, "got 'x'"),
    ):
        with pytest.raises(ConfigError, match=re.escape(expected)):
            build_config(TrainConfig, params, "train")
    assert coerce("none", float | None) is None and coerce("", tuple[int, ...]) == ()


def test_build_config_refuses_unsupported_field_types() -> None:
    @dataclass(frozen=True)
    class Odd:
        where: Path = Path()  # a type the config system does not convert

    with pytest.raises(TypeError, match="not supported"):
        coerce("x", Path)
    with pytest.raises(ConfigError, match="not supported"):
        build_config(Odd, {"where": "x"}, "odd")


def test_resolved_workflow_round_trips_typed() -> None:
    wf = parse_workflow({"steps": {"ingest": {}}}, overrides=["ingest.synthetic_count=2"])
    data = yaml.safe_load(yaml.safe_dump(wf.to_dict()))
    ingest = data["steps"]["ingest"]["params"]
    assert ingest["synthetic_count"] == 2 and ingest["fps"] == 16.0 and "tail" in ingest
    assert parse_workflow(data).to_dict() == wf.to_dict()
