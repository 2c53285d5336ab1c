"""Reductions over one thread block (``wp.launch_tiled``, one block per world). Each is a barrier and returns its
result to every thread, so loops testing reduced values run alike on all; on the CPU a block is one thread, and
each returns that thread's own value."""

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
