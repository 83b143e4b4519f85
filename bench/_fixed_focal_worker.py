"""The SfM worker with the focal held at its prior (never refined); for bench.egodex_scale_probe.

Run as ``python bench/_fixed_focal_worker.py WORK`` in place of
``stages/depth_camera/sfm_worker.py``: same inputs and outputs, but every incremental mapping
keeps the focal it is given (``SfmOptions.focal_factors`` / ``prior_focal``), so a probe can ask
how well the clip's frames fit a given focal (reprojection error) instead of self-calibrating.
"""

from __future__ import annotations

import importlib.util
import sys
import zlib  # noqa: F401  (zlib before pycolmap: HAZARDS.md)
from pathlib import Path

import numpy as np  # noqa: F401

WORKER = Path(__file__).resolve().parents[1] / "stages" / "depth_camera" / "sfm_worker.py"


def main(argv: list[str]) -> int:
    """Run the stage's worker on ``argv[0]`` with focal refinement off; returns its exit code."""
    spec = importlib.util.spec_from_file_location("egosim_sfm_worker_fixed", WORKER)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    original = module._map

    def fixed(work, db, opts, out, refine_focal=True):  # the stage's call, focal held
        return original(work, db, opts, out, False)

    module._map = fixed
    return module.main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
