"""What people read: the paper's tables (``tables``) and figures (``figures``) from run files, the
metrics they report (``metrics``) and which runs each compares (``layout``), the generated pages
(``userdocs``, ``results_sections``, ``page_meta``: ``python -m physmorph.reports.userdocs``), the
exports other programs read (``export``: videos, meshes, splats, the viewer page) and the workflow's
report and study entry points (``stages``).

The top layer: may import every other physmorph package.
"""
