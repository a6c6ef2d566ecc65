"""The plasticity's neighbourhood sums (paper section 3.4, eq. 4) in one Taichi pass each.

Steps 2 and 3 of physmorph.plasticity.step, over each particle's k neighbours j in K_i (the KD tree's
query, the particle itself included with r2 = 0):

- :func:`smooth_displacement`: ``iters`` passes of d_i <- mean_{j in K_i} d_j; with ``sources``
  (the neighbour pool, the only particles any K_i holds) every pass but the last updates those
  rows alone, the others keeping their d (what plasticity.knn_smooth_sparse computes).
- :func:`displacement_jacobian_pairs`: J_i = sum_j w_ij (d_j - d_i)(x_j - x_i)^T / n_i with
  w_ij = 1 / r2_ij (0 for the particle itself or a coincident neighbour) and n_i the count of
  nonzero weights (at least 1).

At the paper's scale (471K particles, k = 64) the sparse-matrix forms took ~1.4 s of a frame. The
pair sums here are summed directly (no expansion of the products, so no cancellation); the
references are plasticity.knn_smooth and plasticity.displacement_jacobian.

The neighbourhoods K_i themselves (step 2's k nearest particles of the pool) come from
:func:`k_nearest`: a uniform cell grid over the particles, cells 0.75 of the k-th neighbour's
radius. Most queries are settled by a block of 4x4x4 cells around them (a histogram of r2 finds the
bin of the k-th nearest, a second pass over the candidates the first scan kept writes the row); the rest scan
rings of cells, keeping their k best in a max-heap and passing over cells farther than its largest,
until the k-th distance is inside the rings scanned. Exact, as the KD tree it replaces
(plasticity.nearest_neighbours, the reference), which took ~3 s of a paper-scale frame for the
query and another ~2 s to gather and square its arrays.
"""

# No "from __future__ import annotations": Taichi needs the kernel annotations as objects.

import numpy as np
import taichi as ti

from physmorph.base.taichi_runtime import ensure_taichi, taichi_state


# The cells per axis of the block a query scans first (_k_nearest_block) and the cells' side in
# k-th-neighbour radii (k_nearest's cell_scale). The k-th neighbour lies at 0.9-1.1 estimated
# radii: a block of 3^3 cells of one radius (its reach 1-1.5 radii) left a tenth of the queries to
# the rings; 4^3 cells of 0.75 radii (the query in the middle two cells on each axis: its reach at
# least 1.125 radii) scan about as many points and leave a hundredth
# (docs/study/performance_history.md, the k-nearest block of 4x4x4 cells).
BLOCK_CELLS = 4
CELL_SCALE = 0.75
# The slots for candidates (points of the block within its reach) a row keeps for its second pass
# (M in _k_nearest_block): ~100-250 candidates at the sampling's density; a row with M or more
# scans its block again. The scratch is chunk x M x 12 bytes (25 MB at k_nearest's chunk).
BLOCK_CANDIDATES = 256
# A cell is passed over only where its box is farther than the heap's largest r2 by this relative
# share: a point the floor of (x - lo) / h put in the cell may lie outside its box by round-off.
_CELL_GAP_SLACK = 1e-9


@ti.kernel
def _mean_rows(d: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3]
               neighbors: ti.types.ndarray(ndim=2),  # [N, k] int
               rows: ti.types.ndarray(ndim=1),  # [R] the rows to update
               out: ti.types.ndarray(dtype=ti.f64, ndim=2)):  # [N, 3], rows written
    k = neighbors.shape[1]
    for r in range(rows.shape[0]):
        i = rows[r]
        acc = ti.Vector([0.0, 0.0, 0.0], ti.f64)
        for a in range(k):
            j = neighbors[i, a]
            acc += ti.Vector([d[j, 0], d[j, 1], d[j, 2]])
        acc /= ti.cast(k, ti.f64)
        for c in ti.static(range(3)):
            out[i, c] = acc[c]


