"""What a dry run says of a user's own meshes (file shapes given by ``path``) before any job: the
refusal their prepare_mesh or sample_particles job would end in, in the same one line, and warnings
for what the run would accept but not do well (``snakemake -n`` and `physmorph morph` both ask)."""

from __future__ import annotations

from pathlib import Path

from .errors import MeshError
from .fit import largest_size_in_views, particle_region, region_limit, region_size
from .mesh_record import mesh_record


def check_user_shape(settings, shape: str, cameras) -> list[str]:
    """Warnings for the file shape ``shape`` of ``settings`` at its configured size (``cameras``:
    the target's views); MeshError, one line naming the file, where the run would refuse it: not
    there, a folder, unreadable, empty, flat, open beyond repair, or too large for the grid's
    particle region (with the largest size that fits)."""
    spec = settings.shape(shape)
    path = Path(spec.path)
    label = f"{path} (shape '{shape}')"
    if path.is_dir():
        raise MeshError(f"{label}: is a folder, not a mesh file")
    if not path.is_file():
        raise MeshError(f"{label}: mesh file not found")
    record = mesh_record(path)
    if record.refusal is not None:
        raise MeshError(f"{record.refusal} (shape '{shape}')")
    grid = settings.sampling.grid_res
    largest = region_size(record.unit_lo, record.unit_hi, grid, settings.domain)
    if spec.size > region_limit(record.unit_lo, record.unit_hi, grid, settings.domain):
        lo, hi = particle_region(grid, settings.domain)
        raise MeshError(f"{label}: size {spec.size:g} does not fit grid {grid}'s particle region [{lo:g}, {hi:g}]^3: "
                        f"the largest size that fits is {largest:.1f} (python -m physmorph.meshes.fit {path})",
                        key=f"shapes.{shape}.size")
    warnings = []
    in_views = largest_size_in_views(record, cameras, spec.size)
    if spec.size > in_views:
        warnings.append(f"{label}: at size {spec.size:g} it reaches past the edge of a target view (every view holds "
                        f"it whole up to size {in_views:.1f}), so the render loss sees part of it")
    if record.bodies > 1:
        warnings.append(f"{label}: {record.bodies} separate bodies; the morph fills them as one shape, and one body "
                        "morphs best (MPM cannot split the source to fill two)")
    return warnings


def user_shape_report(settings, cameras) -> tuple[list[str], str | None]:
    """(warnings, the first refusal or None) over every file shape of ``settings`` given by path."""
    warnings: list[str] = []
    for name, spec in settings.shapes.items():
        if spec.kind == "file" and spec.path is not None:
            try:
                warnings += check_user_shape(settings, name, cameras)
            except MeshError as exc:
                return warnings, " ".join(str(exc).split())
    return warnings, None
