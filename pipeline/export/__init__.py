"""Exports of a run: MCAP for Foxglove, VideoX-Fun, the EgoSim CSV and DWM folder layouts."""
