"""The tiny test profile's morph runs shared by the morph loop's test files."""

import dataclasses

from physmorph.morph.loop import morph_config, run_morph

# Measured on the tiny profile (12 frames, ~1.2K particles): see docs/study/log.md.
TINY_CLOSED_FINAL = 0.5


def run_tiny(tiny, experiment, out_name, **changes):
    """One tiny run (``tiny``: conftest's settings and folder); without the experiment's release
    frames unless a test asks for them. Returns the run file."""
    cfg, d = tiny
    mc = dataclasses.replace(morph_config(cfg, experiment), progress=False, **{"release_frames": 0, **changes})
    out = d / out_name
    run_morph(d / "p_iso.h5", d / "t_bunny.h5", out, mc, name=out_name)
    return out
