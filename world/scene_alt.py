"""The "alt" variant's scene: another room, a round pedestal table, other objects and colours.

It keeps the default's contract (:mod:`egosim.world.scene`): world frame, table top at
``TABLE_TOP_Z``, objects in ``PLACE_LO..PLACE_HI`` with kinds ``box`` and ``cylinder`` to pick
(here a tapered carton and a bottle), a ``container`` followed by its ``lid`` when articulated
(the lid hinged as :func:`lid_pose` says), background bodies in world coordinates. Textures stay
high-frequency (feature matching must work) but come from other families: tiled floor, plaster
walls, a terrazzo, slate or checked-cloth table top.
"""

from __future__ import annotations

import numpy as np

from egosim.pipeline.geometry import transform_points
from egosim.world import meshes
from egosim.world.scene import (
    PICKABLE,
    PLACE_HI,
    PLACE_LO,
    TABLE_TOP_Z,
    Body,
    Scene,
    free_spot,
    lid_pose,
    yaw_pose,
)
from egosim.world.textures import Texture, make_texture

# Named colours (RGB 0..1) of the alt objects; none is a name of the default palette.
ALT_COLOURS: dict[str, tuple[float, float, float]] = {
    "white": (0.90, 0.90, 0.86),
    "black": (0.10, 0.10, 0.11),
    "brown": (0.45, 0.28, 0.15),
    "grey": (0.50, 0.50, 0.52),
    "teal": (0.05, 0.50, 0.48),
    "maroon": (0.50, 0.08, 0.15),
    "olive": (0.45, 0.48, 0.12),
    "navy": (0.10, 0.14, 0.42),
    "lime": (0.60, 0.85, 0.20),
    "magenta": (0.85, 0.10, 0.60),
}
NOUNS = {"box": "carton", "cylinder": "bottle", "cone": "cone", "ball": "ball", "cup": "cup"}
TABLE_CENTRE = np.array([0.30, 0.0])  # round table centre (x, y); the near edge is at x = -0.36
TABLE_RADIUS = 0.66


def _overlay(texture: Texture, mask: np.ndarray, colour: np.ndarray, alpha: float) -> Texture:
    """``texture`` with ``colour`` blended in by ``alpha`` where ``mask (S, S)`` is set."""
    img = texture.image.astype(np.float32)
    img[mask] = (1.0 - alpha) * img[mask] + alpha * 255.0 * colour
    return Texture(np.clip(img + 0.5, 0, 255).astype(np.uint8), texture.texel_size)


