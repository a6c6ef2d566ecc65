"""Screen-tile binning and depth sorting of projected Gaussians (3DGS duplicate-and-sort).

Every visible (view, Gaussian) entry is duplicated once per screen tile its cutoff box touches;
the duplicates are sorted by the key (global tile id, depth rank), so each tile's Gaussians lie
contiguously, nearest first. Memory is O(pairs) = O(Gaussians x tiles each touches), never
O(pixels x Gaussians).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class TileBins:
    point_list: torch.Tensor  # [M] int32: flattened (view * N + gaussian) index, grouped by tile, front to back
    tile_ranges: torch.Tensor  # [V * tiles_y * tiles_x, 2] int32: [start, end) into point_list
    half_extent: torch.Tensor  # [V * N, 2] half width/height of each entry's cutoff box (pixels)
    tiles_x: int
    tiles_y: int
    tile_size: int

    @property
    def pair_count(self) -> int:
        return int(self.point_list.shape[0])


def bin_gaussians(means2d: torch.Tensor, half_extent: torch.Tensor, depth: torch.Tensor,
                  visible: torch.Tensor, width: int, height: int, tile_size: int) -> TileBins:
    """means2d, half_extent: [V, N, 2]; depth, visible: [V, N]. No gradients flow here."""
    with torch.no_grad():
        n_views, n = visible.shape
        device = means2d.device
        tiles_x = (width + tile_size - 1) // tile_size
        tiles_y = (height + tile_size - 1) // tile_size
        flat_visible = visible.reshape(-1)
        ids = torch.nonzero(flat_visible).squeeze(1)  # [P_vis] flattened (v, n)
        m = means2d.reshape(-1, 2)[ids]
        hx = half_extent.reshape(-1, 2)[ids]
        # Tile index range (inclusive) of the cutoff box; conservative at the box edges.
        x0 = torch.clamp(torch.floor((m[:, 0] - hx[:, 0]) / tile_size), 0, tiles_x - 1).long()
        x1 = torch.clamp(torch.floor((m[:, 0] + hx[:, 0]) / tile_size), 0, tiles_x - 1).long()
        y0 = torch.clamp(torch.floor((m[:, 1] - hx[:, 1]) / tile_size), 0, tiles_y - 1).long()
        y1 = torch.clamp(torch.floor((m[:, 1] + hx[:, 1]) / tile_size), 0, tiles_y - 1).long()
        span_x = x1 - x0 + 1
        counts = span_x * (y1 - y0 + 1)
        n_tiles_total = n_views * tiles_y * tiles_x
        if ids.numel() == 0:
            return TileBins(torch.zeros(0, dtype=torch.int32, device=device),
                            torch.zeros(n_tiles_total, 2, dtype=torch.int32, device=device),
                            half_extent.reshape(-1, 2).contiguous(), tiles_x, tiles_y, tile_size)
        # Depth rank over all visible entries: within one tile all entries share a view, so a
        # global rank orders each tile front to back.
        rank = torch.empty_like(ids)
        rank[torch.argsort(depth.reshape(-1)[ids], stable=True)] = torch.arange(ids.numel(), device=device)
        owner = torch.repeat_interleave(torch.arange(ids.numel(), device=device), counts)  # [M]
        first = torch.cumsum(counts, 0) - counts
        first_tile = (ids // n * tiles_y + y0) * tiles_x + x0
        # One gather of everything a pair needs from its owner (gathers dominate on CPU).
        packed = torch.stack([first, span_x, first_tile, rank], dim=1)[owner]  # [M, 4]
        local = torch.arange(owner.numel(), device=device) - packed[:, 0]
        row = torch.div(local, packed[:, 1], rounding_mode="floor")
        tile_id = packed[:, 2] + row * tiles_x + (local - row * packed[:, 1])
        key = tile_id * ids.numel() + packed[:, 3]
        order = torch.argsort(key)
        point_list = ids[owner[order]].to(torch.int32)
        per_tile = torch.bincount(tile_id, minlength=n_tiles_total)
        ends = torch.cumsum(per_tile, 0)
        tile_ranges = torch.stack([ends - per_tile, ends], dim=1).to(torch.int32)
        return TileBins(point_list.contiguous(), tile_ranges.contiguous(), half_extent.reshape(-1, 2).contiguous(),
                        tiles_x, tiles_y, tile_size)
