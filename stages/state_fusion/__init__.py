"""``state_fusion``: interaction-aware world-state update after a clip (EgoSim section 3.3)."""
