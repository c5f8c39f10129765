"""Topology discovery settings (see docs/topology.md for the method)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class TopologyConfig:
    # --- grid ---------------------------------------------------------------
    resolution: int = 128  # nodes along the longest axis of the padded particle bounding box
    voxel_size: float | None = None  # fixed node spacing instead (overrides resolution)
    max_resolution: int = 256  # cap on nodes per axis when voxel_size is given
    padding_voxels: int = 3  # empty nodes kept around the particles' bounding box (+ the particle radius)
    # --- implicit surface SDF(x) = min_p |x - x_p| - r_p ----------------------
    particle_radius: float | None = None  # r_p; None: radius_factor * particle spacing (median 3rd-NN distance)
    radius_factor: float = 1.2  # > sqrt(3)/2 fills a lattice's interior; 1.2 also closes tunnels in jittered samples
    # exact distances within r_p + band_voxels*h of a particle, clamped beyond: 1 voxel is enough, since
    # marching cubes interpolates only along edges that change sign, whose nodes have |sdf| <= h
    band_voxels: float = 1.0
    board_z: float | None = 0.05  # nothing below the board's top face is material (None: no board)
    # --- knife carving ------------------------------------------------------
    carve: bool = True
    min_gap_voxels: float = 2.0  # carved slab is at least this many voxels thick (a gap the grid resolves)
    # a sweep whose lower end is within this many voxels of the board is carved on through the board
    board_snap_voxels: float = 2.0
    carve_radius: float | None = None  # carve only within this distance of damaged particles; None: 3 r_p
    # which particles license carving the sweep: "swept", every particle the blade passed (the simulator separates
    # pieces by the swept surface alone, topocut.sim.pieces.split); "damaged", only damaged ones (the paper's
    # damage-driven rule: at 128^3 cuts that damage few particles left discovery merging what the simulator had
    # separated, docs/topology.md)
    carve_through: str = "swept"
    # --- keep earlier splits ------------------------------------------------
    preserve_splits: bool = True  # different previous clusters never merge (cutting only splits)
    # --- mesh ---------------------------------------------------------------
    smoothing_iterations: int = 5
    smoothing_alpha: float = 0.5  # v_i += alpha * (mean_j v_j - v_i)
    min_component_voxels: int = 8  # pieces with fewer inside nodes are dropped (debris)
    min_piece_particles: int = 20  # smaller pieces are chips of debris: they join the nearest larger piece
    max_void_voxels: int = 64  # enclosed empty regions up to this size are filled (gaps between particles)
    # --- particle assignment ------------------------------------------------
    tau: float | None = None  # proximity threshold to a piece's surface; None: 2 r_p + half the gap
    # --- timing ---------------------------------------------------------------
    # wait for the device after every step so that each gets its own time; off, the host queues the next
    # step's launches while the GPU runs (the total is shorter; per-step figures are then enqueue times)
    step_timings: bool = False
    # --- planning -------------------------------------------------------------
    # MPPI's rollouts discover all scenes of a simulated cut in one call (topology.batch.discover_batch: one
    # grid, one pass of every step); False: one discover() call per scene (to compare the two)
    batch_scenes: bool = True

    def validate(self) -> TopologyConfig:
        if self.carve_through not in ("swept", "damaged"):
            raise ValueError(f"topology.carve_through={self.carve_through!r}; valid: swept, damaged")
        if self.resolution < 8:
            raise ValueError(f"topology.resolution must be >= 8, got {self.resolution}")
        if self.voxel_size is not None and self.voxel_size <= 0:
            raise ValueError(f"topology.voxel_size must be > 0 or None, got {self.voxel_size}")
        if self.radius_factor <= 0 or (self.particle_radius is not None and self.particle_radius <= 0):
            raise ValueError("topology.particle_radius / topology.radius_factor must be > 0")
        if self.band_voxels < 1.0:
            raise ValueError(f"topology.band_voxels must be >= 1 (marching cubes needs exact values one voxel "
                             f"out), got {self.band_voxels}")
        if not 0.0 < self.smoothing_alpha <= 1.0:
            raise ValueError(f"topology.smoothing_alpha must be in (0, 1], got {self.smoothing_alpha}")
        if self.smoothing_iterations < 0 or self.min_component_voxels < 0:
            raise ValueError("topology.smoothing_iterations and topology.min_component_voxels must be >= 0")
        return self
