"""CPU ray-cast renderer of the world (open3d ``RaycastingScene``).

Rays leave the camera centre through pixel centres ``(j + 0.5, i + 0.5)`` with camera-frame
direction ``((u - cx) / fx, (v - cy) / fy, 1)``: with that unnormalised direction the hit distance
that open3d returns is exactly the z-depth. Shading is Lambertian (one directional light plus
ambient), without shadows, so a hand changes only the pixels that it covers. Texture colours are
looked up from the hit point in the body's local frame (tri-planar by the dominant local normal
axis), so textures stick to moving objects.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from egosim.pipeline.geometry import invert_se3, pixel_grid, project_points, transform_points
from egosim.world.meshes import Mesh
from egosim.world.scene import Body, Scene

LIGHT_DIR = np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82])  # towards light
AMBIENT, DIFFUSE = 0.42, 0.58
_OTHER_AXES = np.array([[1, 2], [0, 2], [0, 1]])  # surface coordinates for each dominant axis


@dataclass
class Layer:
    """One ray-cast layer of an image: colour, depth and which body each pixel shows."""

    rgb: np.ndarray  # (H, W, 3) float32 shaded colour in [0, 1]
    depth: np.ndarray  # (H, W) float32 z-depth, inf where nothing was hit
    ids: np.ndarray  # (H, W) int16 body index (layer-specific meaning), -1 where nothing was hit


def _shade(normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Lambertian factor ``(n,)`` float32, with normals turned to face the viewer."""
    n_dot_l = normals @ LIGHT_DIR.astype(np.float32)  # (n,)
    towards_viewer = np.einsum("ij,ij->i", normals, dirs) < 0  # (n,)
    lit = np.where(towards_viewer, n_dot_l, -n_dot_l)
    return AMBIENT + DIFFUSE * np.clip(lit, 0.0, 1.0)


