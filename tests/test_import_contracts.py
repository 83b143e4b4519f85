"""Import contracts (ARCHITECTURE.md section 1), checked on the source by a small AST walk.

- A stage never imports another stage; shared pieces live in ``egosim.stages.common``,
  ``egosim.pipeline`` or ``egosim.schemas``. (``stages/__init__.py`` is the registry: it imports
  every stage.)
- ``egosim.stages.common`` imports no stage.
- ``model/`` never imports ``pipeline/``, ``stages/`` or ``world/``.
- ``schemas/`` imports nothing of egosim but ``schemas``.
- The synthetic world (``world/``, ``egosim.world``) is a library: it imports no stage and, of
  ``pipeline/``, only the data layer (:data:`WORLD_PIPELINE_MODULES`), never the stage API, the
  runner or the CLI. Of the stages only ``ingest`` (its synthetic source) imports the world.

Imports inside functions count as well as module-level ones; relative imports are resolved.
"""

from __future__ import annotations

import ast
import importlib.util
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOP = ("pipeline", "schemas", "stages", "model", "world")  # folders installed as egosim.<name>
# The pipeline modules the synthetic world may build on: geometry, clip records, media codecs and
# the EgoDex file format it writes. Everything else in pipeline/ runs or plans stages.
WORLD_PIPELINE_MODULES = ("geometry", "records", "media", "egodex_format")
WORLD_STAGES = ("ingest",)  # the stages that may import the synthetic world

# Known violations, each with why it is still here. The list only shrinks: an entry that no
# longer matches an import fails the test too, so fixing one means deleting its line.
ALLOWED: dict[tuple[str, str], str] = {
    # (importing module, imported module): reason
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(("egosim", *parts))


def _imports(path: Path) -> Iterator[str]:
    """Every module ``path`` imports (``from a import b`` gives ``a`` and ``a.b``)."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            yield base
            yield from (f"{base}.{alias.name}" for alias in node.names)


def _stage_of(module: str) -> str | None:
    """``x`` for ``egosim.stages.x...``, None outside stage packages."""
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[:2] == ["egosim", "stages"] else None


def _world_problem(imported: str) -> str | None:
    """Why the synthetic world may not import ``imported`` (None when it may)."""
    parts = imported.split(".")
    if parts[1] in ("world", "schemas"):
        return None
    if parts[1] == "pipeline" and (len(parts) == 2 or parts[2] in WORLD_PIPELINE_MODULES):
        return None
    if parts[1] == "pipeline":
        return (
            f"the synthetic world imports {'.'.join(parts[:3])} (of pipeline/ it may use only "
            f"{', '.join(WORLD_PIPELINE_MODULES)})"
        )
    return f"the synthetic world imports {parts[1]}/"


def _problem(importer: str, imported: str) -> str | None:
    """Why ``importer`` may not import ``imported`` (None when it may)."""
    if not imported.startswith("egosim."):
        return None
    top = importer.split(".")[1]
    target_top = imported.split(".")[1]
    if top == "model" and target_top in ("pipeline", "stages", "world"):
        return f"model/ imports {target_top}/"
    if top == "schemas" and target_top != "schemas":
        return f"schemas/ imports {target_top}/"
    if top == "world":
        return _world_problem(imported)
    own, other = _stage_of(importer), _stage_of(imported)
    if own is not None and target_top == "world" and own not in WORLD_STAGES:
        return f"stage {own!r} imports the synthetic world (only {', '.join(WORLD_STAGES)} may)"
    if own is None or other is None or other in (own, "common"):
        return None
    return f"stage {own!r} imports stage {other!r}"


def _violations() -> dict[tuple[str, str], str]:
    found: dict[tuple[str, str], str] = {}
    for top in TOP:
        for path in sorted((REPO / top).rglob("*.py")):
            importer = _module_name(path)
            if importer == "egosim.stages":  # the registry imports every stage
                continue
            for imported in _imports(path):
                problem = _problem(importer, imported)
                if problem is not None:
                    found[(importer, imported)] = problem
    return found


def _allowed(key: tuple[str, str]) -> bool:
    importer, imported = key
    return any(
        importer == a and (imported == b or imported.startswith(b + ".")) for a, b in ALLOWED
    )


def test_no_stage_imports_another_stage_and_model_stays_below_pipeline() -> None:
    found = _violations()
    bad = [f"{a} -> {b}: {why}" for (a, b), why in sorted(found.items()) if not _allowed((a, b))]
    assert not bad, "import contracts broken:\n  " + "\n  ".join(bad)


def test_allow_list_has_no_stale_entries() -> None:
    found = _violations()
    stale = [
        f"{a} -> {b}"
        for a, b in ALLOWED
        if not any(i == a and (j == b or j.startswith(b + ".")) for i, j in found)
    ]
    assert not stale, "remove these ALLOWED entries, the imports are gone: " + ", ".join(stale)


def test_the_checker_sees_violations(tmp_path: Path) -> None:
    assert _problem("egosim.stages.train.run", "egosim.stages.pack.dataset")
    assert _problem("egosim.model.metrics", "egosim.pipeline.geometry")
    assert _problem("egosim.stages.common.x", "egosim.stages.pack")
    assert _problem("egosim.stages.pack.stage", "egosim.stages.common.packed") is None
    assert _problem("egosim.stages.pack.stage", "egosim.stages.pack.dataset") is None
    assert _problem("egosim.stages.train.run", "egosim.pipeline.media") is None
    # the synthetic world: a library below the stages, above pipeline's data layer
    assert _problem("egosim.world.egodex_export", "egosim.stages.ingest.egodex")
    assert _problem("egosim.world.clip", "egosim.stages.common.gripper")
    assert _problem("egosim.world.clip", "egosim.pipeline.runner")
    assert _problem("egosim.world.clip", "egosim.pipeline.cli.app")
    assert _problem("egosim.world.clip", "egosim.pipeline.stage")
    assert _problem("egosim.world.clip", "egosim.model.network")
    assert _problem("egosim.world.clip", "egosim.pipeline.geometry.look_at") is None
    assert _problem("egosim.world.egodex_export", "egosim.pipeline.egodex_format") is None
    assert _problem("egosim.world.clip", "egosim.world.scene") is None
    assert _problem("egosim.stages.hands.stage", "egosim.world.clip")
    assert _problem("egosim.stages.common.gripper", "egosim.world")
    assert _problem("egosim.model.metrics", "egosim.world.robot")
    assert _problem("egosim.stages.ingest.synthetic_source", "egosim.world.clip") is None


def test_the_world_is_walked_and_left_no_shim_in_stages() -> None:
    """world/ is checked like the other top folders, and ``egosim.stages.world`` is gone."""
    assert _module_name(REPO / "world" / "clip.py") == "egosim.world.clip"
    imports = set(_imports(REPO / "stages" / "ingest" / "synthetic_source.py"))
    assert "egosim.world.clip" in imports  # the one stage that calls the world still does
    assert not (REPO / "stages" / "world").exists()
    assert importlib.util.find_spec("egosim.stages.world") is None
