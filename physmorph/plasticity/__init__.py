"""Chamfer-guided plasticity (paper section 3.4, eq. 4): the step that migrates the rest state
toward the target (``step``), its neighbourhood sums in Taichi (``neighbourhood``), the
optimal-transport correspondences (``transport``) and nearest-point queries on a torch device
(``nearest``).

May import physmorph.base and physmorph.settings; not the solver, the renderer or the morph loop.
"""
