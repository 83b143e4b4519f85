"""Deterministic procedural scene: a textured room, a table and 3-6 objects on it.

World frame: metres, z up, floor at z = 0. The person stands on the -x side of the table and looks
towards +x, so their right is -y. Every body is a mesh in its own local frame plus a pose
``world_from_object``. Background bodies are modelled in world coordinates (identity pose);
objects (the movable bodies) have their local origin at the centre of their footprint on the
table, except a lid, whose origin is on its hinge line.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from egosim.pipeline.geometry import make_se3
from egosim.world import meshes
from egosim.world.textures import COLOURS, Texture, make_texture

TABLE_TOP_Z = 0.74  # height of the table top above the floor
TABLE_LO = np.array([-0.45, -0.75])  # table top corner (x, y) nearest the person, on their right
TABLE_HI = np.array([0.60, 0.75])  # opposite corner
PLACE_LO = np.array([-0.06, -0.30])  # region (x, y) where objects are placed and moved
PLACE_HI = np.array([0.24, 0.30])
PICKABLE = ("box", "cylinder")  # object kinds a hand can pick up


@dataclass
class Body:
    """One rigid textured mesh of the scene."""

    name: str  # e.g. "floor", "red box"
    kind: str  # "floor", "wall", "ceiling", "table", "box", "cylinder", "bowl", "container", "lid"
    vertices: np.ndarray  # (V, 3) float32 in the body's local frame
    triangles: np.ndarray  # (F, 3) int32
    texture: Texture  # albedo, sampled by local surface coordinates
    pose: np.ndarray  # (4, 4) float64 world_from_object at the start of the clip
    colour: str = ""  # colour name used in captions ("" for background)
    size: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) footprint x, y, height


@dataclass
class Scene:
    """Background bodies (never move) and objects (instance ids 1..N in list order)."""

    background: list[Body]
    objects: list[Body]

    @property
    def initial_object_poses(self) -> np.ndarray:
        """``(N, 4, 4)`` world_from_object of every object at the start."""
        return np.stack([o.pose for o in self.objects]) if self.objects else np.zeros((0, 4, 4))


def yaw_pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    """``(4, 4)`` pose at ``(x, y, z)`` turned by ``yaw`` radians about world z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return make_se3(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [x, y, z])


def _background(rng: np.random.Generator) -> list[Body]:
    """Room (floor, four walls, ceiling) and table with legs, each with its own texture."""
    eye = np.eye(4)
    grey = rng.uniform(0.45, 0.75, 3)
    bodies = [
        Body("floor", "floor", *meshes.box([-2.0, -2.5, -0.05], [2.5, 2.5, 0.0]),
             make_texture(rng, tuple(grey * [0.9, 0.8, 0.7]), 1024, 0.004), eye),
        Body("ceiling", "ceiling", *meshes.box([-2.0, -2.5, 2.6], [2.5, 2.5, 2.65]),
             make_texture(rng, (0.85, 0.85, 0.82), 512, 0.008, contrast=0.3), eye),
    ]  # fmt: skip
    walls = [
        ([2.5, -2.5, 0.0], [2.55, 2.5, 2.6]),
        ([-2.05, -2.5, 0.0], [-2.0, 2.5, 2.6]),
        ([-2.0, 2.5, 0.0], [2.5, 2.55, 2.6]),
        ([-2.0, -2.55, 0.0], [2.5, -2.5, 2.6]),
    ]
    for k, (lo, hi) in enumerate(walls):
        base = tuple(rng.uniform(0.35, 0.9, 3))
        bodies.append(
            Body(
                f"wall {k}", "wall", *meshes.box(lo, hi), make_texture(rng, base, 1024, 0.005), eye
            )
        )
    wood = tuple(np.array([0.55, 0.38, 0.22]) * rng.uniform(0.7, 1.3, 3))
    top = meshes.box([*TABLE_LO, TABLE_TOP_Z - 0.03], [*TABLE_HI, TABLE_TOP_Z])
    legs = [
        meshes.box([x - 0.025, y - 0.025, 0.0], [x + 0.025, y + 0.025, TABLE_TOP_Z - 0.03])
        for x in (TABLE_LO[0] + 0.05, TABLE_HI[0] - 0.05)
        for y in (TABLE_LO[1] + 0.05, TABLE_HI[1] - 0.05)
    ]
    table_tex = make_texture(rng, wood, 1024, 0.002)
    bodies.append(Body("table", "table", *meshes.merge([top, *legs]), table_tex, eye))
    return bodies


def _object_mesh(rng: np.random.Generator, kind: str) -> tuple[meshes.Mesh, np.ndarray]:
    """Mesh of one object of ``kind`` standing on local z = 0, and its size (x, y, height)."""
    if kind == "box":
        sx, sy, sz = rng.uniform(0.05, 0.085), rng.uniform(0.05, 0.085), rng.uniform(0.05, 0.11)
        return meshes.box([-sx / 2, -sy / 2, 0.0], [sx / 2, sy / 2, sz]), np.array([sx, sy, sz])
    if kind == "cylinder":
        r, h = rng.uniform(0.025, 0.038), rng.uniform(0.07, 0.13)
        return meshes.cylinder(r, h), np.array([2 * r, 2 * r, h])
    r, h = rng.uniform(0.055, 0.075), rng.uniform(0.04, 0.06)
    return meshes.bowl(r, h), np.array([2 * r, 2 * r, h])


