"""lego: a yellow brick bulldozer with studs, tracks and a shovel (built in stud units, then fitted)."""
from __future__ import annotations

import numpy as np

from . import geometry as g
from .description import Material, SceneDescription

STUD_R, STUD_H = 0.3, 0.2  # stud radius and height, in stud pitches


def studs(x0: float, x1: float, y0: float, y1: float, z: float) -> list:
    """One stud on every integer pitch of the rectangle ``[x0, x1] x [y0, y1]`` at height ``z``."""
    xs = np.arange(x0 + 0.5, x1, 1.0)
    ys = np.arange(y0 + 0.5, y1, 1.0)
    return [g.cylinder((x, y, z), (x, y, z + STUD_H), STUD_R, 12) for x in xs for y in ys]


def track(y: float) -> tuple[list, list]:
    """(dark rubber parts, grey wheel parts) of the track centred at ``y``."""
    dark = [g.box((7.0, 2.0, 3.0), (0, y, 1.5))]
    dark += [g.cylinder((x, y - 1, 1.5), (x, y + 1, 1.5), 1.5, 20) for x in (-3.5, 3.5)]
    for x in np.arange(-3.5, 3.6, 0.7):  # treads on top and bottom
        dark += [g.box((0.3, 2.1, 0.2), (x, y, 3.05)), g.box((0.3, 2.1, 0.2), (x, y, -0.05))]
    side = y + np.sign(y) * 1.0
    grey = [g.cylinder((x, side, 1.5), (x, side + np.sign(y) * 0.15, 1.5), r, 16)
            for x, r in ((-3.5, 1.1), (0.0, 0.8), (3.5, 1.1))]
    return dark, grey


def body() -> list:
    """Yellow chassis, cabin, engine cover, arms and studs."""
    parts = [g.box((8, 6, 3), (0, 0, 3.5)), g.box((4, 5, 4), (-2, 0, 7)), g.box((3.5, 4, 1.5), (2.25, 0, 5.75))]
    parts += studs(-4, 4, -3, 3, 5.0) + studs(-4, 0, -2.5, 2.5, 9.0) + studs(0.5, 4, -2, 2, 6.5)
    for y in (-2.6, 2.6):  # shovel arms (square beams)
        parts.append(g.cylinder((3.5, y, 4.2), (7.2, y, 2.2), 0.35, 4))
    return parts


def shovel() -> list:
    """A curved blade in front: boxes along an arc in the x-z plane."""
    parts = []
    for a in np.linspace(-0.2, 1.6, 10):
        x, z = 7.6 + 1.4 * np.sin(a), 2.0 - 1.4 * np.cos(a) + 1.0
        parts.append(g.transform(g.box((0.3, 7.0, 0.55)), g.translation((x, 0, z)) @ g.rotation((0, 1, 0), -a)))
    parts += [g.box((1.6, 0.25, 2.0), (8.2, y, 2.3)) for y in (-3.4, 3.4)]
    return parts


def details() -> tuple[list, list]:
    """(black parts: windows and exhaust, grey parts: light and grille)."""
    black = [g.box((0.1, 4.0, 2.0), (0.02, 0, 7.5)), g.box((3.0, 0.1, 2.0), (-2, 2.52, 7.5)),
             g.box((3.0, 0.1, 2.0), (-2, -2.52, 7.5)), g.cylinder((3.0, 1.2, 6.5), (3.0, 1.2, 9.0), 0.3, 12)]
    grey = [g.box((0.2, 3.0, 1.2), (4.05, 0, 3.5))]
    return black, grey


def build() -> SceneDescription:
    dark, grey = [], []
    for y in (-4.0, 4.0):
        d, gr = track(y)
        dark += d
        grey += gr
    black, grey2 = details()
    meshes = (g.mesh("lego_yellow", body() + shovel(), "yellow"), g.mesh("lego_tracks", dark, "rubber"),
              g.mesh("lego_grey", grey + grey2, "grey"), g.mesh("lego_black", black, "black"))
    mats = {"yellow": Material("yellow", (0.80, 0.50, 0.02), roughness=0.3),
            "rubber": Material("rubber", (0.03, 0.03, 0.03), roughness=0.7),
            "grey": Material("grey", (0.35, 0.35, 0.37), roughness=0.35),
            "black": Material("black", (0.01, 0.01, 0.012), roughness=0.15)}
    return SceneDescription("lego", g.normalise(meshes, 1.2), mats, g.standard_lights(), (1, 1, 1), 0.6,
                            "brick bulldozer: studs, tracks with treads, shovel on two arms")
