"""Triangle meshes of the world's primitives, as ``(V, 3) float32`` vertices and ``(F, 3)`` faces.

Every mesh is built in its own local frame; faces wind counter-clockwise seen from outside, but the
renderer does not rely on it (it flips normals towards the viewer).
"""

from __future__ import annotations

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]  # (vertices (V, 3) float32, triangles (F, 3) int32)

_BOX_FACES = np.array(
    [
        [0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
        [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
    ],
    dtype=np.int32,
)  # fmt: skip


def box(lo: np.ndarray, hi: np.ndarray) -> Mesh:
    """Axis-aligned box between corners ``lo (3,)`` and ``hi (3,)``: 8 vertices, 12 triangles."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    verts = np.array(
        [
            [x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
            [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1],
        ],
        dtype=np.float32,
    )  # fmt: skip
    return verts, _BOX_FACES.copy()


def merge(meshes: list[Mesh]) -> Mesh:
    """Concatenate meshes into one (faces re-indexed)."""
    verts, faces, offset = [], [], 0
    for v, f in meshes:
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(verts).astype(np.float32), np.concatenate(faces).astype(np.int32)


def lathe(profile: np.ndarray, segments: int = 32) -> Mesh:
    """Surface of revolution about local z of a polyline ``profile (P, 2)`` of ``(radius, z)``.

    A closed profile (first point == last point) gives a closed solid; radius 0 points are poles.
    """
    profile = np.asarray(profile, dtype=np.float64)
    angles = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)  # (S,)
    ring_x = profile[:, :1] * np.cos(angles)[None]  # (P, S)
    ring_y = profile[:, :1] * np.sin(angles)[None]  # (P, S)
    ring_z = np.broadcast_to(profile[:, 1:2], ring_x.shape)  # (P, S)
    verts = np.stack([ring_x, ring_y, ring_z], axis=-1).reshape(-1, 3)  # (P * S, 3)
    p = np.arange(len(profile) - 1)[:, None]  # (P-1, 1)
    s = np.arange(segments)[None]  # (1, S)
    a = p * segments + s
    b = p * segments + (s + 1) % segments
    c, d = a + segments, b + segments
    faces = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    )  # (2 * (P-1) * S, 3)
    return verts.astype(np.float32), faces.astype(np.int32)


def cylinder(radius: float, height: float, segments: int = 32) -> Mesh:
    """Closed cylinder standing on local z = 0, axis along local z."""
    return lathe(np.array([[0.0, 0.0], [radius, 0.0], [radius, height], [0.0, height]]), segments)


def bowl(radius: float, height: float, wall: float = 0.006, segments: int = 32) -> Mesh:
    """Open bowl (spherical-ish wall with thickness ``wall``) standing on local z = 0."""
    k = np.linspace(0.0, 1.0, 7)
    outer = np.stack([0.45 * radius + 0.55 * radius * np.sin(k * np.pi / 2), height * k**1.6], 1)
    inner = outer[::-1] * [1.0, 1.0] - [wall, 0.0]
    inner[:, 1] = np.maximum(inner[:, 1], wall)
    profile = np.concatenate([[[0.0, 0.0]], outer, inner, [[0.0, wall]]])  # (P, 2)
    return lathe(profile, segments)


class CapsuleTemplate:
    """Unit capsule rings, turned into many tapered capsules at once by :meth:`build`."""

    def __init__(self, segments: int = 10, rings: int = 3) -> None:
        lat = np.linspace(-np.pi / 2, 0.0, rings + 1)  # bottom hemisphere, pole to equator
        lats = np.concatenate([lat, -lat[::-1]])  # (2R+2,) equator twice
        top = np.concatenate([np.zeros(rings + 1), np.ones(rings + 1)])  # (2R+2,) 1 = top half
        profile = np.stack([np.cos(lats), np.sin(lats)], 1)  # (2R+2, 2) unit radius, z
        profile[0, 0] = profile[-1, 0] = 0.0
        verts, self.faces = lathe(profile, segments)
        self.unit = verts.astype(np.float64)  # (V, 3)
        self.top = np.repeat(top, segments)  # (V,)

    def build(self, start: np.ndarray, end: np.ndarray, r0: np.ndarray, r1: np.ndarray) -> Mesh:
        """Capsules from ``start (C, 3)`` (radius ``r0 (C,)``) to ``end (C, 3)`` (``r1 (C,)``)."""
        axis = end - start  # (C, 3)
        length = np.linalg.norm(axis, axis=1)  # (C,)
        z = axis / np.maximum(length, 1e-9)[:, None]  # (C, 3)
        helper = np.where(np.abs(z[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        y = np.cross(z, x)
        radius = np.where(self.top[None] > 0, r1[:, None], r0[:, None])  # (C, V)
        local = self.unit[None] * radius[..., None]  # (C, V, 3)
        local[..., 2] += self.top[None] * length[:, None]
        rot = np.stack([x, y, z], axis=-1)  # (C, 3, 3) columns are capsule axes
        verts = np.einsum("cij,cvj->cvi", rot, local) + start[:, None]  # (C, V, 3)
        n_v = self.unit.shape[0]
        faces = self.faces[None] + (np.arange(len(start)) * n_v)[:, None, None]  # (C, F, 3)
        return verts.reshape(-1, 3).astype(np.float32), faces.reshape(-1, 3).astype(np.int32)
