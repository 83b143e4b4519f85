"""A robot embodiment for the synthetic world: a 6-joint arm with a two-finger gripper.

The arm is defined once here (:data:`ARM`: joints, link shapes) and written out as a URDF
(:func:`arm_urdf`), so consumers that read robot logs (joint states + a URDF) are tested against
exact ground truth: the world renders the arm from its own forward kinematics
(:func:`link_poses`), and the frames, the arm mask and the joint states all come from the same
joint values.

Frames: every link frame follows the URDF rules (joint origin ``xyz`` + ``rpy`` in the parent link
frame, then the joint motion about/along ``axis``); link shapes are URDF boxes (centred on their
origin) and cylinders (centred, axis along local z). The base sits on the table's near edge, to
the right of the head camera (a humanoid's arm seen from its head camera, as in AgiBot World), and
the tool frame ``tool`` lies between the fingertips with z along the approach direction and the
fingers opening along its y axis.
"""

from __future__ import annotations

from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from egosim.pipeline.geometry import make_se3
from egosim.world import meshes
from egosim.world.config import WorldConfig
from egosim.world.meshes import Mesh


@dataclass(frozen=True)
class Shape:
    """The visual geometry of one link: a URDF box or cylinder at ``xyz`` in the link frame."""

    kind: str  # "box" (size = 3 edge lengths) or "cylinder" (size = radius, length)
    size: tuple[float, ...]  # box: (x, y, z) metres; cylinder: (radius, length) metres
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)  # shape centre in the link frame, metres


@dataclass(frozen=True)
class Joint:
    """One URDF joint: ``child`` = ``parent`` * origin(xyz, rpy) * motion(axis, q)."""

    name: str  # URDF joint name
    kind: str  # "revolute", "prismatic" or "fixed"
    parent: str  # parent link name
    child: str  # child link name
    xyz: tuple[float, float, float]  # origin translation in the parent frame, metres
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)  # origin roll, pitch, yaw, radians
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)  # motion axis in the child frame
    lower: float = -np.pi  # joint limit (radians or metres)
    upper: float = np.pi  # joint limit (radians or metres)


@dataclass(frozen=True)
class Arm:
    """A serial arm: links with shapes, joints in chain order (the fingers last)."""

    name: str  # robot name written into the URDF
    shapes: dict[str, tuple[Shape, ...]]  # link name -> its visual shapes
    joints: tuple[Joint, ...]  # every joint, parents before children

    @property
    def arm_joints(self) -> tuple[str, ...]:
        """Names of the joints :func:`solve_ik` moves (the revolute ones)."""
        return tuple(j.name for j in self.joints if j.kind == "revolute")

    @property
    def moving_joints(self) -> tuple[str, ...]:
        """Names of all non-fixed joints, in the order of a joint-state vector."""
        return tuple(j.name for j in self.joints if j.kind != "fixed")


FINGER_TRAVEL = 0.04  # each finger's prismatic travel (m): max opening 0.08 m
PALM_TO_TIP = 0.085  # palm base to fingertip centre along the approach axis (m)
FINGER_BASE = 0.03  # palm origin to the finger joints along the approach axis (m)
FINGER_LENGTH = 0.055  # finger length along the approach axis (m)

