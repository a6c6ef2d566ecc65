"""The study's surface-topology probe (benchmarks/surface_topology.py): a particle torus is drawn of
genus 1 at every surface setting the probe tries, its tunnel kept in voxels finer than its hole
(the voxel counts themselves: tests/reports/test_body_measures.py)."""

import numpy as np

from benchmark_scripts import load_benchmark

surface_topology = load_benchmark("surface_topology")


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
