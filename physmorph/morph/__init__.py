"""The morph (paper Algorithm 1) and what only it uses: the resumable loop (``loop``), the state a
frame hands the next (``frame_state``) and its per-frame measures (``frame_measures``), the
steering policies (``steering``), the render injection's gain (``injection``), the settling phase
(``settle``), the divergence checks (``stability``), the surface mask (``surface_mask``), the
share of the reachable gap (``quality``) and the target images (``targets``).

May import the solver (physmorph.mpm), the renderer (physmorph.render), the plasticity and every
foundation (meshes, records, settings, base).
"""