ARM = Arm(
    name="egosim_arm",
    shapes={
        "base_link": (Shape("cylinder", (0.055, 0.06), (0.0, 0.0, 0.03)),),
        "shoulder": (Shape("cylinder", (0.045, 0.09), (0.0, 0.0, 0.045)),),
        "upper_arm": (Shape("box", (0.055, 0.055, 0.30), (0.0, 0.0, 0.15)),),
        "forearm": (Shape("box", (0.045, 0.045, 0.26), (0.0, 0.0, 0.13)),),
        "wrist_1": (Shape("cylinder", (0.035, 0.05), (0.0, 0.0, 0.025)),),
        "wrist_2": (Shape("cylinder", (0.032, 0.04), (0.0, 0.0, 0.02)),),
        "palm": (Shape("box", (0.035, 0.11, 0.03), (0.0, 0.0, 0.015)),),
        "finger_left": (Shape("box", (0.018, 0.012, FINGER_LENGTH), (0, 0, FINGER_LENGTH / 2)),),
        "finger_right": (Shape("box", (0.018, 0.012, FINGER_LENGTH), (0, 0, FINGER_LENGTH / 2)),),
        "tool": (),
    },
    joints=(
        Joint("shoulder_pan", "revolute", "base_link", "shoulder", (0.0, 0.0, 0.06)),
        Joint("shoulder_lift", "revolute", "shoulder", "upper_arm", (0, 0, 0.09), axis=(0, 1, 0)),
        Joint("elbow", "revolute", "upper_arm", "forearm", (0.0, 0.0, 0.30), axis=(0, 1, 0)),
        Joint("wrist_pitch", "revolute", "forearm", "wrist_1", (0.0, 0.0, 0.26), axis=(0, 1, 0)),
        Joint("wrist_roll", "revolute", "wrist_1", "wrist_2", (0.0, 0.0, 0.05)),
        Joint("wrist_yaw", "revolute", "wrist_2", "palm", (0.0, 0.0, 0.04), axis=(1, 0, 0)),
        Joint(
            "finger_left_joint", "prismatic", "palm", "finger_left", (0.0, 0.006, FINGER_BASE),
            axis=(0, 1, 0), lower=0.0, upper=FINGER_TRAVEL,
        ),
        Joint(
            "finger_right_joint", "prismatic", "palm", "finger_right", (0.0, -0.006, FINGER_BASE),
            axis=(0, -1, 0), lower=0.0, upper=FINGER_TRAVEL,
        ),
        Joint("tool_joint", "fixed", "palm", "tool", (0.0, 0.0, PALM_TO_TIP)),
    ),
)  # fmt: skip


def _fmt(values: tuple[float, ...]) -> str:
    return " ".join(f"{float(v):.9g}" for v in values)


def arm_urdf(arm: Arm = ARM) -> str:
    """The URDF document of ``arm`` (primitive shapes only, no mesh files)."""
    lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(arm.name)}>"]
    for link, shapes in arm.shapes.items():
        lines.append(f"  <link name={quoteattr(link)}>")
        for shape in shapes:
            geom = (
                f'<box size="{_fmt(shape.size)}"/>'
                if shape.kind == "box"
                else f'<cylinder radius="{shape.size[0]:.9g}" length="{shape.size[1]:.9g}"/>'
            )
            lines += [
                "    <visual>",
                f'      <origin xyz="{_fmt(shape.xyz)}" rpy="0 0 0"/>',
                f"      <geometry>{geom}</geometry>",
                "    </visual>",
            ]
        lines.append("  </link>")
    for j in arm.joints:
        lines += [
            f"  <joint name={quoteattr(j.name)} type={quoteattr(j.kind)}>",
            f"    <parent link={quoteattr(j.parent)}/>",
            f"    <child link={quoteattr(j.child)}/>",
            f'    <origin xyz="{_fmt(j.xyz)}" rpy="{_fmt(j.rpy)}"/>',
        ]
        if j.kind != "fixed":
            lines += [
                f'    <axis xyz="{_fmt(j.axis)}"/>',
                f'    <limit lower="{j.lower:.9g}" upper="{j.upper:.9g}" effort="10" '
                'velocity="2"/>',
            ]
        lines.append("  </joint>")
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def _motion(joint: Joint, q: float) -> np.ndarray:
    axis = np.asarray(joint.axis, dtype=np.float64)
    if joint.kind == "revolute":
        return make_se3(Rotation.from_rotvec(axis * q).as_matrix(), np.zeros(3))
    if joint.kind == "prismatic":
        return make_se3(np.eye(3), axis * q)
    return np.eye(4)


def link_poses(q: np.ndarray, world_from_base: np.ndarray, arm: Arm = ARM) -> dict[str, np.ndarray]:
    """``world_from_link`` (4, 4) of every link for joint values ``q`` (``moving_joints`` order)."""
    values = dict(zip(arm.moving_joints, np.asarray(q, dtype=np.float64), strict=True))
    poses = {"base_link": np.asarray(world_from_base, dtype=np.float64)}
    for j in arm.joints:
        origin = make_se3(Rotation.from_euler("xyz", j.rpy).as_matrix(), np.asarray(j.xyz))
        poses[j.child] = poses[j.parent] @ origin @ _motion(j, values.get(j.name, 0.0))
    return poses


