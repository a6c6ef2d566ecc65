"""The config sections' one-line texts, in the order of config/config.yaml, and the reading of
every key's declaration (meaning, unit, range) out of the generated schema
(physmorph.settings.workflow.json_schema: each field's description, unit and bounds are declared with the
field, physmorph.settings.base). ``config_reference()`` (physmorph.reports.userdocs) joins them into
config/README.md.
"""

from __future__ import annotations

from physmorph.settings.base import interval_text

# Sections, in the order of config/config.yaml, with one line each.
SECTIONS = {
    "": "Run-wide settings.",
    "raw_meshes": "Raw meshes fetched from a pinned URL and checked against their SHA-256.",
    "shapes": "The shapes experiments morph from and to; each is repaired, normalised to `size` and centred "
              "on its volume centroid.",
    "sampling": "Particle sampling on the simulation grid (file tag {grid_res}x{ppc_surface}x{ppc_interior}).",
    "target": "The target's images (cameras on a ring around the origin), grid mass and surface points.",
    "mpm": "The differentiable MPM solver and the optimiser of its control field (physmorph.settings.mpm.MPMConfig).",
    "render": "The differentiable Gaussian splatting renderer and its losses (physmorph.settings.render.RenderConfig).",
    "plasticity": "Chamfer-guided plasticity: each particle's rest state pulled toward its destination "
                  "(physmorph.settings.plasticity.PlasticityConfig).",
    "surface": "The surface mask: which particles the render loss sees (physmorph.settings.surface.SurfaceMaskConfig).",
    "morph": "The frame loop of one run (physmorph.settings.morph.MorphConfig).",
    "experiments": "The experiments: one morph run each; unset keys take the sections' values.",
    "tradeoff": "The speed/accuracy study: the base experiment rerun with one knob changed at a time.",
    "tables": "What `snakemake tables` (and `figures`) builds.",
    "export": "Videos, surface meshes and Gaussian-splat files of the full-method runs (`snakemake export`; "
              "physmorph.settings.export.ExportConfig).",
}


def schema_keys() -> list[tuple[str, dict]]:
    """(dotted key, its schema) of every key of the config schema, mapping entries as ``<name>``."""
    from physmorph.settings.schema import json_schema

    out: list[tuple[str, dict]] = []

    def walk(node: dict, prefix: str) -> None:
        for k, v in (node.get("properties") or {}).items():
            key = f"{prefix}.{k}" if prefix else k
            out.append((key, v))
            walk(v, key)
        extra = node.get("additionalProperties")
        if isinstance(extra, dict):
            walk(extra, f"{prefix}.<name>")
        for option in node.get("anyOf", []):
            walk(option, prefix)

    walk(json_schema(), "")
    return out


def range_of(sub: dict) -> str:
    """A key's range in words: its declared range note, else its bounds (">= 1", "[0, 1)")."""
    if sub.get("range"):
        return sub["range"]
    for option in sub.get("anyOf", []):  # an optional number: the number's bounds
        if range_of(option):
            return range_of(option)
    return interval_text(sub.get("minimum"), sub.get("exclusiveMinimum"), sub.get("maximum"), sub.get("exclusiveMaximum"))


def field_docs() -> dict[str, tuple[str, str, str]]:
    """(meaning, unit, range) of every key, read from its declaration (through the schema)."""
    return {key: (sub.get("description", ""), sub.get("unit", ""), range_of(sub))
            for key, sub in schema_keys() if key not in SECTIONS or "description" in sub}
