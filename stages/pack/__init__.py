"""The ``pack`` stage (training samples with a quality gate) and the pack-shard reader."""