def _table_texture(rng: np.random.Generator) -> Texture:
    """Table-top albedo of one of three families: terrazzo, slate or a checked cloth."""
    family = int(rng.integers(0, 3))
    if family == 0:  # terrazzo: light stone full of chips
        base = np.array([0.82, 0.80, 0.76]) * rng.uniform(0.9, 1.05, 3)
        return make_texture(rng, tuple(base), 1024, 0.0015, contrast=0.35)
    if family == 1:  # slate: dark, strongly veined
        base = np.array([0.25, 0.27, 0.30]) * rng.uniform(0.85, 1.2, 3)
        return make_texture(rng, tuple(base), 1024, 0.002, contrast=0.9)
    tex = make_texture(rng, tuple(rng.uniform(0.6, 0.95, 3)), 1024, 0.0015, contrast=0.3)
    i, j = np.mgrid[0:1024, 0:1024]
    period = int(rng.integers(12, 28))  # texels: 2-4 cm checks
    colour = rng.uniform(0.05, 0.7, 3)
    tex = _overlay(tex, (i // period) % 2 == 0, colour, 0.45)
    return _overlay(tex, (j // period) % 2 == 0, colour, 0.45)


def _world(mesh: meshes.Mesh, x: float, y: float, z: float) -> meshes.Mesh:
    """``mesh`` moved by ``(x, y, z)`` (background bodies are modelled in world coordinates)."""
    pose = yaw_pose(x, y, z, 0.0)
    return transform_points(pose, mesh[0]).astype(np.float32), mesh[1]


def _background(rng: np.random.Generator) -> list[Body]:
    """Room (tiled floor, plaster walls, ceiling) and a round table on a pedestal."""
    eye = np.eye(4)
    floor_tex = make_texture(rng, tuple(rng.uniform(0.35, 0.7, 3)), 1024, 0.004)
    i, j = np.mgrid[0:1024, 0:1024]
    grout = (i % 75 < 3) | (j % 75 < 3)  # 30 cm tiles
    bodies = [
        Body("floor", "floor", *meshes.box([-1.8, -2.2, -0.05], [3.0, 2.2, 0.0]),
             _overlay(floor_tex, grout, np.array([0.9, 0.9, 0.88]), 0.8), eye),
        Body("ceiling", "ceiling", *meshes.box([-1.8, -2.2, 2.45], [3.0, 2.2, 2.5]),
             make_texture(rng, (0.92, 0.9, 0.86), 512, 0.008, contrast=0.25), eye),
    ]  # fmt: skip
    walls = [
        ([3.0, -2.2, 0.0], [3.05, 2.2, 2.45]),
        ([-1.85, -2.2, 0.0], [-1.8, 2.2, 2.45]),
        ([-1.8, 2.2, 0.0], [3.0, 2.25, 2.45]),
        ([-1.8, -2.25, 0.0], [3.0, -2.2, 2.45]),
    ]
    paint = rng.uniform(0.25, 0.85, 3) * np.array([0.8, 0.95, 1.1])  # cool paint family
    for k, (lo, hi) in enumerate(walls):
        base = tuple(np.clip(paint * rng.uniform(0.85, 1.1, 3), 0, 1))
        tex = make_texture(rng, base, 1024, 0.006, contrast=0.45)
        bodies.append(Body(f"wall {k}", "wall", *meshes.box(lo, hi), tex, eye))
    cx, cy = TABLE_CENTRE
    top = _world(meshes.cylinder(TABLE_RADIUS, 0.035, 64), cx, cy, TABLE_TOP_Z - 0.035)
    column = _world(meshes.cylinder(0.05, TABLE_TOP_Z - 0.035, 24), cx, cy, 0.0)
    foot = _world(meshes.cylinder(0.3, 0.03, 32), cx, cy, 0.0)
    table = meshes.merge([top, column, foot])
    bodies.append(Body("table", "table", *table, _table_texture(rng), eye))
    return bodies


def _object_mesh(rng: np.random.Generator, kind: str) -> tuple[meshes.Mesh, np.ndarray]:
    """Mesh of one alt object of ``kind`` standing on local z = 0, and its size (x, y, height)."""
    if kind == "box":  # carton: a square frustum, narrower at the top
        r, h = rng.uniform(0.035, 0.055), rng.uniform(0.06, 0.11)
        profile = np.array([[0.0, 0.0], [r, 0.0], [0.75 * r, h], [0.0, h]])
        verts, faces = meshes.lathe(profile, 4)
        return (verts, faces), np.array([2 * r, 2 * r, h])
    if kind == "cylinder":  # bottle: body, shoulder, neck
        r, h = rng.uniform(0.025, 0.035), rng.uniform(0.12, 0.17)
        profile = np.array(
            [[0.0, 0.0], [r, 0.0], [r, 0.6 * h], [0.4 * r, 0.8 * h], [0.4 * r, h], [0.0, h]]
        )
        return meshes.lathe(profile, 20), np.array([2 * r, 2 * r, h])
    if kind == "cone":
        r, h = rng.uniform(0.03, 0.05), rng.uniform(0.06, 0.1)
        return meshes.lathe(np.array([[0.0, 0.0], [r, 0.0], [0.0, h]]), 24), np.array(
            [2 * r, 2 * r, h]
        )
    if kind == "ball":
        r = rng.uniform(0.03, 0.045)
        lat = np.linspace(-np.pi / 2, np.pi / 2, 9)
        profile = np.stack([r * np.cos(lat), r + r * np.sin(lat)], 1)
        profile[0, 0] = profile[-1, 0] = 0.0
        return meshes.lathe(profile, 20), np.array([2 * r, 2 * r, 2 * r])
    r, h, w = rng.uniform(0.035, 0.045), rng.uniform(0.08, 0.1), 0.005  # cup: straight thin wall
    profile = np.array([[0.0, 0.0], [r, 0.0], [r, h], [r - w, h], [r - w, w], [0.0, w]])
    return meshes.lathe(profile, 24), np.array([2 * r, 2 * r, h])


def _container(rng: np.random.Generator) -> tuple[meshes.Mesh, meshes.Mesh, np.ndarray]:
    """Open-top crate with a rim and its flat lid (hinged on the crate's +x edge, see lid_pose)."""
    sx, sy, sz = rng.uniform(0.13, 0.17), rng.uniform(0.12, 0.16), rng.uniform(0.07, 0.09)
    w = 0.005
    rim = 0.012
    base = meshes.merge(
        [
            meshes.box([-sx / 2, -sy / 2, 0.0], [sx / 2, sy / 2, w]),
            meshes.box([-sx / 2, -sy / 2, 0.0], [-sx / 2 + w, sy / 2, sz]),
            meshes.box([sx / 2 - w, -sy / 2, 0.0], [sx / 2, sy / 2, sz]),
            meshes.box([-sx / 2, -sy / 2, 0.0], [sx / 2, -sy / 2 + w, sz]),
            meshes.box([-sx / 2, sy / 2 - w, 0.0], [sx / 2, sy / 2, sz]),
            meshes.box([-sx / 2 - 0.004, -sy / 2 - 0.004, sz - rim], [-sx / 2, sy / 2 + 0.004, sz]),
        ]
    )
    lid = meshes.box([0.0, -sy / 2 - 0.003, 0.0], [sx + 0.006, sy / 2 + 0.003, 0.009])
    return base, lid, np.array([sx, sy, sz])


def build_scene_alt(seed: int, articulated: bool) -> Scene:
    """The alt scene of ``seed``: background plus 3-6 non-overlapping objects on the table."""
    rng = np.random.default_rng([seed, 11])
    background = _background(rng)
    colour_names = list(rng.permutation(list(ALT_COLOURS)))
    objects: list[Body] = []
    placed: list[tuple[np.ndarray, float]] = []  # (centre (2,), footprint radius)

    def texture(colour: str) -> Texture:
        return make_texture(rng, ALT_COLOURS[colour], 256, 0.0012, contrast=0.5)

    if articulated:
        base, lid, size = _container(rng)
        radius = 0.5 * float(np.hypot(size[0], size[1]))
        lo, hi = PLACE_LO + np.array([0.05, -0.05]), PLACE_HI - np.array([0.0, 0.15])
        xy = free_spot(rng, placed, radius, lo, hi)
        xy = 0.5 * (lo + hi) if xy is None else xy
        pose = yaw_pose(xy[0], xy[1], TABLE_TOP_Z, rng.uniform(-0.3, 0.3))
        colour = colour_names.pop()
        objects.append(
            Body(f"{colour} crate", "container", *base, texture(colour), pose, colour, size)
        )
        objects.append(
            Body(
                f"{colour} lid",
                "lid",
                *lid,
                texture(colour),
                lid_pose(pose, size, 0.0),
                colour,
                size,
            )
        )
        placed.append((xy, radius))
    others = ["cone", "ball", "cup"]
    num = int(rng.integers(3, 6 if not articulated else 5))
    for k in range(num):
        kind = PICKABLE[(k + 1) % 2] if k < 2 else others[int(rng.integers(0, 3))]
        (verts, faces), size = _object_mesh(rng, kind)
        radius = 0.5 * float(np.hypot(size[0], size[1]))
        xy = free_spot(rng, placed, radius, PLACE_LO, PLACE_HI)
        if xy is None:
            continue
        placed.append((xy, radius))
        colour = colour_names.pop()
        pose = yaw_pose(xy[0], xy[1], TABLE_TOP_Z, rng.uniform(-np.pi, np.pi))
        name = f"{colour} {NOUNS[kind]}"
        objects.append(Body(name, kind, verts, faces, texture(colour), pose, colour, size))
    return Scene(background, objects)
