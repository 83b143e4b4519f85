"""Training on pack shards (``egosim train``): a whole-dataset step, not a per-clip stage."""
