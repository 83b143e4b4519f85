"""The static HTML dataset report of a run (``egosim report RUN --out DIR``).

- :mod:`.run_data` reads a run folder's records (summary, manifest, rejects) and its shards;
- :mod:`.quality` lists the per-clip quality figures each stage records;
- :mod:`.sheets` draws a clip's contact sheet and side-by-side video (``bench/real_sheets.py``
  uses it too);
- :mod:`.html` writes the page, plotly.js beside it and the clips' sheets and videos.
"""

from egosim.pipeline.report.html import SECTIONS, ReportConfig, write_report
from egosim.pipeline.report.run_data import RunFolderError, load_run

__all__ = ["SECTIONS", "ReportConfig", "RunFolderError", "load_run", "write_report"]
