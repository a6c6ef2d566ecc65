"""Export of a morph's bodies to files other programs read: pure functions on arrays and run files.

- runs.py: what an export needs from a finished run file (saved frames, a frame's x, F, Fp, and
  the rest volumes from the particle file the run was made from).
- surface.py: a closed, smoothed triangle surface of the particle body (volume splat, marching
  cubes, Taubin smoothing, volume matched to sum_p V_p det F_p), the transform from the simulation
  domain back to the input mesh's frame, and PLY/GLB writers.
- splats.py: the particles as 3D Gaussians (Sigma_p = sigma0^2 F_p F_p^T, the renderer's) in the
  PLY layout of the original 3D Gaussian splatting viewers, and a reader of its covariances.

Typical use (frame k of the run iso_bunny_full of the default profile; the run's particle file
is its source shape's, ``particles/<source>_<grid>x<ppc_surface>x<ppc_interior>.h5``)::

    from physmorph.reports.export.surface import domain_to_input, particle_surface, write_glb
    from physmorph.reports.export.runs import frame_state
    from physmorph.reports.export.splats import write_splats
    r = "results/default"
    s = frame_state(f"{r}/runs/iso_bunny_full.h5", k, particles_h5=f"{r}/particles/iso_32x2x1.h5")
    mesh = particle_surface(s["x"], s["volume"], s["det_F"], s["dx"])        # domain units
    write_glb(mesh, "iso_bunny_full_k.glb")
    to_bunny = domain_to_input(f"{r}/meshes/bunny.h5")  # the target's raw frame (or iso.h5: the source's)
    write_glb(particle_surface(s["x"], s["volume"], s["det_F"], s["dx"], transform=to_bunny), "k_bunny_frame.glb")
    write_splats("iso_bunny_full_k_splats.ply", s["x"], s["F"], s["sigma0"])  # all particles; s["is_surface"] selects

This package imports neither the solver nor the renderer (no taichi, no torch).
"""
