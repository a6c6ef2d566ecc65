"""The columns of a run's measures.csv (physmorph.reports.export.measures writes them, each
explained there and in docs/outputs.md), in a module of their own that imports nothing: the
workflow reads them while it plans (a new measure reruns the mesh jobs), before any job."""

MEASURE_COLUMNS = ("frame", "stray_share", "surface_distance_dx", "closed", "faces", "outside_largest_body",
                   "components", "genus", "target_genus", "surface_genus", "surface_p95_dx",
                   "roughness_percent")
