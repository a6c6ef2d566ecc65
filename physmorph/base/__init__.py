"""Foundations every layer may use: the simulation grid, the cameras, batched 3x3 linear algebra,
the Taichi runtime, Markdown tables, preview images, memory release, a call isolated in its own
process and what a SLURM cluster offers.

May import nothing of physmorph: it is the lowest layer.
"""
