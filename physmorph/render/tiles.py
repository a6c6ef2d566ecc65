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
    """means2d, half_extent: [V, N, 2]; depth, visible: [V, N]. No gradients flow here.

    View by view: a tile belongs to one view, so each view's pairs sort on their own and the
    lists concatenate in view order to the list of one sort over every view (the same list), with
    a view's temporaries (~90 B a pair) alive at a time instead of every view's."""
    with torch.no_grad():
        n_views, n = visible.shape
        device = means2d.device
        tiles_x = (width + tile_size - 1) // tile_size
        tiles_y = (height + tile_size - 1) // tile_size
        per_view = tiles_y * tiles_x
        lists = []
        per_tile = torch.zeros(n_views * per_view, dtype=torch.int64, device=device)
        for v in range(n_views):
            point_list, counts = _bin_view(means2d[v], half_extent[v], depth[v], visible[v], tiles_x, tiles_y,
                                           tile_size)
            lists.append((point_list + v * n).to(torch.int32))
            per_tile[v * per_view:(v + 1) * per_view] = counts
        ends = torch.cumsum(per_tile, 0)
        tile_ranges = torch.stack([ends - per_tile, ends], dim=1).to(torch.int32)
        return TileBins(torch.cat(lists).contiguous(), tile_ranges.contiguous(), half_extent.reshape(-1, 2).contiguous(),
                        tiles_x, tiles_y, tile_size)


def _bin_view(means2d: torch.Tensor, half_extent: torch.Tensor,  # [N, 2] one view
              depth: torch.Tensor, visible: torch.Tensor,  # [N]
              tiles_x: int, tiles_y: int, tile_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """One view's (tile, depth)-sorted Gaussian indices [M_v] and its pairs per tile [tiles_y * tiles_x]."""
    device = means2d.device
    ids = torch.nonzero(visible).squeeze(1)  # [P_vis]
    if ids.numel() == 0:
        return ids, torch.zeros(tiles_y * tiles_x, dtype=torch.int64, device=device)
    m = means2d[ids]
    hx = half_extent[ids]
    # Tile index range (inclusive) of the cutoff box; conservative at the box edges.
    x0 = torch.clamp(torch.floor((m[:, 0] - hx[:, 0]) / tile_size), 0, tiles_x - 1).long()
    x1 = torch.clamp(torch.floor((m[:, 0] + hx[:, 0]) / tile_size), 0, tiles_x - 1).long()
    y0 = torch.clamp(torch.floor((m[:, 1] - hx[:, 1]) / tile_size), 0, tiles_y - 1).long()
    y1 = torch.clamp(torch.floor((m[:, 1] + hx[:, 1]) / tile_size), 0, tiles_y - 1).long()
    span_x = x1 - x0 + 1
    counts = span_x * (y1 - y0 + 1)
    # Depth rank: each tile's entries front to back (stable: ties keep the index order).
    rank = torch.empty_like(ids)
    rank[torch.argsort(depth[ids], stable=True)] = torch.arange(ids.numel(), device=device)
    owner = torch.repeat_interleave(torch.arange(ids.numel(), device=device), counts)  # [M_v]
    first = torch.cumsum(counts, 0) - counts
    first_tile = y0 * tiles_x + x0
    # One gather of everything a pair needs from its owner (gathers dominate on CPU).
    packed = torch.stack([first, span_x, first_tile, rank], dim=1)[owner]  # [M_v, 4]
    local = torch.arange(owner.numel(), device=device) - packed[:, 0]
    row = torch.div(local, packed[:, 1], rounding_mode="floor")
    tile_id = packed[:, 2] + row * tiles_x + (local - row * packed[:, 1])
    key = tile_id * ids.numel() + packed[:, 3]
    del packed, local, row
    order = torch.argsort(key)
    return ids[owner[order]], torch.bincount(tile_id, minlength=tiles_y * tiles_x)
