"""physmorph: physics-based shape morphing with differentiable MPM and Gaussian splatting.

The library never imports snakemake: every stage is a plain Python function.
"""

__version__ = "0.1.0"
