"""The ``evaluate`` stage (per-clip figures) and the per-clip + overall report."""
