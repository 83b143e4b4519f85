"""Encode a :class:`State` as a ``state`` row and decode it back."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from egosim.stages.state_fusion.fusion import Instance, State


def row_from_state(state: State, clip_id: str | None = None) -> dict[str, Any]:
    """One ``state`` row holding ``state`` (point arrays as little-endian bytes).

    ``clip_id`` keys the row (default: the clip the state was fused from).
    """
    t = state.num_frames
    insts = state.instances
    return {
        "clip_id": state.clip_id if clip_id is None else clip_id,
        "state_clip_id": state.clip_id,
        "previous_clip_id": state.previous_clip_id,
        "world_frame": state.world_frame,
        "num_frames": t,
        "num_points": len(state.points),
        "points_xyz": state.points.astype("<f4").tobytes(),
        "points_rgb": state.colours.astype(np.uint8).tobytes(),
        "point_size": state.point_size.astype("<f4").tobytes(),
        "point_instance": state.instance.astype("<i4").tobytes(),
        "point_source": state.source.astype(np.uint8).tobytes(),
        "instance_id": [int(i.id) for i in insts],
        "instance_label": [i.label for i in insts],
        "instance_interactive": [bool(i.interactive) for i in insts],
        "instance_last_observed_frame": [int(i.last_observed_frame) for i in insts],
        "instance_geometry_frame": [int(i.geometry_frame) for i in insts],
        "instance_interaction": [np.asarray(i.interaction, bool).tolist() for i in insts],
        "instance_depth_gap_m": [np.asarray(i.depth_gap, np.float32).tolist() for i in insts],
        "instance_centroid": [np.asarray(i.centroid, np.float64).tolist() for i in insts],
        "width": int(state.width),
        "height": int(state.height),
        "intrinsics": np.asarray(state.intrinsics, np.float64).tolist(),
        "world_from_cam": np.asarray(state.world_from_cam).reshape(-1, 16).tolist(),
        "camera_frames": list(state.camera_frames),
        "previous_from_clip": np.asarray(state.previous_from_clip).reshape(16).tolist(),
        "sim3_scale": float(state.sim3_scale),
        "registration_rms_m": state.registration_rms,
    }


def state_from_row(row: Mapping[str, Any]) -> State:
    """Decode one ``state`` row into a :class:`State`."""
    n = int(row["num_points"])
    t = int(row["num_frames"])
    insts = [
        Instance(
            id=int(iid),
            label=str(label),
            interactive=bool(inter),
            last_observed_frame=int(last),
            geometry_frame=int(geo),
            interaction=np.asarray(status, bool).reshape(t),
            depth_gap=np.asarray([np.nan if g is None else g for g in gap], np.float32),
            centroid=np.asarray(centroid, np.float64),
        )
        for iid, label, inter, last, geo, status, gap, centroid in zip(
            row["instance_id"],
            row["instance_label"],
            row["instance_interactive"],
            row["instance_last_observed_frame"],
            row["instance_geometry_frame"],
            row["instance_interaction"],
            row["instance_depth_gap_m"],
            row["instance_centroid"],
            strict=True,
        )
    ]
    scale = float(row["sim3_scale"])
    return State(
        clip_id=row["state_clip_id"],
        previous_clip_id=row["previous_clip_id"],
        world_frame=row["world_frame"],
        num_frames=t,
        points=np.frombuffer(row["points_xyz"], dtype="<f4").reshape(n, 3).astype(np.float32),
        colours=np.frombuffer(row["points_rgb"], dtype=np.uint8).reshape(n, 3).copy(),
        point_size=np.frombuffer(row["point_size"], dtype="<f4").astype(np.float32),
        instance=np.frombuffer(row["point_instance"], dtype="<i4").astype(np.int32),
        source=np.frombuffer(row["point_source"], dtype=np.uint8).copy(),
        instances=insts,
        intrinsics=np.asarray(row["intrinsics"], np.float64),
        width=int(row["width"]),
        height=int(row["height"]),
        world_from_cam=np.asarray(row["world_from_cam"], np.float64).reshape(-1, 4, 4),
        camera_frames=list(row["camera_frames"]),
        previous_from_clip=np.asarray(row["previous_from_clip"], np.float64).reshape(4, 4),
        sim3_scale=scale,
        registration_rms=row["registration_rms_m"],
    )
