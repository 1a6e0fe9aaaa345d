"""What a scene is, independent of any renderer: meshes, materials, lights and world (pure NumPy).

Units are Blender's (metres); world ``+Z`` is up; the object sits at the origin and fits the
NeRF camera rig (a bounding sphere of radius <= :data:`MAX_RADIUS`, so that it stays inside the
frame of a camera at distance 4.0311 with ``camera_angle_x`` 0.6911 from every direction).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MAX_RADIUS = 1.3  # asin(1.3 / 4.0311) = 0.328 rad < half the field of view (0.3456 rad)


@dataclass(frozen=True, eq=False)
class Material:
    """A principled surface. Colours are linear RGB in 0..1.

    ``texture`` (optional) is a linear RGB image ``float32 [h, w, 3]`` multiplied into the base
    colour, box-projected from object coordinates with ``texture_scale`` repeats per metre.
    """

    name: str
    base_color: tuple = (0.8, 0.8, 0.8)
    roughness: float = 0.5
    metallic: float = 0.0
    transmission: float = 0.0
    ior: float = 1.45
    specular: float = 0.5
    texture: np.ndarray | None = None
    texture_scale: float = 1.0


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh: ``vertices float32 [N, 3]``, ``faces int32 [M, 3]`` (counter-clockwise outward)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    material: str
    smooth: bool = False


@dataclass(frozen=True)
class Light:
    """A light: ``kind`` "SUN" (``direction`` it shines along, ``strength`` W/m^2) or
    "AREA"/"POINT" (``location``, ``direction`` for AREA, ``strength`` in W, ``size`` m)."""

    kind: str
    strength: float
    location: tuple = (0.0, 0.0, 0.0)
    direction: tuple = (0.0, 0.0, -1.0)
    color: tuple = (1.0, 1.0, 1.0)
    size: float = 0.1


@dataclass(frozen=True, eq=False)
class SceneDescription:
    """A whole scene. ``world_color`` (linear RGB) x ``world_strength`` lights it from every side
    (the film is transparent, so the world is never seen directly)."""

    name: str
    meshes: tuple
    materials: dict
    lights: tuple = ()
    world_color: tuple = (1.0, 1.0, 1.0)
    world_strength: float = 0.5
    notes: str = ""
    extra: dict = field(default_factory=dict)

    def vertices(self) -> np.ndarray:
        """All vertices ``[N, 3]`` of all meshes."""
        return np.concatenate([m.vertices for m in self.meshes]).astype(np.float64)

    def triangle_count(self) -> int:
        return int(sum(len(m.faces) for m in self.meshes))

    def bounding_radius(self) -> float:
        """Largest distance of any vertex from the origin."""
        return float(np.linalg.norm(self.vertices(), axis=1).max())