class WorldRenderer:
    """Renders a :class:`Scene` (and optionally hand meshes) for one camera model."""

    def __init__(
        self, scene: Scene, intrinsics: np.ndarray, height: int, width: int, nthreads: int = 0
    ) -> None:
        """Prepare rays for ``(height, width)`` pixels; ``nthreads`` 0 lets open3d choose."""
        self.nthreads = nthreads
        fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
        uv = pixel_grid(height, width).reshape(-1, 2)  # (H*W, 2)
        self.dirs_cam = np.stack(
            [(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(len(uv))], axis=1
        ).astype(np.float32)  # (H*W, 3)
        self._dirs_cam_t = np.ascontiguousarray(self.dirs_cam.T)  # (3, H*W) for fast rotation
        self._dirs_norm = np.linalg.norm(self.dirs_cam, axis=1)  # (H*W,) rotation-invariant
        self.intrinsics = np.asarray(intrinsics, dtype=np.float64)
        self.height, self.width = height, width
        self.scene = scene
        self.bodies: list[Body] = scene.background + scene.objects
        self._background_world = [
            transform_points(b.pose, b.vertices).astype(np.float32) for b in scene.background
        ]
        self.num_background = len(scene.background)
        if any(not np.array_equal(b.pose, np.eye(4)) for b in scene.background):
            raise ValueError("background bodies must be modelled in world coordinates")
        self._fx = float(self.intrinsics[0])
        self._pyramids = [_mip_pyramid(b.texture.image) for b in self.bodies]
        self._tex_centre = np.array([b.texture.image.shape[0] // 2 for b in self.bodies] + [0])
        self._tex_scale = np.array(
            [1.0 / b.texture.texel_size for b in self.bodies] + [1.0], dtype=np.float32
        )
        # Ray-casting scenes by object poses: the most recent two (initial and current poses).
        self._scenes: dict[bytes, o3d.t.geometry.RaycastingScene] = {}

    def _sample(
        self, body: np.ndarray, u: np.ndarray, v: np.ndarray, lod: np.ndarray
    ) -> np.ndarray:
        """Filtered texture colour ``(n, 3)`` float32 in [0, 255] at level-0 texel ``(u, v)``.

        Bilinear (``cv2.remap``, wrapping) within the nearest mip level of ``lod`` (log2 of the
        pixel footprint in texels); the sentinel body ``len(self.bodies)`` samples black.
        """
        out = np.zeros((len(body), 3), np.float32)
        level = np.rint(lod).astype(np.int64)  # (n,)
        for b, pyramid in enumerate(self._pyramids):
            idx = np.flatnonzero(body == b)
            if not len(idx):
                continue
            lev = np.clip(level[idx], 0, len(pyramid) - 1)  # (m,)
            for k in np.flatnonzero(np.bincount(lev)):  # the levels present
                sel = idx[lev == k] if len(pyramid) > 1 else idx
                inv = np.float32(2.0**-k)
                # cv2.remap wants maps under 32767 rows: lay the m samples out in rows of 1024.
                m = len(sel)
                rows = -(-m // 1024)
                map_x = np.zeros(rows * 1024, np.float32)
                map_y = np.zeros(rows * 1024, np.float32)
                map_x[:m] = u[sel] * inv - 0.5  # texel centres sit at integers for cv2
                map_y[:m] = v[sel] * inv - 0.5
                sampled = cv2.remap(
                    pyramid[k],
                    map_x.reshape(rows, 1024),
                    map_y.reshape(rows, 1024),
                    cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_WRAP,
                )  # (rows, 1024, 3)
                out[sel] = sampled.reshape(-1, 3)[:m]
        return out

    def _static_scene(self, object_poses: np.ndarray) -> o3d.t.geometry.RaycastingScene:
        """Ray-casting scene of background plus objects at ``object_poses (N, 4, 4)``."""
        key = np.ascontiguousarray(object_poses).tobytes()
        if key not in self._scenes:
            rc = o3d.t.geometry.RaycastingScene()
            for verts, body in zip(self._background_world, self.scene.background, strict=True):
                rc.add_triangles(verts, body.triangles.astype(np.uint32))
            for pose, body in zip(object_poses, self.scene.objects, strict=True):
                verts = transform_points(pose, body.vertices).astype(np.float32)
                rc.add_triangles(verts, body.triangles.astype(np.uint32))
            if len(self._scenes) >= 2:
                del self._scenes[next(iter(self._scenes))]
            self._scenes[key] = rc
        return self._scenes[key]

    def rays(self, world_from_cam: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
        """World rays ``(n, 6)`` float32 for all pixels or the flat pixel ``index``."""
        dirs_t = self._dirs_cam_t if index is None else self._dirs_cam_t[:, index]  # (3, n)
        rays = np.empty((dirs_t.shape[1], 6), np.float32)
        rays[:, :3] = world_from_cam[:3, 3]
        rays[:, 3:] = (world_from_cam[:3, :3].astype(np.float32) @ dirs_t).T  # (n, 3)
        return rays

    def render_static(
        self, world_from_cam: np.ndarray, object_poses: np.ndarray, rays: np.ndarray | None = None
    ) -> Layer:
        """Background and objects seen from ``world_from_cam``; ids index ``self.bodies``.

        ``rays`` (from :meth:`rays` for the same camera, all pixels) may be passed to avoid
        recomputing them.
        """
        rays = self.rays(world_from_cam) if rays is None else rays  # (H*W, 6)
        hit = self._static_scene(object_poses).cast_rays(rays, nthreads=self.nthreads)
        depth = hit["t_hit"].numpy()  # (H*W,)
        found = np.isfinite(depth)
        body = np.where(found, hit["geometry_ids"].numpy(), len(self.bodies)).astype(np.int64)
        normals = hit["primitive_normals"].numpy()  # (H*W, 3) float32
        dirs = rays[:, 3:]
        local = rays[:, :3] + np.where(found, depth, 0.0)[:, None] * dirs  # (H*W, 3) world
        local_normals = normals.copy()
        # Background bodies are modelled in world coordinates; objects need their own frame.
        on_object = np.flatnonzero((body >= self.num_background) & found)
        for k, pose in enumerate(object_poses):
            idx = on_object[body[on_object] == self.num_background + k]
            rot = pose[:3, :3].astype(np.float32)
            local[idx] = (local[idx] - pose[:3, 3].astype(np.float32)) @ rot
            local_normals[idx] = normals[idx] @ rot
        axis = np.argmax(np.abs(local_normals), axis=1)  # (H*W,) dominant normal axis
        a = np.where(axis == 0, local[:, 1], local[:, 0])  # tri-planar surface coordinates
        b = np.where(axis == 2, local[:, 1], local[:, 2])
        scale = self._tex_scale[body]  # (H*W,) texels per metre
        u = a * scale + self._tex_centre[body] + 97 * axis  # (n,) level-0 texel coordinates;
        v = b * scale + self._tex_centre[body]  # a different patch per face direction
        # Pixel footprint on the surface in level-0 texels picks the mip level (no aliasing).
        cos = np.abs(np.einsum("ij,ij->i", normals, dirs)) / self._dirs_norm  # (H*W,)
        footprint = np.where(found, depth, 1.0) / self._fx / np.maximum(cos, 0.25) * scale
        albedo = self._sample(body, u, v, np.log2(np.maximum(footprint, 1.0)))  # (n, 3)
        shade = _shade(normals, dirs) * (1.0 / 255.0)  # (H*W,)
        rgb = np.where(found[:, None], albedo * shade[:, None], 0.0).astype(np.float32)
        ids = np.where(found, body, -1).astype(np.int16)
        return Layer(
            rgb.reshape(self.height, self.width, 3),
            depth.reshape(self.height, self.width),
            ids.reshape(self.height, self.width),
        )

    def _covered_pixels(self, world_from_cam: np.ndarray, parts: list[Mesh]) -> np.ndarray:
        """Flat indices of the pixels that any part may cover (conservative).

        A mesh's image lies inside the convex hull of its projected vertices when it is wholly in
        front of the camera; the hull is filled and grown by one pixel.
        """
        h, w = self.height, self.width
        covered = np.zeros((h, w), np.uint8)
        cam_from_world = invert_se3(world_from_cam)
        for verts, _ in parts:
            cam = transform_points(cam_from_world, verts)  # (V, 3)
            if np.all(cam[:, 2] <= 0):
                continue
            if np.any(cam[:, 2] <= 1e-3):  # crosses the camera plane: cast every ray
                return np.arange(h * w)
            uv, _ = project_points(cam, self.intrinsics)  # (V, 2)
            if np.all(uv < -1) or np.all(uv[:, 0] > w + 1) or np.all(uv[:, 1] > h + 1):
                continue
            # OpenCV draws pixel (i, j) at integer (x=j, y=i): shift by the 0.5 centre offset.
            fixed = np.rint((np.clip(uv, -4 * w, 4 * w) - 0.5) * 4).astype(np.int32)  # 2 bits
            hull = cv2.convexHull(fixed)
            cv2.fillConvexPoly(covered, hull, 1, lineType=cv2.LINE_8, shift=2)
        covered = cv2.dilate(covered, np.ones((3, 3), np.uint8))
        return np.flatnonzero(covered)

    def render_meshes(
        self, world_from_cam: np.ndarray, parts: list[Mesh], colours: np.ndarray
    ) -> Layer:
        """Flat-coloured world meshes ``parts`` (e.g. hands, forearms); ids index ``parts``.

        Only the rays inside the image bounding boxes of the parts are cast.
        """
        h, w = self.height, self.width
        depth = np.full(h * w, np.inf, np.float32)
        ids = np.full(h * w, -1, np.int16)
        rgb = np.zeros((h * w, 3), np.float32)
        index = self._covered_pixels(world_from_cam, parts)  # (n,)
        if len(index):
            rc = o3d.t.geometry.RaycastingScene()
            for verts, faces in parts:
                rc.add_triangles(verts.astype(np.float32), faces.astype(np.uint32))
            rays = self.rays(world_from_cam, index)  # (n, 6)
            hit = rc.cast_rays(rays, nthreads=self.nthreads)
            t_hit = hit["t_hit"].numpy()
            ok = np.isfinite(t_hit)
            sel = index[ok]
            part = hit["geometry_ids"].numpy()[ok].astype(np.int64)
            depth[sel] = t_hit[ok]
            ids[sel] = part
            shade = _shade(hit["primitive_normals"].numpy()[ok], rays[ok, 3:])
            rgb[sel] = colours[part] * shade[:, None]
        return Layer(rgb.reshape(h, w, 3), depth.reshape(h, w), ids.reshape(h, w))


def _mip_pyramid(image: np.ndarray) -> list[np.ndarray]:
    """Box-filtered mip levels of a square texture, down to 1x1 (level ``l`` is 2**l coarser)."""
    levels = [np.ascontiguousarray(image)]
    while levels[-1].shape[0] > 1 and levels[-1].shape[1] > 1:
        h, w = levels[-1].shape[:2]
        levels.append(cv2.resize(levels[-1], (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    return levels


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """Float colour in [0, 1] to ``uint8`` (rounded)."""
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
