"""Render one synthetic clip with full ground truth: :func:`render_clip`."""

from __future__ import annotations

import numpy as np

from egosim.pipeline.geometry import intrinsics_from_fov
from egosim.pipeline.records import Clip
from egosim.world.camera_alt import alt_fov_deg, camera_path_alt
from egosim.world.camera_path import camera_path
from egosim.world.config import WorldConfig
from egosim.world.hands import (
    FOREARM_LENGTH,
    forearm_mesh,
    hand_joints_world,
    hand_mesh,
)
from egosim.world.hands_alt import AltBody
from egosim.world.interaction import LEFT_SIDE, RIGHT_SIDE, Interaction, script_interaction
from egosim.world.meshes import Mesh
from egosim.world.render import WorldRenderer, to_uint8
from egosim.world.scene import Scene, build_scene
from egosim.world.scene_alt import build_scene_alt

SKIN_TONES = np.array(
    [[0.96, 0.80, 0.69], [0.90, 0.70, 0.56], [0.78, 0.57, 0.42], [0.56, 0.38, 0.26]]
)
SIDES = (LEFT_SIDE, RIGHT_SIDE)


def hand_joints(interaction: Interaction) -> np.ndarray:
    """World joints ``(T, 2, 21, 3)`` of both hands of a scripted interaction."""
    t = interaction.curl.shape[0]
    return np.stack(
        [
            np.stack(
                [
                    hand_joints_world(interaction.world_from_hand[k, h], interaction.curl[k, h], s)
                    for h, s in enumerate(SIDES)
                ]
            )
            for k in range(t)
        ]
    )  # (T, 2, 21, 3)


def _elbow(wrist: np.ndarray, world_from_cam: np.ndarray, side: int) -> np.ndarray:
    """Elbow ``(3,)``: behind the wrist as seen from the shoulder of ``side``, a little higher.

    The forearm then lies low over the table and enters the view from the bottom.
    """
    right = world_from_cam[:3, 0]
    shoulder = world_from_cam[:3, 3] + 0.18 * side * right  # (3,)
    away = wrist[:2] - shoulder[:2]
    away /= max(float(np.linalg.norm(away)), 1e-9)
    direction = np.array([-away[0], -away[1], 0.15])
    return wrist + FOREARM_LENGTH * direction / np.linalg.norm(direction)


def _default_parts(
    joints: np.ndarray, world_from_hand: np.ndarray, world_from_cam: np.ndarray
) -> list[Mesh]:
    """``[left hand, left forearm, right hand, right forearm]`` meshes of the default variant.

    ``joints (2, 21, 3)`` and ``world_from_hand (2, 4, 4)`` are the left and right hands.
    """
    parts: list[Mesh] = []
    for side_index, side in enumerate(SIDES):
        wrist = joints[side_index, 0]
        parts.append(hand_mesh(joints[side_index], world_from_hand[side_index], side))
        parts.append(forearm_mesh(wrist, _elbow(wrist, world_from_cam, side)))
    return parts


def world_cameras(config: WorldConfig) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics ``(4,)`` and ``world_from_cam (T, 4, 4)`` of the config's variant.

    Builds no scene: the camera path has its own random stream, so it is the one
    :func:`render_clip` uses whether or not the scene is built.
    """
    t, h, w = config.num_frames, config.height, config.width
    if config.variant == "alt":
        fov = alt_fov_deg(config.seed, config.horizontal_fov_deg)
        return (
            intrinsics_from_fov(w, h, fov),
            camera_path_alt(config.seed, config.mode, t, config.fps),
        )
    return (
        intrinsics_from_fov(w, h, config.horizontal_fov_deg),
        camera_path(config.seed, config.mode, t, config.fps),
    )


def world_scene(config: WorldConfig) -> Scene:
    """The textured scene of the config's variant (the costly part: its textures)."""
    if config.variant == "alt":
        return build_scene_alt(config.seed, config.articulated)
    return build_scene(config.seed, config.articulated)


def _setup(config: WorldConfig) -> tuple[Scene, np.ndarray, np.ndarray]:
    """Scene, intrinsics ``(4,)`` and ``world_from_cam (T, 4, 4)`` of the config's variant."""
    return (world_scene(config), *world_cameras(config))


