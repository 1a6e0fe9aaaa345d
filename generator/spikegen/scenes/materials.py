"""materials: a grid of spheres in glossy, rough, metal and glass materials (view-dependent effects)."""
from __future__ import annotations

from . import geometry as g
from .description import Material, SceneDescription

MATERIALS = (
    Material("glossy_red", (0.7, 0.05, 0.04), roughness=0.05),
    Material("rough_blue", (0.05, 0.15, 0.6), roughness=0.9),
    Material("gold", (1.0, 0.71, 0.29), roughness=0.15, metallic=1.0),
    Material("chrome", (0.95, 0.95, 0.95), roughness=0.02, metallic=1.0),
    Material("glass", (1.0, 1.0, 1.0), roughness=0.0, transmission=1.0, ior=1.5),
    Material("brushed_copper", (0.95, 0.64, 0.54), roughness=0.45, metallic=1.0),
    Material("frosted_glass", (0.8, 0.95, 0.9), roughness=0.35, transmission=1.0, ior=1.45),
    Material("glossy_green", (0.05, 0.45, 0.08), roughness=0.15),
    Material("rough_white", (0.8, 0.8, 0.8), roughness=1.0),
)


def build() -> SceneDescription:
    meshes = []
    for i, mat in enumerate(MATERIALS):
        x, y = 0.75 * (i % 3 - 1), 0.75 * (i // 3 - 1)
        meshes.append(g.mesh(f"sphere_{mat.name}", [g.sphere((x, y, 0.0), 0.3, 4)], mat.name, smooth=True))
    mats = {m.name: m for m in MATERIALS}
    return SceneDescription("materials", g.normalise(tuple(meshes), 1.2), mats, g.standard_lights(), (1, 1, 1), 0.6,
                            "3 x 3 spheres: glossy, rough, metallic and glass")
