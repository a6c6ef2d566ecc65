"""Nearest-point queries on a torch device: for each query x_i the nearest point of a fixed set and
its distance, what ``scipy.spatial.cKDTree(points).query(x, k=1)`` answers on the CPU.

An exhaustive search in float64, by blocks of query rows: with centred coordinates,
argmin_j |x_i - p_j|^2 = argmin_j (|p_j|^2 - 2 x_i.p_j), one matrix product and one row minimum
per block (NEAREST_BLOCK_ENTRIES pairs at a time); the winner's distance is then computed directly,
|x_i - p_j| = sqrt((e_0^2 + e_1^2) + e_2^2). The expansion's rounding (~1e-16 of the coordinates'
squared extent) can only pick another point whose squared distance is within that of the nearest's,
so the distances equal the KD tree's to ~1e-12 of the domain and the indices differ only at such
near-ties (tests/plasticity/test_plasticity_device.py). A query costs N M pairs (471K particles against 200K
target points: ~1e11, about 1.5 TB of float64 traffic, memory-bound on a GPU); on the CPU the KD
tree is far faster, and the callers use this search only with a device (``search_device``).
"""

from __future__ import annotations

import numpy as np
import torch

# Query-point pairs per block: the block's [rows, M] float64 matrix is 256 MB.
NEAREST_BLOCK_ENTRIES = 1 << 25


class DevicePoints:
    """A point set held on a torch device, centred, for repeated nearest-point queries."""

    def __init__(self, points: np.ndarray,  # [M, 3]
                 device: str = "cpu"):
        P = torch.as_tensor(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3), device=device)
        if len(P) == 0:
            raise ValueError("nearest-point queries need at least one point")
        self.device = P.device
        self.points = P
        self.centre = 0.5 * (P.amin(0) + P.amax(0))  # [3]
        self.centred_t = (P - self.centre).T.contiguous()  # [3, M]
        self.norm2 = (self.centred_t * self.centred_t).sum(0)  # [M]

    def query(self, x: np.ndarray,  # [N, 3]
              block_entries: int = NEAREST_BLOCK_ENTRIES) -> tuple[np.ndarray, np.ndarray]:  # [N] float64, [N] int64
        """Each x_i's nearest point: its distance and its index (the module docstring's search)."""
        X = torch.as_tensor(np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3), device=self.device)
        idx = torch.empty(len(X), dtype=torch.int64, device=self.device)
        rows = max(1, int(block_entries) // self.norm2.numel())
        for a in range(0, len(X), rows):
            q = X[a:a + rows] - self.centre
            # |p_j|^2 - 2 q.p_j: the squared distance less |q|^2, which leaves each row's argmin
            idx[a:a + rows] = torch.addmm(self.norm2[None, :], q, self.centred_t, alpha=-2.0).argmin(1)
        e = X - self.points[idx]
        dist = ((e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1]) + e[:, 2] * e[:, 2]).sqrt()
        return dist.cpu().numpy(), idx.cpu().numpy()


def nearest_points(points: np.ndarray,  # [M, 3]
                   x: np.ndarray,  # [N, 3]
                   device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:  # [N] distances, [N] indices
    """Each x_i's nearest of ``points`` on the torch ``device``: DevicePoints(points, device).query(x)."""
    return DevicePoints(points, device).query(x)
