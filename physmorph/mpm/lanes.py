"""Scatter lanes: the particle loops that add into the grid (P2G, the reverse of G2P) without
atomic adds on the CPU (paper section 4, "Physics rollout": the transfers' sums
m_I = sum_p w_Ip m_p and their adjoints).

On the CPU a float atomic add is a compare-and-swap loop: the 108 adds a particle of P2G took
~80 % of the kernel (benchmarks/bench_roofline.py) and cost about three times a plain add even
on one thread. So each CPU thread scatters into a copy of the grid of its own (a lane) with plain
adds, and the pass over the grid that follows (the grid update's store, the grid's adjoint)
sums the lanes in a fixed order and zeroes them. The sums are then the same on every run (the
order of atomic adds from two threads is not) and, on one thread, those of the atomic loop.

Why a lane is never written by two threads at once: the particle loop runs over
``blocks = LANE_BLOCK x lanes`` chunks of consecutive particles, chunk c on lane
c // LANE_BLOCK, and Taichi's CPU range-for hands a thread whole tasks of LANE_BLOCK
consecutive iterations (its adaptive block size is max(512, items / (32 threads)), at most 1024,
which is 512 for this range; the loop also asks for it). A thread may run several tasks one
after the other, never part of one. tests/mpm/test_mpm_lanes.py checks the sums against one
thread's on many particles, which would fail if tasks were split otherwise. On a GPU the loops
keep their atomic adds (fast there), one lane.
"""

import taichi as ti
from taichi.lang import impl

from physmorph.base import taichi_runtime  # noqa: F401  (Taichi's fast class test, before the kernels below)

# iterations of a Taichi CPU range-for task for a range of 512 x threads (see above)
LANE_BLOCK = 512


def cpu_threads() -> int:
    """The thread count of the process's Taichi runtime (its cpu_max_num_threads)."""
    return max(1, int(impl.current_cfg().cpu_max_num_threads))


@ti.data_oriented
class ScatterLanes:
    """How a particle loop of n particles is split into lanes, and the lane-wise add."""

    def __init__(self, n: int, on_cpu: bool):
        self.n = int(n)
        self.private = bool(on_cpu)  # a compile-time constant of every kernel that scatters
        self.count = cpu_threads() if on_cpu else 1
        self.blocks = LANE_BLOCK * self.count

    def grid_field(self, dtype, res: int, components: int = 1):
        """A [lanes, res, res, res] copy of a grid field (zero; None on a GPU: no lanes)."""
        if not self.private:
            return None
        shape = (self.count, res, res, res)
        return ti.field(dtype, shape=shape) if components == 1 else ti.types.vector(components, dtype).field(shape=shape)

    @ti.func
    def first(self, c):
        """The first particle of chunk c (chunks of n / blocks particles, in order)."""
        return ti.cast((ti.cast(c, ti.i64) * self.n) // self.blocks, ti.i32)

    @ti.func
    def add(self, lanes: ti.template(), grid: ti.template(), lane, I, value):
        """grid[I] += value: into the lane's copy with a plain add (CPU), or atomically (GPU)."""
        if ti.static(self.private):
            lanes[lane, I[0], I[1], I[2]] = lanes[lane, I[0], I[1], I[2]] + value
        else:
            grid[I] += value

    @ti.func
    def add_mass_momentum(self, lanes: ti.template(), grid_mv: ti.template(), grid_m: ti.template(), lane, I,
                          mv, m):
        """grid_mv[I] += mv and grid_m[I] += m: on the CPU one 4-vector (mv, m) into the lane's
        copy of the packed grid (one address and one 16-byte line touched, not two), on a GPU two
        atomic adds."""
        if ti.static(self.private):
            lanes[lane, I[0], I[1], I[2]] = lanes[lane, I[0], I[1], I[2]] + ti.Vector([mv[0], mv[1], mv[2], m])
        else:
            grid_mv[I] += mv
            grid_m[I] += m

    @ti.func
    def lane_sum(self, lanes: ti.template(), I):
        """The sum of node I over the lanes in lane order, each lane's entry zeroed (CPU only)."""
        total = lanes[0, I[0], I[1], I[2]]
        lanes[0, I[0], I[1], I[2]] = ti.zero(total)
        for lane in range(1, self.count):
            total += lanes[lane, I[0], I[1], I[2]]
            lanes[lane, I[0], I[1], I[2]] = ti.zero(total)
        return total

    @ti.func
    def collect(self, lanes: ti.template(), grid: ti.template(), I):
        """The sum of node I over the lanes in lane order (each lane's entry zeroed), or grid[I]
        where there are no lanes."""
        total = grid[I]
        if ti.static(self.private):
            total = self.lane_sum(lanes, I)
        return total

    @ti.func
    def collect_mass_momentum(self, lanes: ti.template(), grid_mv: ti.template(), grid_m: ti.template(), I):
        """(m_I, mv_I): the packed lanes' sum (add_mass_momentum), or the grids where there are no lanes."""
        m, mv = grid_m[I], grid_mv[I]
        if ti.static(self.private):
            total = self.lane_sum(lanes, I)
            m, mv = total[3], ti.Vector([total[0], total[1], total[2]])
        return m, mv