@ti.kernel
def _jacobian(x: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3]
              d: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3]
              neighbors: ti.types.ndarray(ndim=2),  # [N, k] int
              r2: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, k], or unused (given_r2 False)
              out: ti.types.ndarray(dtype=ti.f64, ndim=3),  # [N, 3, 3]
              given_r2: ti.template()):  # False: r2_ij = |x_j - x_i|^2 here (k_nearest's own value)
    k = neighbors.shape[1]
    for i in range(x.shape[0]):
        xi = ti.Vector([x[i, 0], x[i, 1], x[i, 2]])
        di = ti.Vector([d[i, 0], d[i, 1], d[i, 2]])
        J = ti.Matrix.zero(ti.f64, 3, 3)
        count = 0
        for a in range(k):
            j = neighbors[i, a]
            e = ti.Vector([x[j, 0], x[j, 1], x[j, 2]]) - xi
            rr = e.dot(e)
            if ti.static(given_r2):
                rr = r2[i, a]
            if rr > 0.0:
                w = 1.0 / rr
                J += w * (ti.Vector([d[j, 0], d[j, 1], d[j, 2]]) - di).outer_product(e)
                count += 1
        n = ti.cast(ti.max(count, 1), ti.f64)
        J /= n
        for a, b in ti.static(ti.ndrange(3, 3)):
            out[i, a, b] = J[a, b]


def _as_index(neighbors: np.ndarray) -> np.ndarray:
    nb = np.asarray(neighbors)
    return np.ascontiguousarray(nb if nb.dtype in (np.int32, np.int64) else nb.astype(np.int64))


def smooth_displacement(d: np.ndarray,  # [N, 3]
                        neighbors: np.ndarray,  # [N, k] indices
                        iters: int,
                        sources: np.ndarray | None = None) -> np.ndarray:  # [P] the neighbour pool -> [N, 3]
    """``iters`` passes of the neighbourhood mean (module docstring)."""
    ensure_taichi()
    d = np.ascontiguousarray(d, dtype=np.float64)
    nb = _as_index(neighbors)
    n = len(d)
    every = np.arange(n, dtype=nb.dtype)
    pool = None if sources is None or len(sources) == n else np.ascontiguousarray(sources, dtype=nb.dtype)
    for it in range(iters):
        rows = pool if it + 1 < iters and pool is not None else every
        out = d.copy() if rows is pool else np.empty_like(d)
        if n:
            _mean_rows(d, nb, rows, out)
        d = out
    return d


