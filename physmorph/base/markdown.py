"""Markdown tables of DataFrames, for every page and table file the package writes (the paper's
tables, the speed/accuracy study, the stability map, the generated docs)."""

from __future__ import annotations

import numpy as np


def markdown_table(df) -> str:
    """A GitHub table of the DataFrame ``df``, without the optional tabulate dependency."""
    def fmt(v):
        if isinstance(v, float):
            return "" if np.isnan(v) else f"{v:.4g}"
        return str(v)
    lines = ["| " + " | ".join(map(str, df.columns)) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join(lines) + "\n"
