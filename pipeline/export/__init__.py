"""Exports of a run to other tools' formats and viewers (MCAP for Foxglove, VideoX-Fun, EgoSim CSV, DWM)."""
