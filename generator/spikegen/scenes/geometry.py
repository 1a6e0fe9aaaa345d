"""Small geometry helpers for building scenes: primitives as ``(vertices [N, 3], faces [M, 3])``.

Built on ``trimesh.creation``; everything is deterministic (no randomness here: scene modules
pass their own seeded ``np.random.Generator`` where they scatter things).
"""
from __future__ import annotations

import numpy as np
import trimesh

from .description import Mesh

Part = tuple  # (vertices float64 [N, 3], faces int64 [M, 3])


def _part(m: trimesh.Trimesh) -> Part:
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def box(size, center=(0.0, 0.0, 0.0)) -> Part:
    """Axis-aligned box of ``size [3]`` centred at ``center [3]``."""
    v, f = _part(trimesh.creation.box(extents=size))
    return v + np.asarray(center, dtype=np.float64), f


def cylinder(p0, p1, radius: float, sections: int = 16) -> Part:
    """Closed cylinder from point ``p0 [3]`` to ``p1 [3]``."""
    return _part(trimesh.creation.cylinder(radius=radius, segment=[p0, p1], sections=sections))


def sphere(center, radius: float, subdivisions: int = 3) -> Part:
    """Icosphere of ``radius`` at ``center [3]``."""
    v, f = _part(trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius))
    return v + np.asarray(center, dtype=np.float64), f


def capsule(p0, p1, radius: float, count=(12, 12)) -> Part:
    """Capsule (cylinder with round ends) from ``p0 [3]`` to ``p1 [3]``."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    m = trimesh.creation.capsule(height=length, radius=radius, count=list(count))
    m.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], axis / length))
    m.apply_translation((p0 + p1) / 2)
    return _part(m)


def torus(center, major: float, minor: float, axis=(0.0, 0.0, 1.0), sections=(32, 8)) -> Part:
    """Torus around ``axis [3]`` through ``center [3]``."""
    m = trimesh.creation.torus(major, minor, major_sections=sections[0], minor_sections=sections[1])
    axis = np.asarray(axis, float)
    m.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], axis / np.linalg.norm(axis)))
    m.apply_translation(center)
    return _part(m)


def tube(points, radius: float, sections: int = 8) -> Part:
    """Open tube of ``radius`` along the polyline ``points [P, 3]`` (P >= 2)."""
    pts = np.asarray(points, dtype=np.float64)
    tangents = np.gradient(pts, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    normal = _any_perpendicular(tangents[0])
    rings = []
    for t in tangents:  # parallel transport of the normal along the curve
        normal = normal - t * (normal @ t)
        normal /= np.linalg.norm(normal)
        rings.append(_ring(normal, np.cross(t, normal), radius, sections))
    v = (pts[:, None, :] + np.stack(rings)).reshape(-1, 3)
    return v, _ring_faces(len(pts), sections)


def _any_perpendicular(t: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    n = np.cross(t, a)
    return n / np.linalg.norm(n)


def _ring(n: np.ndarray, b: np.ndarray, radius: float, sections: int) -> np.ndarray:
    ang = 2 * np.pi * np.arange(sections) / sections
    return radius * (np.cos(ang)[:, None] * n + np.sin(ang)[:, None] * b)


def _ring_faces(rings: int, sections: int) -> np.ndarray:
    i = np.arange(rings - 1)[:, None] * sections
    j = np.arange(sections)[None, :]
    a, b = i + j, i + (j + 1) % sections
    c, d = a + sections, b + sections
    quads = np.stack([a, b, d, c], axis=-1).reshape(-1, 4)
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def revolve(profile_rz, sections: int = 32, center=(0.0, 0.0, 0.0)) -> Part:
    """Surface of revolution about +Z of the profile ``[(r, z), ...]`` (closed by trimesh)."""
    m = trimesh.creation.revolve(np.asarray(profile_rz, dtype=np.float64), sections=sections)
    m.apply_translation(center)
    return _part(m)


def transform(part: Part, matrix: np.ndarray) -> Part:
    """Apply a ``[4, 4]`` matrix to a part."""
    v, f = part
    return (np.c_[v, np.ones(len(v))] @ np.asarray(matrix).T)[:, :3], f


def rotation(axis, angle_rad: float) -> np.ndarray:
    """``[4, 4]`` rotation about ``axis [3]`` through the origin."""
    return trimesh.transformations.rotation_matrix(angle_rad, axis)


def translation(offset) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = offset
    return m


def scaling(factors) -> np.ndarray:
    return np.diag([*np.broadcast_to(np.asarray(factors, float), (3,)), 1.0])


def merge(parts) -> Part:
    """One ``(vertices, faces)`` from many parts."""
    vs, fs, n = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def mesh(name: str, parts, material: str, smooth: bool = False) -> Mesh:
    """A :class:`Mesh` from parts (float32 vertices, int32 faces)."""
    v, f = merge(parts)
    return Mesh(name, np.ascontiguousarray(v, dtype=np.float32), np.ascontiguousarray(f, dtype=np.int32),
                material, smooth)


def normalise(meshes, radius: float = 1.2) -> tuple:
    """Centre the meshes' joint bounding box at the origin and scale them uniformly so that the
    farthest vertex is ``radius`` from it. Returns a new tuple of :class:`Mesh`."""
    allv = np.concatenate([m.vertices for m in meshes]).astype(np.float64)
    centre = (allv.min(0) + allv.max(0)) / 2
    scale = radius / np.linalg.norm(allv - centre, axis=1).max()
    return tuple(Mesh(m.name, np.ascontiguousarray((m.vertices - centre) * scale, dtype=np.float32), m.faces,
                      m.material, m.smooth) for m in meshes)


def standard_lights(strength: float = 3.0) -> tuple:
    """A sun from above, slightly in front (-Y is "front" in these scenes)."""
    from .description import Light

    d = np.array([0.35, 0.45, -1.0])
    return (Light("SUN", strength, direction=tuple(d / np.linalg.norm(d))),)
