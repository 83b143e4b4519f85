"""Import contracts (ARCHITECTURE.md section 1), checked on the source by a small AST walk.

- A stage never imports another stage; shared pieces live in ``egosim.stages.common``,
  ``egosim.pipeline`` or ``egosim.schemas``. (``stages/__init__.py`` is the registry: it imports
  every stage.)
- ``egosim.stages.common`` imports no stage.
- ``model/`` never imports ``pipeline/`` or ``stages/``.
- ``schemas/`` imports nothing of egosim but ``schemas``.

Imports inside functions count as well as module-level ones; relative imports are resolved.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOP = ("pipeline", "schemas", "stages", "model")  # folders installed as egosim.<name>

# Known violations, each with why it is still here. The list only shrinks: an entry that no
# longer matches an import fails the test too, so fixing one means deleting its line.
ALLOWED: dict[tuple[str, str], str] = {
    # (importing module, imported module): reason
    ("egosim.stages.ingest.synthetic_source", "egosim.stages.world"): (
        "being moved: the synthetic world becomes a library outside stages/ (issue 12)"
    ),
    ("egosim.stages.world.egodex_export", "egosim.stages.ingest.egodex"): (
        "being moved: the synthetic world becomes a library outside stages/ (issue 12)"
    ),
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


def _problem(importer: str, imported: str) -> str | None:
    """Why ``importer`` may not import ``imported`` (None when it may)."""
    if not imported.startswith("egosim."):
        return None
    top = importer.split(".")[1]
    target_top = imported.split(".")[1]
    if top == "model" and target_top in ("pipeline", "stages"):
        return f"model/ imports {target_top}/"
    if top == "schemas" and target_top != "schemas":
        return f"schemas/ imports {target_top}/"
    own, other = _stage_of(importer), _stage_of(imported)
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
