"""The `physmorph` command: a user's own morph from two shapes to a video, meshes, splats and a
viewer page, through the Snakemake workflow (run as a process, so resume, locks and the cluster
profile work as for every target).

The top layer: it may import every package below it; nothing imports it, and it never imports
Snakemake.
"""
