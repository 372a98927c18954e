"""Block-level helpers for kernels that run one CUDA block per filter (``wp.launch_tiled``) and the same code as one
thread per filter on the CPU: a barrier, and the share of a loop's pieces each thread does."""

import warp as wp


@wp.func_native("""
#if defined(__CUDA_ARCH__)
__syncthreads();
#endif
""")
def block_sync():
    """A barrier of the CUDA block: the block's writes before it (shared or global memory) are seen after it.
    Nothing on the CPU, where a block is one thread. Every thread of the block must reach it."""
    ...


@wp.func
def span(sh: int, piece: int, lo: int, hi: int):
    """The pieces ``[start, stop)`` of ``[lo, hi)`` a thread does: all of them on the CPU (``sh`` = 0, one thread per
    filter), else (a CUDA block per filter) the lane's own piece ``piece`` when it is in range. The lanes then run
    one loop body side by side (a branch per lane would run them one after the other)."""
    if sh == 0:
        return lo, hi
    if piece >= lo and piece < hi:
        return piece, piece + 1
    return 0, 0