def arm_meshes(poses: dict[str, np.ndarray], arm: Arm = ARM) -> list[Mesh]:
    """One world-frame triangle mesh per link that has shapes, in ``arm.shapes`` order."""
    out = []
    for link, shapes in arm.shapes.items():
        parts = []
        for shape in shapes:
            if shape.kind == "box":
                half = np.asarray(shape.size) / 2.0
                verts, faces = meshes.box(-half, half)
            else:
                radius, length = shape.size
                verts, faces = meshes.cylinder(radius, length, segments=24)
                verts = verts - np.array([0.0, 0.0, length / 2.0], np.float32)  # centred
            verts = verts.astype(np.float64) + np.asarray(shape.xyz)
            world = verts @ poses[link][:3, :3].T + poses[link][:3, 3]
            parts.append((world.astype(np.float32), faces))
        if parts:
            out.append(meshes.merge(parts))
    return out


def solve_ik(
    targets: np.ndarray, world_from_base: np.ndarray, q0: np.ndarray, arm: Arm = ARM
) -> np.ndarray:
    """Arm joint values ``(T, n_arm)`` placing the tool frame at ``targets (T, 4, 4)``.

    Damped least squares per frame (scipy), warm-started from the previous frame's solution;
    position residuals in metres, orientation residuals as 0.1 m per radian. The fingers stay
    at 0. Joint limits are respected; an unreachable target gives the nearest reachable pose
    (the world renders whatever the joint values give, so ground truth stays exact).
    """
    n_arm = len(arm.arm_joints)
    n_all = len(arm.moving_joints)
    lo = np.array([j.lower for j in arm.joints if j.kind == "revolute"])
    hi = np.array([j.upper for j in arm.joints if j.kind == "revolute"])
    out = np.zeros((len(targets), n_arm))
    q = np.clip(np.asarray(q0, dtype=np.float64), lo + 1e-6, hi - 1e-6)
    for k, target in enumerate(targets):

        def residual(x: np.ndarray, target: np.ndarray = target) -> np.ndarray:
            full = np.concatenate([x, np.zeros(n_all - n_arm)])
            tool = link_poses(full, world_from_base, arm)["tool"]
            rot_err = Rotation.from_matrix(target[:3, :3].T @ tool[:3, :3]).as_rotvec()
            return np.concatenate([tool[:3, 3] - target[:3, 3], 0.1 * rot_err])

        q = least_squares(residual, q, bounds=(lo, hi), xtol=1e-12, ftol=1e-12).x
        out[k] = q
    return out


BASE_XY = (-0.30, -0.32)  # arm base on the table, right of the head camera (world x, y, m)
ARM_COLOURS = np.array([0.55, 0.57, 0.6], np.float32)  # grey links (shading varies per face)
_TOOL_DOWN = np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])  # z down, y = world y


@dataclass
class RobotClip:
    """A rendered robot episode with exact ground truth (world metres, OpenCV camera axes)."""

    frames: np.ndarray  # (T, H, W, 3) uint8 RGB: the scene with the arm
    depth: np.ndarray  # (T, H, W) float32 z-depth of the frames, metres (0 = nothing hit)
    static_frames: np.ndarray  # (T, H, W, 3) uint8: the same views without the arm
    static_depth: np.ndarray  # (T, H, W) float32 z-depth of the static views, metres
    arm_mask: np.ndarray  # (T, H, W) uint8, 1 = a pixel of the arm (any link) in front of the scene
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy in pixels
    world_from_cam: np.ndarray  # (T, 4, 4) head camera poses
    world_from_base: np.ndarray  # (4, 4) arm base pose
    joint_names: tuple[str, ...]  # names of the joint-state columns (ARM.moving_joints)
    joint_positions: np.ndarray  # (T, J) radians / metres in joint_names order
    world_from_tool: np.ndarray  # (T, 4, 4) tool frame (between the fingertips)
    world_from_ee: np.ndarray  # (T, 4, 4) end-effector (palm) frame: the gripper skeleton's wrist
    opening: np.ndarray  # (T,) distance between the fingers' inner faces, metres
    urdf: str  # the URDF document the arm was built from
    fps: float  # frames per second
    target: str  # name of the object the arm reaches for ("" when the scene has none)