def render_clip(config: WorldConfig, clip_id: str | None = None) -> Clip:
    """Render the clip of ``config``: interaction and static videos plus all ground truth.

    Frames, depth and masks are deterministic functions of the config. ``static_frames`` use the
    same camera path without hands and with every object at its initial pose, so
    ``first_frame_clean == static_frames[0]``; outside the hand mask, the interaction video equals
    the static video bit for bit until the first object moves. ``hand_valid`` is True where at
    least one pixel of that hand (or its forearm) is visible; ``object_mask`` holds object
    instance ids ``1..N`` (index into ``object_poses`` plus one) where no hand covers them.
    """
    t, h, w = config.num_frames, config.height, config.width
    scene, intrinsics, world_from_cam = _setup(config)  # world_from_cam (T, 4, 4)
    inter = script_interaction(scene, config.seed, t, config.articulated)
    joints = hand_joints(inter)  # (T, 2, 21, 3)
    if config.variant == "alt":
        alt_body = AltBody(config.seed)
        body, part_colours = alt_body.parts, alt_body.colours  # colours (4, 3)
    else:
        body = _default_parts
        rng = np.random.default_rng([config.seed, 4])
        skin = SKIN_TONES[int(rng.integers(0, len(SKIN_TONES)))] * rng.uniform(0.95, 1.05, 3)
        sleeve = rng.uniform(0.1, 0.6, 3)
        part_colours = np.stack([skin, sleeve, skin, sleeve]).astype(np.float32)  # (4, 3)

    renderer = WorldRenderer(scene, intrinsics, h, w)
    n_bg = len(scene.background)
    initial = scene.initial_object_poses  # (N, 4, 4)
    frames = np.zeros((t, h, w, 3), np.uint8)
    static_frames = np.zeros((t, h, w, 3), np.uint8)
    depth = np.zeros((t, h, w), np.float32)
    static_depth = np.zeros((t, h, w), np.float32)
    hand_mask = np.zeros((t, h, w), np.uint8)
    object_mask = np.zeros((t, h, w), np.uint8)
    hand_valid = np.zeros((t, 2), bool)
    for k in range(t):
        cam = world_from_cam[k]
        rays = renderer.rays(cam)  # (H*W, 6)
        static = renderer.render_static(cam, initial, rays)
        static_frames[k] = to_uint8(static.rgb)
        static_depth[k] = np.where(np.isfinite(static.depth), static.depth, 0.0)
        if np.array_equal(inter.object_poses[k], initial):
            moving = static
        else:
            moving = renderer.render_static(cam, inter.object_poses[k], rays)
        parts = body(joints[k], inter.world_from_hand[k], cam)  # 2 meshes per hand, left first
        hands = renderer.render_meshes(cam, parts, part_colours)
        on_hand = hands.depth < moving.depth  # (H, W)
        frames[k] = to_uint8(np.where(on_hand[..., None], hands.rgb, moving.rgb))
        z = np.where(on_hand, hands.depth, moving.depth)
        depth[k] = np.where(np.isfinite(z), z, 0.0)
        hand_mask[k] = on_hand
        is_object = ~on_hand & (moving.ids >= n_bg)
        object_mask[k] = np.where(is_object, moving.ids - n_bg + 1, 0)
        hand_valid[k] = [np.any(on_hand & (hands.ids // 2 == s)) for s in range(2)]
    if clip_id is None:
        kind = "lid" if config.articulated else "pick"
        variant = "" if config.variant == "default" else f"{config.variant}-"
        clip_id = f"synthetic-{variant}{config.mode}-{kind}-{config.seed:06d}"
    return Clip(
        clip_id=clip_id,
        source="synthetic",
        source_uri="",
        fps=float(config.fps),
        timestamps=np.arange(t) / float(config.fps),
        intrinsics=intrinsics,
        frames=frames,
        world_from_cam=world_from_cam,
        depth=depth,
        static_frames=static_frames,
        static_depth=static_depth,
        first_frame_clean=static_frames[0].copy(),
        hand_joints=joints.astype(np.float32),
        hand_valid=hand_valid,
        hand_confidence=np.ones((t, 2, 21), np.float32),
        hand_mask=hand_mask,
        object_mask=object_mask,
        object_poses=inter.object_poses,
        text=inter.text,
    ).check()
