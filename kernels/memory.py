"""Fills and copies of memory as kernels, for what a graph captured on the CPU records: Warp 1.19 records a memset,
fill or copy of host memory with a snapshot of the region it touches (for a saved graph), so every graph that zeroes
an array holds a copy of it; a kernel launch is recorded by reference (warpcloth/tape.py memory_ops_as_kernels)."""

import warp as wp


@wp.kernel
def fill_u64(dst: wp.array(dtype=wp.uint64), value: wp.uint64):
    dst[wp.tid()] = value


@wp.kernel
def fill_u32(dst: wp.array(dtype=wp.uint32), value: wp.uint32):
    dst[wp.tid()] = value


@wp.kernel
def fill_u8(dst: wp.array(dtype=wp.uint8), value: wp.uint8):
    dst[wp.tid()] = value


@wp.kernel
def copy_u64(dst: wp.array(dtype=wp.uint64), src: wp.array(dtype=wp.uint64)):
    i = wp.tid()
    dst[i] = src[i]


@wp.kernel
def copy_u32(dst: wp.array(dtype=wp.uint32), src: wp.array(dtype=wp.uint32)):
    i = wp.tid()
    dst[i] = src[i]


@wp.kernel
def copy_u8(dst: wp.array(dtype=wp.uint8), src: wp.array(dtype=wp.uint8)):
    i = wp.tid()
    dst[i] = src[i]