def displacement_jacobian_pairs(x: np.ndarray,  # [N, 3]
                                d: np.ndarray,  # [N, 3]
                                neighbors: np.ndarray,  # [N, k] indices
                                r2: np.ndarray | None,  # [N, k] squared neighbour distances (0: the particle itself)
                                ) -> np.ndarray:  # -> [N, 3, 3]
    """The displacement Jacobian of eq. 4 from the pair sums (module docstring). ``r2`` None: each
    pair's |x_j - x_i|^2 computed here, as k_nearest computes it (0 for the particle itself)."""
    ensure_taichi()
    x = np.ascontiguousarray(x, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    nb = _as_index(neighbors)
    given = r2 is not None
    r2 = np.ascontiguousarray(r2, dtype=np.float64) if given else np.zeros((1, 1))
    if not (len(x) == len(d) == len(nb)) or (given and nb.shape != r2.shape):
        raise ValueError(f"x {x.shape}, d {d.shape}, neighbors {nb.shape} and r2 {r2.shape} must agree")
    out = np.empty((len(x), 3, 3))
    if len(x):
        _jacobian(x, d, nb, r2, out, given)
    return out


@ti.func
def _sift_down(r2: ti.template(), nb: ti.template(), r, i, base, root, end):
    """Restore the max-heap order of the heap r2[r, base:end] (nb[i] moved along) below its node ``root``."""
    a = root
    n = end - base
    while 2 * a + 1 < n:
        c = 2 * a + 1
        if c + 1 < n and r2[r, base + c + 1] > r2[r, base + c]:
            c += 1
        if r2[r, base + c] > r2[r, base + a]:
            r2[r, base + a], r2[r, base + c] = r2[r, base + c], r2[r, base + a]
            nb[i, base + a], nb[i, base + c] = nb[i, base + c], nb[i, base + a]
            a = c
        else:
            break


@ti.func
def _cell_range(cell, dims: ti.template(), cell_start: ti.template()):
    """The sorted pool points [first, end) of grid cell ``cell`` (z, y, x); empty outside the grid."""
    first, end = 0, 0
    if 0 <= cell[0] < dims[0] and 0 <= cell[1] < dims[1] and 0 <= cell[2] < dims[2]:
        at = (cell[0] * dims[1] + cell[1]) * dims[2] + cell[2]
        first, end = cell_start[at], cell_start[at + 1]
    return first, end


@ti.func
def _row_range(corner, o, block: ti.template(), dims: ti.template(), cell_start: ti.template()):
    """The sorted pool points [first, end) of row ``o`` (0 .. block^2 - 1) of the block of
    block^3 cells from cell ``corner``: its cells within the grid, contiguous in the cell order (x
    last), so one range in the order the cells would be scanned one by one."""
    z, y = corner[0] + o // block, corner[1] + o % block
    first, end = 0, 0
    if 0 <= z < dims[0] and 0 <= y < dims[1]:
        row = (z * dims[1] + y) * dims[2]
        first = cell_start[row + ti.max(corner[2], 0)]
        end = cell_start[row + ti.min(corner[2] + block - 1, dims[2] - 1) + 1]
    return first, end


@ti.func
def _cell_gap2(xi, cell, lo: ti.template(), h):
    """The squared distance from x_i to grid cell ``cell``'s box (0 inside it): no point of the
    cell is nearer (to round-off: _CELL_GAP_SLACK)."""
    g2 = ti.f64(0.0)
    for a in ti.static(range(3)):
        below = lo[a] + cell[a] * h
        g = ti.max(below - xi[a], xi[a] - (below + h), 0.0)
        g2 += g * g
    return g2


@ti.func
def _cell_of(xi, lo: ti.template(), dims: ti.template(), h):
    c = ti.Vector([0, 0, 0])
    for a in ti.static(range(3)):
        c[a] = ti.min(ti.max(ti.cast(ti.floor((xi[a] - lo[a]) / h), ti.i32), 0), dims[a] - 1)
    return c


@ti.func
def _block_corner(xi, c, lo: ti.template(), h, block: ti.template()):
    """The first cell of x_i's block of block^3 cells: centred on its cell c (block odd), or with c
    among the middle two on each axis, on the side of the half of c that holds x_i (block even:
    x_i then lies at least block / 2 - 1/2 cells inside each face)."""
    corner = c - block // 2
    if ti.static(block % 2 == 0):
        for a in ti.static(range(3)):
            if xi[a] - (lo[a] + c[a] * h) >= 0.5 * h:
                corner[a] += 1
    return corner


@ti.func
def _block_reach2(xi, corner, lo: ti.template(), dims: ti.template(), h, block: ti.template()):
    """R_b^2 of x_i's block of block^3 cells from cell ``corner``: the squared distance to the
    block's nearest face with cells beyond it (no point outside the block is nearer), at most the
    block's farthest corner's (every point of the block is within it)."""
    bound = ti.f64(1e300)
    far = ti.f64(0.0)
    for a in ti.static(range(3)):
        below = xi[a] - (lo[a] + corner[a] * h)
        above = lo[a] + (corner[a] + block) * h - xi[a]
        far += ti.max(below, above) ** 2
        if corner[a] > 0:
            bound = ti.min(bound, below)
        if corner[a] + block < dims[a]:
            bound = ti.min(bound, above)
    return ti.min(bound * bound, far) if bound < 1e300 else far


@ti.func
def _kth_bin(nb: ti.template(), i, k):
    """The histogram bin (in row i's slots) holding the k-th nearest point, and how many points
    the bins before it hold."""
    kb = 0
    m0 = 0
    for b in range(k):
        if m0 + nb[i, b] >= k:
            kb = b
            break
        m0 += nb[i, b]
    return kb, m0


@ti.kernel
def _k_nearest_block(x: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3] the queries
                     pts: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [P, 3] the pool, sorted by cell
                     ids: ti.types.ndarray(ndim=1),  # [P] each sorted pool point's index into x
                     cell_start: ti.types.ndarray(ndim=1),  # [C + 1] first sorted point of each cell
                     lo: ti.types.ndarray(dtype=ti.f64, ndim=1),  # [3] the grid's corner
                     dims: ti.types.ndarray(ndim=1),  # [3] cells per axis
                     h: ti.f64,  # the cells' side
                     row0: ti.i32,  # the first query of this chunk
                     nb: ti.types.ndarray(ndim=2),  # [N, k] out: neighbour indices
                     r2: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [R, k] out: squared distances of rows row0..
                     cand_r2: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [R, M] scratch: the candidates' r2
                     cand_at: ti.types.ndarray(ndim=2),  # [R, M] scratch: the candidates' sorted pool rows
                     settled: ti.types.ndarray(ndim=1),  # [N] out: 1 where the row is written
                     block: ti.template()):  # cells per axis of a query's block (BLOCK_CELLS)
    """K_i from x_i's block of block^3 cells alone (_block_corner), where it settles it: the points of the block
    within R_b of x_i (R_b: the distance to the block's nearest face with cells beyond it, so no
    point outside is nearer) number at least k. A histogram of their r2 in k bins over [0, R_b^2] finds the
    bin holding the k-th; a second pass writes every point below that bin and keeps the nearest
    of that bin's in a max-heap over the row's remaining slots. The row is in no particular order.
    The first scan keeps its candidates (the points within R_b, about a quarter of the block's) in
    scan order where fewer than M, so the histogram and the second pass read them instead of scanning
    the block again (the same row); a row with more scans again. Where the candidates are kept,
    the scan and the second pass's points below the k-th's bin go without a branch: each point is
    written to the next free slot, which only a kept one advances (a branch on whether a point is
    within the reach, taken at random, cost about a sixth of the search)."""
    k = nb.shape[1]
    cap_cand = cand_r2.shape[1]
    for r in range(ti.min(r2.shape[0], x.shape[0] - row0)):
        i = row0 + r
        xi = ti.Vector([x[i, 0], x[i, 1], x[i, 2]])
        corner = _block_corner(xi, _cell_of(xi, lo, dims, h), lo, h, block)
        rb2 = _block_reach2(xi, corner, lo, dims, h, block)
        to_bin = k / rb2
        # the first scan keeps every point within the reach as a candidate, in scan order and
        # without a branch (each point is written to the next slot, which only a candidate keeps;
        # the last slot is overwritten by the points after the row's M-th candidate, so a row is
        # taken from its kept candidates only where it has fewer than M)
        n_in = 0
        for o in range(block * block):  # a loop, not unrolled: one copy of the body (the heap's sift is long)
            first, end = _row_range(corner, o, block, dims, cell_start)
            for s in range(first, end):
                e = ti.Vector([pts[s, 0], pts[s, 1], pts[s, 2]]) - xi
                d2 = e.dot(e)
                slot = ti.min(n_in, cap_cand - 1)
                cand_r2[r, slot] = d2
                cand_at[r, slot] = s
                n_in += ti.cast(d2 <= rb2, ti.i32)
        settled[i] = 0
        if n_in >= k:
            # the histogram of the candidates' r2 in k bins, in the row's index slots (a local array
            # indexed at run time would be lowered to a chain of selects); the second pass overwrites them
            for b in range(k):
                nb[i, b] = 0
            if n_in < cap_cand:
                _kept_histogram(nb, cand_r2, r, i, k, n_in, to_bin)
            else:
                _rescan_block(r2, nb, pts, ids, cell_start, dims, corner, xi, rb2, to_bin, r, i, k, 0, 0, block, True)
            kb, m0 = _kth_bin(nb, i, k)
            if n_in < cap_cand:
                _place_kept(r2, nb, cand_r2, cand_at, ids, r, i, k, kb, m0, n_in, to_bin)
            else:
                _rescan_block(r2, nb, pts, ids, cell_start, dims, corner, xi, rb2, to_bin, r, i, k, kb, m0, block, False)
            settled[i] = 1