def _tool_path(scene_objects: list, base: np.ndarray, t: int) -> np.ndarray:
    """``(T, 4, 4)`` tool poses: from a raised pose over to the first object, down, and up."""
    goal = scene_objects[0].pose[:3, 3] if scene_objects else np.array([0.05, -0.1, 0.74])
    height = float(scene_objects[0].size[2]) if scene_objects else 0.05
    start = base[:3, 3] + np.array([0.18, 0.0, 0.32])
    above = goal + np.array([0.0, 0.0, height + 0.16])
    grasp = goal + np.array([0.0, 0.0, max(height - 0.03, 0.02)])
    u = np.linspace(0.0, 1.0, t)
    w1 = np.clip(u / 0.45, 0, 1)[:, None]  # start -> above
    w2 = np.clip((u - 0.45) / 0.3, 0, 1)[:, None]  # above -> grasp
    w3 = np.clip((u - 0.8) / 0.2, 0, 1)[:, None]  # grasp -> lift halfway
    ease = lambda w: 0.5 - 0.5 * np.cos(np.pi * w)  # noqa: E731
    pos = start + ease(w1) * (above - start) + ease(w2) * (grasp - above)
    pos = pos + ease(w3) * 0.5 * (above - grasp)
    yaw = 0.4 * np.sin(np.pi * u)  # a turn of the wrist about the approach axis
    rot = Rotation.from_euler("z", yaw[:, None]).as_matrix() @ _TOOL_DOWN  # (T, 3, 3)
    return make_se3(rot, pos)


def render_robot_clip(config: WorldConfig) -> RobotClip:
    """Render the robot embodiment in the world of ``config`` (a :class:`WorldConfig`).

    The scene, camera path and intrinsics are the config's (default or alt variant); the arm
    replaces the hands: it reaches over the first object, closes its fingers and lifts. Objects do
    not move. The arm mask is where the arm's ray-cast depth is nearer than the scene's.
    """
    from egosim.world.clip import _setup  # the world's scene and camera set-up
    from egosim.world.render import WorldRenderer, to_uint8
    from egosim.world.scene import TABLE_TOP_Z

    t, h, w = config.num_frames, config.height, config.width
    scene, intrinsics, world_from_cam = _setup(config)
    base = make_se3(np.eye(3), np.array([*BASE_XY, TABLE_TOP_Z]))
    targets = _tool_path(scene.objects, base, t)
    q_arm = solve_ik(targets, base, np.array([0.0, 0.6, 1.2, 1.3, 0.0, 0.0]))
    u = np.linspace(0.0, 1.0, t)
    finger = FINGER_TRAVEL * np.where(u < 0.75, 0.9, 0.9 - 0.7 * np.clip((u - 0.75) / 0.1, 0, 1))
    q = np.concatenate([q_arm, finger[:, None], finger[:, None]], axis=1)  # (T, 8)
    renderer = WorldRenderer(scene, intrinsics, h, w)
    initial = scene.initial_object_poses
    frames = np.zeros((t, h, w, 3), np.uint8)
    static_frames = np.zeros((t, h, w, 3), np.uint8)
    depth = np.zeros((t, h, w), np.float32)
    static_depth = np.zeros((t, h, w), np.float32)
    arm_mask = np.zeros((t, h, w), np.uint8)
    tools, palms = np.zeros((t, 4, 4)), np.zeros((t, 4, 4))
    for k in range(t):
        cam = world_from_cam[k]
        static = renderer.render_static(cam, initial)
        poses = link_poses(q[k], base)
        parts = arm_meshes(poses)
        arm = renderer.render_meshes(cam, parts, np.tile(ARM_COLOURS, (len(parts), 1)))
        on_arm = arm.depth < static.depth
        frames[k] = to_uint8(np.where(on_arm[..., None], arm.rgb, static.rgb))
        static_frames[k] = to_uint8(static.rgb)
        scene_z = np.where(np.isfinite(static.depth), static.depth, 0.0)
        static_depth[k] = scene_z
        depth[k] = np.where(on_arm, arm.depth, scene_z)
        arm_mask[k] = on_arm
        tools[k], palms[k] = poses["tool"], poses["palm"]
    gap = 2 * finger  # inner faces: joint offset 0.006 + travel - half the 0.012 finger width
    return RobotClip(
        frames=frames,
        depth=depth,
        static_frames=static_frames,
        static_depth=static_depth,
        arm_mask=arm_mask,
        intrinsics=np.asarray(intrinsics, dtype=np.float64),
        world_from_cam=world_from_cam,
        world_from_base=base,
        joint_names=ARM.moving_joints,
        joint_positions=q,
        world_from_tool=tools,
        world_from_ee=palms,
        opening=gap,
        urdf=arm_urdf(),
        fps=float(config.fps),
        target=scene.objects[0].name if scene.objects else "",
    )
