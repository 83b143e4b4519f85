"""Robot arm masks from a URDF and joint states, without a learned model.

When a robot log gives joint states, its URDF and the head camera's poses, the arm's silhouette
is known: pose every link by forward kinematics (yourdfpy reads the URDF and does the kinematics;
its trimesh scene holds the link geometry, primitives and mesh files alike), cast one ray per
pixel centre (integer + 0.5) through open3d's ``RaycastingScene``, and grow the hit pixels by
``dilate_px`` to cover calibration and timing slop. The result is the embodiment mask the scene
condition is cleaned with, the robot counterpart of ``hand_mask``.

The arm is placed in the world by ``world_from_base`` (the URDF root link's pose), constant or
per frame; camera poses are ``world_from_cam`` in OpenCV axes.
"""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from egosim.pipeline.geometry import transform_points, unproject_depth


class UrdfMaskError(ValueError):
    """A URDF cannot be read, or joint states do not fit it; the message says which."""


def load_urdf(urdf: str | Path):
    """The ``yourdfpy.URDF`` of a file path or a URDF document string (mesh files resolved
    relative to the file's folder)."""
    import yourdfpy  # imported here: only robot clips need it

    text = str(urdf)
    try:
        if text.lstrip().startswith("<"):
            return yourdfpy.URDF.load(io.StringIO(text), build_scene_graph=True, load_meshes=True)
        return yourdfpy.URDF.load(str(urdf), build_scene_graph=True, load_meshes=True)
    except Exception as exc:  # yourdfpy raises lxml, KeyError and ValueError alike
        raise UrdfMaskError(f"cannot read URDF {text[:80]!r}: {exc}") from exc


def arm_triangles(robot, joint_names: list[str], q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` in the root link's frame and faces ``(F, 3)`` of the posed arm."""
    values = dict(zip(joint_names, np.asarray(q, dtype=np.float64), strict=True))
    missing = [n for n in robot.actuated_joint_names if n not in values]
    if missing:
        raise UrdfMaskError(f"joint states lack the URDF's actuated joints {missing}")
    robot.update_cfg(np.array([values[n] for n in robot.actuated_joint_names]))
    mesh = robot.scene.to_geometry()  # every link's geometry in the root frame
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def arm_masks(
    urdf: str | Path,
    joint_names: list[str],
    joint_positions: np.ndarray,
    world_from_base: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    dilate_px: int = 2,
) -> np.ndarray:
    """Arm masks ``(T, H, W)`` uint8 (1 = arm) for joint states ``(T, J)`` named ``joint_names``.

    ``world_from_base`` is ``(4, 4)`` or ``(T, 4, 4)``; ``world_from_cam (T, 4, 4)``;
    ``intrinsics (4,)`` fx, fy, cx, cy. Pixels whose centre ray hits the arm, grown by a
    ``(2 * dilate_px + 1)`` square.
    """
    q = np.asarray(joint_positions, dtype=np.float64)
    cams = np.asarray(world_from_cam, dtype=np.float64)
    t = len(cams)
    if q.ndim != 2 or len(q) != t or q.shape[1] != len(joint_names):
        raise UrdfMaskError(f"joint_positions must be (T={t}, J={len(joint_names)}), got {q.shape}")
    bad = np.flatnonzero(~np.isfinite(q).all(axis=1))
    if len(bad):
        raise UrdfMaskError(f"joint_positions hold NaN or inf at frames {bad[:5].tolist()}")
    bases = np.broadcast_to(np.asarray(world_from_base, dtype=np.float64), (t, 4, 4))
    robot = load_urdf(urdf)
    # camera rays through the pixel centres, z = 1 (so t_hit is the z-depth)
    dirs = unproject_depth(np.ones((height, width)), intrinsics).reshape(-1, 3)  # (H*W, 3)
    kernel = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
    out = np.zeros((t, height, width), np.uint8)
    for k in range(t):
        verts, faces = arm_triangles(robot, joint_names, q[k])
        world = transform_points(bases[k], verts)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(world.astype(np.float32), faces.astype(np.uint32))
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = cams[k][:3, 3]
        rays[:, 3:] = dirs @ cams[k][:3, :3].T
        hit = np.isfinite(scene.cast_rays(rays)["t_hit"].numpy()).reshape(height, width)
        mask = hit.astype(np.uint8)
        out[k] = cv2.dilate(mask, kernel) if dilate_px > 0 else mask
    return out
