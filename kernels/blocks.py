"""Reductions over the threads of one thread block, for kernels launched with ``wp.launch_tiled`` as one block per
world (a world's CG, its collision QP). Each is a tile reduction, so each is also a barrier: what the block's
threads wrote before it, every thread reads after it. Every thread gets the result, so a loop whose test reads only
reduced values runs the same on every thread of the block. On the CPU a block is one thread: each returns the
thread's own value, and a kernel written with them runs as a sequential loop would."""

import warp as wp


@wp.func
def block_sum(value: wp.float64):
    return wp.tile_sum(wp.tile(value))[0]


@wp.func
def block_max(value: wp.float64):
    return wp.tile_max(wp.tile(value))[0]


@wp.func
def block_min(value: wp.float64):
    return wp.tile_min(wp.tile(value))[0]


@wp.func
def block_barrier():
    """Every thread of the block waits here for the others."""
    block_sum(wp.float64(0.0))
