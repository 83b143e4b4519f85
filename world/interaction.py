"""The scripted hand-object interaction: hand poses, finger closure and object poses per frame.

Pick-and-place: the right hand reaches an object, closes its fingers, lifts and moves it, places
it and lets go; the left hand rests on the table. While held, the object is rigidly attached to
the hand (``world_from_object = world_from_hand @ hand_from_object``, constant
``hand_from_object``). Articulated: the right hand grips the free edge of a container's lid and
swings it open about its hinge. Phases use normalised time, so any clip length gets the whole
interaction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egosim.pipeline.geometry import invert_se3, make_se3, slerp_rotations
from egosim.world.hands import axis_rotation, hand_joints_local
from egosim.world.scene import PLACE_HI, PLACE_LO, TABLE_TOP_Z, Scene, lid_pose, spot_is_free

GRASP_CURL = 0.5  # finger closure while holding
REST_CURL = 0.15  # finger closure of a relaxed hand
REST_CURL_MAX = 0.3  # the idle hand's closure varies up to this
LEFT_SIDE, RIGHT_SIDE = -1, 1  # hand index 0 is left, 1 is right


@dataclass
class Interaction:
    """Everything that moves, per frame."""

    world_from_hand: np.ndarray  # (T, 2, 4, 4) wrist frames, 0 = left, 1 = right
    curl: np.ndarray  # (T, 2) finger closure in [0, 1]
    object_poses: np.ndarray  # (T, N, 4, 4) world_from_object
    target: int  # index of the object the right hand moves (the lid when articulated)
    held: np.ndarray  # (T,) bool: the right hand grips the target (rigidly, when picking)
    text: str  # caption


def _smooth(x: np.ndarray) -> np.ndarray:
    """Smoothstep of ``x`` clipped to [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _phase(u: np.ndarray, start: float, end: float) -> np.ndarray:
    """Eased progress ``(T,)`` in [0, 1] of a phase running from ``start`` to ``end``."""
    return _smooth((u - start) / (end - start))


def _rot_zy(heading: float, pitch: float) -> np.ndarray:
    """Rotation: yaw ``heading`` about world z after tilting the fingers down by ``pitch``."""
    ch, sh, cp, sp = np.cos(heading), np.sin(heading), np.cos(pitch), np.sin(pitch)
    rz = np.array([[ch, -sh, 0.0], [sh, ch, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return rz @ ry


def _blend(pose_a: np.ndarray, pose_b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Poses ``(T, 4, 4)`` moving from ``pose_a`` to ``pose_b`` by weights ``w (T,)``."""
    rots = slerp_rotations(np.array([0.0, 1.0]), np.stack([pose_a[:3, :3], pose_b[:3, :3]]), w)
    trans = (1.0 - w)[:, None] * pose_a[:3, 3] + w[:, None] * pose_b[:3, 3]  # (T, 3)
    return make_se3(rots, trans)


def _grip_point(curl: float) -> np.ndarray:
    """Hand-frame point ``(3,)`` between the thumb tip and the index/middle tips at ``curl``."""
    j = hand_joints_local(curl, RIGHT_SIDE)
    return 0.5 * j[4] + 0.25 * (j[8] + j[12])


def _rest_pose(side: int, rng: np.random.Generator) -> np.ndarray:
    """A relaxed hand just above the table on the near edge of the workspace.

    Its height keeps every joint at least 1.5 cm above the table for any curl up to
    ``REST_CURL_MAX`` (joints are bone axes; the capsules around them are thinner than that).
    """
    rot = _rot_zy(side * np.deg2rad(rng.uniform(5.0, 20.0)), np.deg2rad(8.0))
    lowest = min(float((rot @ hand_joints_local(c, side).T)[2].min()) for c in (0.0, REST_CURL_MAX))
    xy = [-0.22 + rng.uniform(-0.02, 0.03), -side * rng.uniform(0.15, 0.22)]
    return make_se3(rot, [*xy, TABLE_TOP_Z + 0.015 - lowest])


@dataclass
class _RightHandScript:
    """What the right hand does with the target, before the shared let-go and return to rest."""

    target: int  # index of the object the right hand moves
    reach: np.ndarray  # (T, 4, 4) from rest towards the first grasp pose
    grasp: np.ndarray  # (T, 4, 4) the hand while it grips the target
    hold_start: float  # normalised time the grip starts
    held: np.ndarray  # (T,) bool: the right hand grips the target
    release_end: float  # normalised time the fingers have let go
    curl: np.ndarray  # (T,) finger closure of the right hand
    text: str  # caption


def _closure(u: np.ndarray, close: tuple[float, float], open_: tuple[float, float]) -> np.ndarray:
    """Right-hand closure ``(T,)``: from rest to the grasp over ``close``, back over ``open_``."""
    return REST_CURL + (GRASP_CURL - REST_CURL) * (_phase(u, *close) - _phase(u, *open_))


def _grip_script(
    target: int,
    reach: np.ndarray,
    grasp: np.ndarray,
    u: np.ndarray,
    close: tuple[float, float],
    open_: tuple[float, float],
    text: str,
) -> _RightHandScript:
    """The script of a grip whose fingers close over ``close`` and open over ``open_`` (normalised
    times): the hand holds the target from the end of the closing to the start of the opening,
    and has let go at the end of the opening."""
    return _RightHandScript(
        target=target,
        reach=reach,
        grasp=grasp,
        hold_start=close[1],
        held=(u >= close[1]) & (u < open_[0]),
        release_end=open_[1],
        curl=_closure(u, close, open_),
        text=text,
    )


def _open_lid(
    scene: Scene,
    rng: np.random.Generator,
    u: np.ndarray,
    rest_r: np.ndarray,
    grip: np.ndarray,
    poses: np.ndarray,
) -> _RightHandScript:
    """Grip the lid's free edge and swing it open; writes the lid's poses into ``poses``."""
    t = len(poses)  # poses: (T, N, 4, 4)
    target = next(k for k, o in enumerate(scene.objects) if o.kind == "lid")
    base = scene.objects[target - 1]
    edge_local = np.array([base.size[0] + 0.006, 0.0, 0.006])  # lid's free edge, lid frame
    heading = np.arctan2(*(base.pose[:2, 3] - rest_r[:2, 3])[::-1])
    hand_rot0 = _rot_zy(heading, np.deg2rad(35.0))
    angle = np.deg2rad(rng.uniform(85.0, 105.0)) * _phase(u, 0.38, 0.72)  # (T,)
    grasp = np.zeros((t, 4, 4))
    for k in range(t):
        poses[k, target] = lid_pose(base.pose, base.size, angle[k])
        edge = poses[k, target, :3, :3] @ edge_local + poses[k, target, :3, 3]
        rot = axis_rotation(-poses[k, target, :3, 1], 0.4 * angle[k]) @ hand_rot0
        grasp[k] = make_se3(rot, edge - rot @ grip)
    return _grip_script(
        target,
        _blend(rest_r, grasp[0], _phase(u, 0.0, 0.28)),
        grasp,
        u,
        close=(0.24, 0.3),
        open_=(0.78, 0.84),
        text=f"the right hand opens the lid of the {base.colour} box",
    )


def _place_destination(
    scene: Scene, rng: np.random.Generator, target: int, p0: np.ndarray, radius: float
) -> np.ndarray:
    """A free spot ``(2,)`` in the placing area 10-22 cm from ``p0``, preferably to its left."""
    dest = p0[:2] + np.array([0.0, 0.15])  # fallback when no free spot is found
    for attempt in range(200):
        # Prefer the left (+y); widen to any direction after 50 tries.
        spread = np.pi / 4 if attempt < 50 else np.pi
        theta = np.pi / 2 + rng.uniform(-spread, spread)
        xy = p0[:2] + rng.uniform(0.1, 0.22) * np.array([np.cos(theta), np.sin(theta)])
        inside = np.all(xy >= PLACE_LO + radius) and np.all(xy <= PLACE_HI - radius)
        if inside and spot_is_free(scene, xy, radius, target):
            dest = xy
            break
    return dest


def _direction_words(shift: np.ndarray) -> str:
    """The caption's words for the move ``shift (2,)`` (+x away, +y left): its larger component."""
    if abs(shift[1]) >= abs(shift[0]):
        return "to the left" if shift[1] > 0 else "to the right"
    return "further away" if shift[0] > 0 else "closer"


def _pick_and_place(
    scene: Scene,
    rng: np.random.Generator,
    u: np.ndarray,
    rest_r: np.ndarray,
    grip: np.ndarray,
    poses: np.ndarray,
) -> _RightHandScript:
    """Pick the rightmost object up and place it nearby; writes its poses into ``poses``."""
    pickable = [k for k, o in enumerate(scene.objects) if o.kind in ("box", "cylinder")]
    target = min(pickable, key=lambda k: scene.objects[k].pose[1, 3])  # rightmost
    obj = scene.objects[target]
    p0 = obj.pose[:3, 3]
    radius = 0.5 * float(np.hypot(obj.size[0], obj.size[1]))
    dest = _place_destination(scene, rng, target, p0, radius)
    where = _direction_words(dest - p0[:2])
    heading = np.arctan2(*(p0[:2] - rest_r[:2, 3])[::-1])
    grasp_rot = _rot_zy(heading, np.deg2rad(40.0))
    grasp0 = make_se3(grasp_rot, p0 + np.array([0.0, 0.0, 0.6 * obj.size[2]]) - grasp_rot @ grip)
    hand_from_object = invert_se3(grasp0) @ obj.pose
    end_hand = make_se3(
        _rot_zy(heading + rng.uniform(-0.5, 0.5), np.deg2rad(40.0)),
        np.array([*dest, p0[2]]) + grasp0[:3, 3] - p0,
    )
    move = _phase(u, 0.45, 0.72)  # (T,)
    lift = _phase(u, 0.42, 0.58) - _phase(u, 0.62, 0.76)  # (T,) up, then down
    grasp = _blend(grasp0, end_hand, move)  # (T, 4, 4)
    grasp[:, 2, 3] += 0.1 * lift
    moved = u >= 0.42  # lift and move both start at 0.42 or later
    poses[moved, target] = grasp[moved] @ hand_from_object
    return _grip_script(
        target,
        _blend(rest_r, grasp0, _phase(u, 0.0, 0.32)),
        grasp,
        u,
        close=(0.3, 0.36),
        open_=(0.8, 0.86),
        text=f"the right hand picks up the {obj.name} and places it {where}",
    )


def _right_hand_path(script: _RightHandScript, rest_r: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Right wrist ``(T, 4, 4)``: reach, follow the grasp while holding, let go, back to rest."""
    grasp, release_end = script.grasp, script.release_end
    released = grasp[-1].copy()
    released[:3, 3] += [-0.05, 0.0, 0.06]
    let_go = _blend(grasp[-1], released, _phase(u, release_end - 0.06, release_end))
    back = _blend(released, rest_r, _phase(u, release_end, 1.0))
    return np.where(
        (u < script.hold_start)[:, None, None],
        script.reach,
        np.where(
            script.held[:, None, None],
            grasp,
            np.where((u < release_end)[:, None, None], let_go, back),
        ),
    )  # (T, 4, 4)


def _idle_left_hand(
    rest_l: np.ndarray, rng: np.random.Generator, u: np.ndarray, t: int
) -> tuple[np.ndarray, np.ndarray]:
    """The idle left hand over ``t`` frames: its wrist ``(T, 4, 4)`` and closure ``(T,)``.

    It rests, swaying by a centimetre or two.
    """
    sway = 0.012 * np.sin(2 * np.pi * (0.5 * u + rng.uniform(0, 1)))  # (T,)
    left = np.repeat(rest_l[None], t, axis=0)
    left[:, 0, 3] += sway
    left[:, 2, 3] += 0.3 * np.abs(sway)
    curl_l = 0.2 + 0.1 * np.sin(  # stays in [0.1, REST_CURL_MAX]
        2 * np.pi * (0.7 * u + rng.uniform(0, 1))
    )
    return left, curl_l


def script_interaction(scene: Scene, seed: int, num_frames: int, articulated: bool) -> Interaction:
    """The interaction of ``seed`` in ``scene`` over ``num_frames`` frames."""
    rng = np.random.default_rng([seed, 3])
    t = num_frames
    u = np.linspace(0.0, 1.0, t) if t > 1 else np.zeros(1)  # (T,) normalised time
    poses = np.repeat(scene.initial_object_poses[None], t, axis=0)  # (T, N, 4, 4)
    rest_r, rest_l = _rest_pose(RIGHT_SIDE, rng), _rest_pose(LEFT_SIDE, rng)
    grip = _grip_point(GRASP_CURL)  # (3,)
    act = _open_lid if articulated else _pick_and_place
    script = act(scene, rng, u, rest_r, grip, poses)
    right = _right_hand_path(script, rest_r, u)  # (T, 4, 4)
    left, curl_l = _idle_left_hand(rest_l, rng, u, t)
    return Interaction(
        world_from_hand=np.stack([left, right], axis=1),
        curl=np.stack([curl_l, script.curl], axis=1),
        object_poses=poses,
        target=script.target,
        held=script.held,
        text=script.text,
    )
