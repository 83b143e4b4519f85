"""The ``ingest`` stage and its source backends."""
