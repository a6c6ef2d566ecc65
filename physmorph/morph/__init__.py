"""The morph (paper Algorithm 1) and what only it uses: the resumable loop (``loop``), what a run
reads and never changes (``inputs``), the state a frame hands the next (``frame_state``) and its
per-frame measures (``frame_measures``), the judgement of each frame (``judge``) with the
steering policies (``steering``) and the settling phase (``settle``), the render injection's gain
(``injection``), the divergence checks (``stability``), the surface mask (``surface_mask``), the
share of the reachable gap (``quality``) and the target images (``targets``).

May import the solver (physmorph.mpm), the renderer (physmorph.render), the plasticity and every
foundation (meshes, records, settings, base).
"""
