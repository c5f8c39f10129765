"""Settings of the simulator's tools besides the knife (Hydra keys ``task.pen.*``, ``task.spoon.*``).

The cream pen (``PenConfig``, topocut/sim/pen.py) and the spoon and cup (``SpoonConfig``, topocut/sim/spoon.py)
are simulator parts, so their settings live here and the simulator needs nothing from topocut.tasks;
the cream writing and scooping task configs hold them (task.pen, task.spoon; docs/tasks.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def nozzle_layer(spacing: float, radius: float) -> np.ndarray:
    """Offsets (m,3) of one extruded layer: the horizontal lattice points within radius spacings of the axis."""
    r = int(math.floor(radius + 1e-9))
    ij = np.array([(i, j) for i in range(-r, r + 1) for j in range(-r, r + 1) if i * i + j * j <= radius ** 2 + 1e-9])
    return np.concatenate([ij * spacing, np.zeros((len(ij), 1))], 1).astype(np.float32)


@dataclass
class PenConfig:
    """Cream pen: a nozzle at a fixed height above the board extrudes a von Mises "cream" (docs/tasks.md)."""

    height: float = 0.03  # nozzle above the board's top face [units]
    nozzle_radius: float = 1.0  # in particle spacings: a layer = lattice points within it (1.0 -> 5, a plus)
    extrude_speed: float = 1.5  # downward speed of the cream leaving the nozzle [units/s]; a layer per spacing
    speed: float = 1.2  # pen speed while writing [units/s]
    travel_speed: float = 2.0  # pen speed between strokes (extrusion off)
    friction: float = 4.0  # Coulomb coefficient of cream on the board: it sticks where it lands (food's: 0.5)
    step: float = 0.02  # longest pen move of one action (dx, dy, b) [units]
    yield_stress: float = 4.0  # cream's von Mises yield stress, per particle (the food's skin: 60)
    mu: float = 400.0  # cream's shear modulus (softer than the food: a larger stable dt)
    lam: float = 800.0
    settle_substeps: int = 300  # free settling after the last stroke
    max_particles: int = 12000  # capacity reserved for extruded particles

    def layer_pitch(self, spacing: float) -> float:
        """Stroke length between two extruded layers: the column grows one spacing at extrude_speed while the pen
        moves at speed (so m * extrude_speed / (spacing * speed) particles per unit of stroke)."""
        return self.speed * spacing / self.extrude_speed


@dataclass
class SpoonConfig:
    """Ice-cream scooping: a spherical-cap spoon, a cylindrical cup and an elastoplastic block (docs/tasks.md)."""

    radius: float = 0.06  # spoon bowl: spherical shell of this inner radius (>= ~3 cells: the band is a cell)
    thickness: float = 0.01  # shell thickness
    opening: float = 0.0  # rim plane at opening * radius from the centre along the bowl's axis (0: hemisphere)
    depth: float = 0.045  # how deep the bowl dips into the block (height of the scooped cap)
    advance: float = 0.02  # forward travel while the bowl curls through the block
    speed: float = 0.5  # spoon speed [units/s]
    block: list[float] = field(default_factory=lambda: [0.24, 0.24, 0.1])  # block size (x, y, z)
    block_center: list[float] = field(default_factory=lambda: [0.33, 0.5])  # block centre on the board (x, y)
    cup_center: list[float] = field(default_factory=lambda: [0.7, 0.5])  # cup axis (x, y)
    cup_radius: float = 0.1  # inner radius
    cup_height: float = 0.07
    cup_wall: float = 0.01
    yield_stress: float = 30.0  # the ice cream's von Mises yield stress (material 1 everywhere)
    # the 2-D placement actions: (x, y) of each scoop's bowl centre relative to the block centre
    scoops: list[list[float]] = field(default_factory=lambda: [[-0.03, -0.06], [-0.03, 0.06]])
