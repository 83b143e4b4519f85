"""Exports of a run: MCAP for Foxglove, VideoX-Fun, the EgoSim CSV and DWM folder layouts.

- :mod:`.foxglove`: Foxglove message builders (the one pixel-centre conversion, ``cx - 0.5``);
- :mod:`.run_index`: a run's steps by the schema they wrote, one clip's row from any step;
- :mod:`.view`: ``egosim view``, one MCAP per clip with every step's output aligned;
- :mod:`.pack_rows`: the pack-row decoder and the inpainting mask (shared with stages);
- :mod:`.files`: reading pack samples, atomic file writes, paths kept under the output;
- :mod:`.videox_fun`, :mod:`.egosim_csv`, :mod:`.dwm`: ``egosim export FORMAT RUN --out DIR``.

Pipeline code: nothing here imports a stage.
"""