@ti.func
def _rescan_block(r2: ti.template(), nb: ti.template(), pts: ti.template(), ids: ti.template(),
                  cell_start: ti.template(), dims: ti.template(), corner, xi, rb2, to_bin, r, i, k, kb, m0,
                  block: ti.template(), histogram: ti.template()):
    """Row i's block scanned again, for a row with more candidates than its slots: with
    ``histogram`` each point within the reach counted by its bin in the row's index slots, else
    placed by the second pass (_place, the k-th's bin kb holding the (m0 + 1)-th nearest on)."""
    placed = ti.Vector([0, 0])  # (left, held): rows written below the k-th bin, and in it
    for o in range(block * block):
        first, end = _row_range(corner, o, block, dims, cell_start)
        for s in range(first, end):
            e = ti.Vector([pts[s, 0], pts[s, 1], pts[s, 2]]) - xi
            d2 = e.dot(e)
            if d2 <= rb2:
                if ti.static(histogram):
                    b = ti.min(ti.cast(d2 * to_bin, ti.i32), k - 1)
                    nb[i, b] = nb[i, b] + 1
                else:
                    placed = _place(r2, nb, r, i, k, kb, m0, d2, ids[s], to_bin, placed)


@ti.func
def _kept_histogram(nb: ti.template(), cand_r2: ti.template(), r, i, k, n_in, to_bin):
    """Row i's n_in kept candidates counted by their r2's bin (k bins over [0, R_b^2]) in the
    row's index slots, zeroed before."""
    for q in range(n_in):
        b = ti.min(ti.cast(cand_r2[r, q] * to_bin, ti.i32), k - 1)
        nb[i, b] = nb[i, b] + 1  # not +=: Taichi makes that an atomic add


