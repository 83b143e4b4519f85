"""Run every benchmark, print a table and write ``bench/results.jsonl``.

Each ``bench/bench_*.py`` module exposes functions named ``bench_*`` that return a list of
figures: ``{"name", "value", "unit", "baseline", "baseline_value"}``, the baseline measured in
the same run. The ratio column is ``value / baseline_value``. Run one module with
``python -m bench.run --only scene_render``.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import platform
import time
import traceback
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
RESULTS = BENCH_DIR / "results.jsonl"


def collect(only: str | None) -> list[tuple[str, object]]:
    """Every ``bench_*`` function of every ``bench/bench_*.py`` module (optionally filtered)."""
    found = []
    for path in sorted(BENCH_DIR.glob("bench_*.py")):
        if only and only not in path.stem:
            continue
        module = importlib.import_module(f"bench.{path.stem}")
        for name, fn in inspect.getmembers(module, inspect.isfunction):
            if name.startswith("bench_") and fn.__module__ == module.__name__:
                found.append((f"{path.stem}.{name}", fn))
    return found


def main() -> int:
    """Run the benchmarks; returns a process exit code (1 if any benchmark raised)."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--only", help="run modules whose name contains this")
    args = parser.parse_args()
    figures: list[dict] = []
    failed = 0
    for label, fn in collect(args.only):
        start = time.perf_counter()
        try:
            results = fn()
        except Exception:  # a broken benchmark is reported, the others still run
            failed += 1
            print(f"{label} FAILED\n{traceback.format_exc()}")
            continue
        for fig in results:
            fig = {**fig, "benchmark": label, "host": platform.node()}
            base = fig.get("baseline_value")
            fig["ratio"] = fig["value"] / base if base else None
            figures.append(fig)
        print(f"{label}: {time.perf_counter() - start:.1f} s")
    with RESULTS.open("w") as fh:
        for fig in figures:
            fh.write(json.dumps(fig) + "\n")
    header = f"{'figure':46} {'value':>12} {'unit':10} {'baseline':34} {'ratio':>8}"
    print("\n" + header + "\n" + "-" * len(header))
    for fig in figures:
        ratio = f"{fig['ratio']:.2f}" if fig["ratio"] is not None else "-"
        baseline = f"{fig.get('baseline', '-')}"[:34]
        print(f"{fig['name']:46} {fig['value']:12.4g} {fig['unit']:10} {baseline:34} {ratio:>8}")
    print(f"\nwrote {len(figures)} figures to {RESULTS}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
