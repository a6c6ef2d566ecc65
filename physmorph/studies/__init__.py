"""The studies built on the morph: the speed/accuracy trade-off (``tradeoff``) and the stability
map of the extremes (``stability_map``: its terms and outputs; ``extremes``: its cells).

May import physmorph.stages and every layer below it; not the reports.
"""