def _container(rng: np.random.Generator) -> tuple[meshes.Mesh, meshes.Mesh, np.ndarray]:
    """Open-top box (5 slabs) and its lid; the lid's local origin is on the hinge line.

    The base's local frame has its origin at the footprint centre; the lid's frame has x pointing
    from the hinge (the base's +x edge) across the lid, z up, so a rotation about the lid's -y
    lifts its free edge.
    """
    sx, sy, sz = rng.uniform(0.12, 0.16), rng.uniform(0.13, 0.18), rng.uniform(0.06, 0.08)
    w = 0.007
    base = meshes.merge(
        [
            meshes.box([-sx / 2, -sy / 2, 0.0], [sx / 2, sy / 2, w]),
            meshes.box([-sx / 2, -sy / 2, 0.0], [-sx / 2 + w, sy / 2, sz]),
            meshes.box([sx / 2 - w, -sy / 2, 0.0], [sx / 2, sy / 2, sz]),
            meshes.box([-sx / 2, -sy / 2, 0.0], [sx / 2, -sy / 2 + w, sz]),
            meshes.box([-sx / 2, sy / 2 - w, 0.0], [sx / 2, sy / 2, sz]),
        ]
    )
    lid = meshes.box([0.0, -sy / 2 - 0.003, 0.0], [sx + 0.006, sy / 2 + 0.003, 0.012])
    return base, lid, np.array([sx, sy, sz])


def lid_pose(base_pose: np.ndarray, size: np.ndarray, angle: float) -> np.ndarray:
    """World pose of a container's lid opened by ``angle`` radians (0 = closed)."""
    hinge = make_se3(np.diag([-1.0, -1.0, 1.0]), [size[0] / 2 + 0.003, 0.0, size[2]])
    c, s = np.cos(angle), np.sin(angle)
    opening = make_se3(np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]), np.zeros(3))
    return base_pose @ hinge @ opening


def free_spot(
    rng: np.random.Generator,
    placed: list[tuple[np.ndarray, float]],
    radius: float,
    lo: np.ndarray,
    hi: np.ndarray,
) -> np.ndarray | None:
    """A random table spot ``(2,)`` in ``lo..hi`` whose footprint of ``radius`` keeps 3 cm from
    every ``placed`` (centre, radius); None after 200 tries."""
    for _ in range(200):
        xy = rng.uniform(lo + radius, hi - radius)
        if all(np.linalg.norm(xy - c) > radius + r + 0.03 for c, r in placed):
            return xy
    return None


def build_scene(seed: int, articulated: bool) -> Scene:
    """The scene of ``seed``: background plus 3-6 non-overlapping objects on the table.

    With ``articulated`` the first two objects are a container and its hinged lid.
    """
    rng = np.random.default_rng([seed, 1])
    background = _background(rng)
    colour_names = list(rng.permutation(list(COLOURS)))
    objects: list[Body] = []
    placed: list[tuple[np.ndarray, float]] = []  # (centre (2,), footprint radius)

    if articulated:
        base, lid, size = _container(rng)
        radius = 0.5 * float(np.hypot(size[0], size[1]))
        lo, hi = PLACE_LO + np.array([0.05, -0.05]), PLACE_HI - np.array([0.0, 0.15])
        xy = free_spot(rng, placed, radius, lo, hi)
        xy = 0.5 * (lo + hi) if xy is None else xy  # the region is empty: always fits
        pose = yaw_pose(xy[0], xy[1], TABLE_TOP_Z, rng.uniform(-0.3, 0.3))
        colour = colour_names.pop()
        tex = make_texture(rng, COLOURS[colour], 256, 0.0015)
        objects.append(Body(f"{colour} box", "container", *base, tex, pose, colour, size))
        lid_tex = make_texture(rng, COLOURS[colour], 256, 0.0015)
        objects.append(
            Body(f"{colour} lid", "lid", *lid, lid_tex, lid_pose(pose, size, 0.0), colour, size)
        )
        placed.append((xy, radius))
    kinds = ["box", "cylinder", "bowl"]
    num = int(rng.integers(3, 6 if not articulated else 5))
    for k in range(num):
        kind = PICKABLE[k % 2] if k < 2 else kinds[int(rng.integers(0, 3))]
        (verts, faces), size = _object_mesh(rng, kind)
        radius = 0.5 * float(np.hypot(size[0], size[1]))
        xy = free_spot(rng, placed, radius, PLACE_LO, PLACE_HI)
        if xy is None:
            continue
        placed.append((xy, radius))
        colour = colour_names.pop()
        pose = yaw_pose(xy[0], xy[1], TABLE_TOP_Z, rng.uniform(-np.pi, np.pi))
        tex = make_texture(rng, COLOURS[colour], 256, 0.0015)
        objects.append(Body(f"{colour} {kind}", kind, verts, faces, tex, pose, colour, size))
    return Scene(background, objects)


def spot_is_free(scene: Scene, xy: np.ndarray, radius: float, skip: int) -> bool:
    """Whether a footprint of ``radius`` at ``xy`` clears every object except index ``skip``."""
    for k, obj in enumerate(scene.objects):
        if k == skip or obj.kind == "lid":
            continue
        r = 0.5 * float(np.hypot(obj.size[0], obj.size[1]))
        if np.linalg.norm(xy - obj.pose[:2, 3]) <= radius + r + 0.02:
            return False
    return True
