"""The study's surface-topology probe (benchmarks/surface_topology.py): a voxel solid's pieces,
tunnels and cavities are counted as their definitions say, and a particle torus is drawn of genus 1
at every surface setting the probe tries, its tunnel kept in voxels finer than its hole."""

import numpy as np

from benchmark_scripts import load_benchmark

surface_topology = load_benchmark("surface_topology")


def test_pieces_tunnels_and_cavities_of_voxel_solids():
    ring = np.zeros((8, 8, 3), bool)
    ring[1:7, 1:7, :] = True
    ring[3:5, 3:5, :] = False  # a square hole through the block: one tunnel
    assert surface_topology.solid_topology(ring) == (1, 1, 0)
    hollow = np.zeros((7, 7, 7), bool)
    hollow[1:6, 1:6, 1:6] = True
    hollow[3, 3, 3] = False  # a closed void: one cavity, no tunnel
    assert surface_topology.solid_topology(hollow) == (1, 0, 1)
    two = np.zeros((9, 4, 4), bool)
    two[0:3], two[5:9] = True, True
    assert surface_topology.solid_topology(two) == (2, 0, 0)
    # a diagonal contact is a 26-connection: two cubes meeting at an edge are one piece
    edge = np.zeros((4, 4, 2), bool)
    edge[0:2, 0:2], edge[2:4, 2:4] = True, True
    assert surface_topology.solid_topology(edge) == (1, 0, 0)


def test_a_particle_torus_is_of_genus_one_at_every_setting_and_in_fine_voxels():
    # a solid torus (major radius 4, minor 1.5) sampled on a grid of 0.5: its hole is 5 units across
    axis = np.arange(-6.0, 6.01, 0.5)
    g = np.stack(np.meshgrid(axis, axis, np.arange(-2.0, 2.01, 0.5), indexing="ij"), axis=-1).reshape(-1, 3)
    inside = (np.hypot(g[:, 0], g[:, 1]) - 4.0) ** 2 + g[:, 2] ** 2 < 1.5 ** 2
    x = g[inside]
    state = {"x": x, "volume": np.full(len(x), 0.125), "det_F": np.ones(len(x)), "dx": 1.0}
    rows = surface_topology.settings_topology(state)
    assert len(rows) == 1 + len(surface_topology.SETTINGS)
    assert all(row[2:] == (1, 1) for row in rows), rows
    mesh = surface_topology.particle_surface(x, state["volume"], state["det_F"], 1.0)
    assert surface_topology.voxel_topology(mesh, 0.5) == (1, 1, 0)