@ti.func
def _place_kept(r2: ti.template(), nb: ti.template(), cand_r2: ti.template(), cand_at: ti.template(),
                ids: ti.template(), r, i, k, kb, m0, n_in, to_bin):
    """Row i's second pass from its n_in kept candidates: those below the k-th's bin to the row's
    first m0 slots, in scan order and without a branch (a slot is kept by a candidate below the
    bin; one past the last is at most m0, a slot of the heap, filled after this pass), then the
    k-th's bin, a few candidates, into the heap of the remaining slots (_place)."""
    left = 0
    for q in range(n_in):
        d2 = cand_r2[r, q]
        r2[r, left] = d2
        nb[i, left] = ids[cand_at[r, q]]
        left += ti.cast(ti.cast(d2 * to_bin, ti.i32) < kb, ti.i32)
    placed = ti.Vector([m0, 0])  # (left, held)
    for q in range(n_in):
        d2 = cand_r2[r, q]
        if ti.min(ti.cast(d2 * to_bin, ti.i32), k - 1) == kb:
            placed = _place(r2, nb, r, i, k, kb, m0, d2, ids[cand_at[r, q]], to_bin, placed)


@ti.func
def _place(r2: ti.template(), nb: ti.template(), r, i, k, kb, m0, d2, idx, to_bin, placed):
    """Row i's second pass, one candidate (r2 d2, pool index idx) of the block: below the k-th's
    bin it takes the next slot; in that bin it fills the heap of the row's last k - m0 slots, then
    replaces its largest where nearer. Returns the updated (left, held)."""
    left, held = placed[0], placed[1]
    cap = k - m0
    b = ti.min(ti.cast(d2 * to_bin, ti.i32), k - 1)
    if b < kb:
        r2[r, left] = d2
        nb[i, left] = idx
        left += 1
    elif b == kb:
        if held < cap:
            r2[r, m0 + held] = d2
            nb[i, m0 + held] = idx
            held += 1
            if held == cap:
                for q in range(cap // 2):
                    _sift_down(r2, nb, r, i, m0, cap // 2 - 1 - q, k)
        elif d2 < r2[r, m0]:
            r2[r, m0] = d2
            nb[i, m0] = idx
            _sift_down(r2, nb, r, i, m0, 0, k)
    return ti.Vector([left, held])


@ti.kernel
def _k_nearest_rings(x: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [N, 3] the queries
                     rows: ti.types.ndarray(ndim=1),  # [R] the queries to answer
                     pts: ti.types.ndarray(dtype=ti.f64, ndim=2),  # [P, 3] the pool, sorted by cell
                     ids: ti.types.ndarray(ndim=1),  # [P] each sorted pool point's index into x
                     cell_start: ti.types.ndarray(ndim=1),  # [C + 1] first sorted point of each cell
                     lo: ti.types.ndarray(dtype=ti.f64, ndim=1),  # [3] the grid's corner
                     dims: ti.types.ndarray(ndim=1),  # [3] cells per axis
                     h: ti.f64,  # the cells' side
                     row0: ti.i32,  # the first query of this chunk
                     nb: ti.types.ndarray(ndim=2),  # [N, k] out: neighbour indices, nearest first
                     r2: ti.types.ndarray(dtype=ti.f64, ndim=2)):  # [R, k] out: squared distances of rows row0..
    """K_i for any query: cells are scanned in rings r = 0, 1, ... around x_i's cell, the k nearest
    so far in a max-heap, until the heap is full and its largest r2 is no more than the squared
    distance from x_i to the scanned block's nearest face with cells beyond it (every point
    outside is farther), or the block covers the grid. The row ends sorted, nearest first."""
    k = nb.shape[1]
    for t in range(rows.shape[0]):
        i = rows[t]
        r = i - row0
        xi = ti.Vector([x[i, 0], x[i, 1], x[i, 2]])
        c = _cell_of(xi, lo, dims, h)
        filled = 0
        ring = 0
        done = False
        while not done:
            for dz, dy, dx in ti.ndrange((-ring, ring + 1), (-ring, ring + 1), (-ring, ring + 1)):
                if ti.max(ti.abs(dz), ti.abs(dy), ti.abs(dx)) == ring:
                    cell = c + ti.Vector([dz, dy, dx])
                    first, end = _cell_range(cell, dims, cell_start)
                    # a full heap takes no point of a cell farther than its largest r2: the heap
                    # ends the same without scanning it
                    if filled == k and _cell_gap2(xi, cell, lo, h) > r2[r, 0] * ti.f64(1.0 + _CELL_GAP_SLACK):
                        end = first
                    for s in range(first, end):
                        e = ti.Vector([pts[s, 0], pts[s, 1], pts[s, 2]]) - xi
                        d2 = e.dot(e)
                        if filled < k:  # fill, then heapify once full
                            r2[r, filled] = d2
                            nb[i, filled] = ids[s]
                            filled += 1
                            if filled == k:
                                for q in range(k // 2):
                                    _sift_down(r2, nb, r, i, 0, k // 2 - 1 - q, k)
                        elif d2 < r2[r, 0]:
                            r2[r, 0] = d2
                            nb[i, 0] = ids[s]
                            _sift_down(r2, nb, r, i, 0, 0, k)
            bound = ti.f64(1e300)
            covered = True
            for a in ti.static(range(3)):
                if c[a] - ring > 0:
                    bound = ti.min(bound, xi[a] - (lo[a] + (c[a] - ring) * h))
                    covered = False
                if c[a] + ring < dims[a] - 1:
                    bound = ti.min(bound, lo[a] + (c[a] + ring + 1) * h - xi[a])
                    covered = False
            if covered or (filled == k and r2[r, 0] <= bound * bound):
                done = True
            ring += 1
        for q in range(k - 1):  # heap sort: ascending r2
            end = k - 1 - q
            r2[r, 0], r2[r, end] = r2[r, end], r2[r, 0]
            nb[i, 0], nb[i, end] = nb[i, end], nb[i, 0]
            _sift_down(r2, nb, r, i, 0, 0, end)


def k_nearest(x: np.ndarray,  # [N, 3]
              source: np.ndarray,  # [P] indices into x the neighbours are drawn from
              k: int,
              cell_scale: float = CELL_SCALE,
              with_r2: bool = True,
              chunk: int = 1 << 13,
              candidates: int = BLOCK_CANDIDATES,
              block: int = BLOCK_CELLS) -> tuple[np.ndarray, np.ndarray | None]:  # -> [N, k] indices, [N, k] r2
    """Each particle's k nearest particles of ``source``, in no particular order, and their squared
    distances, 0 for the particle itself (module docstring; plasticity.nearest_neighbours is the
    KD-tree reference). Indices are int32 below 2^31 particles. ``cell_scale``: the cells' side in
    k-th-neighbour radii (estimated from the pool's density); any value gives the same answer.
    ``with_r2`` False: r2 is None, and the distances are kept for ``chunk`` rows at a time only
    (displacement_jacobian_pairs recomputes them: 241 MB fewer at 471K particles, k = 64).
    ``candidates``: the slots for a row's block candidates, which the first scan keeps for the
    second (a row with as many or more scans its block again; any value gives the same answer). ``block``: the
    cells per axis of the block a query scans first (any value gives the same answer)."""
    ensure_taichi()
    x = np.ascontiguousarray(x, dtype=np.float64)
    source = np.asarray(source)
    n, p = len(x), len(source)
    if not 1 <= k <= p:
        raise ValueError(f"k must be in 1..{p} (the pool's size), got {k}")
    index = np.int32 if n < np.iinfo(np.int32).max else np.int64
    nb = np.empty((n, k), dtype=index)
    r2 = np.empty((n, k)) if with_r2 else None
    if n == 0:
        return nb, r2
    pts = x[source]
    lo = x.min(axis=0)
    extent = np.maximum(x.max(axis=0) - lo, 1e-12)
    # the k-th neighbour's radius from the pool's density in the cells it occupies (a coarse
    # grid first, then one of about that radius); at most ~2 cells per pool point
    h = float(extent.max()) / max(1.0, np.ceil(p ** (1 / 3)))
    for _ in range(2):
        occupied = len(np.unique(np.floor((pts - lo) / h).astype(np.int64) @ np.array([1 << 42, 1 << 21, 1])))
        h = (3.0 * k * occupied * h ** 3 / (4.0 * np.pi * p)) ** (1 / 3)
    h = max(cell_scale * h, float((np.prod(extent) / (2.0 * p)) ** (1 / 3)))
    dims = np.maximum(1, np.ceil(extent / h).astype(np.int64))
    cell = np.minimum(np.floor((pts - lo) / h).astype(np.int64), dims - 1)
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    cell_start = np.zeros(int(np.prod(dims)) + 1, dtype=index)
    np.cumsum(np.bincount(key, minlength=len(cell_start) - 1), out=cell_start[1:])
    grid = (np.ascontiguousarray(pts[order]), np.ascontiguousarray(source[order].astype(index)), cell_start, lo,
            dims.astype(np.int32), h)
    settled = np.empty(n, dtype=np.int32)
    # on a GPU each launch copies the NumPy arguments there and back: one launch, no kept candidates
    on_device = taichi_state()["arch"] != "cpu"
    step = n if on_device else max(1, int(chunk))
    keep = 1 if on_device else max(1, int(candidates))
    scratch = None if with_r2 else np.empty((min(step, n), k))
    kept = (np.empty((min(step, n), keep)), np.empty((min(step, n), keep), dtype=index))
    for row0 in range(0, n, step):
        rows_r2 = r2[row0:row0 + step] if with_r2 else scratch  # a chunk's rows of r2 are contiguous
        _k_nearest_block(x, *grid, row0, nb, rows_r2, *kept, settled, int(block))
        rest = np.flatnonzero(settled[row0:row0 + step] == 0).astype(index) + row0
        if len(rest):
            _k_nearest_rings(x, rest, *grid, row0, nb, rows_r2)
    return nb, r2
