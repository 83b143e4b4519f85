"""The static HTML dataset report of a run (egosim report RUN --out DIR)."""
