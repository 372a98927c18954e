"""Block-level helpers for kernels that run one CUDA block per filter (``wp.launch_tiled``) and the same code as one
thread per filter on the CPU: a barrier, the share of a loop's pieces each thread does, and a warp's sum and maximum
by shuffles (the same bits in every lane)."""

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


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return 1;
#else
return 0;
#endif
""")
def on_cuda() -> int:
    """1 in code compiled for CUDA (a block per filter whose lanes share the work), 0 on the CPU (one thread)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __shfl_xor_sync(0xffffffffu, v, mask);
#else
return v;
#endif
""")
def shfl_xor(v: wp.float64, mask: int) -> wp.float64:
    """The value of lane ``lane ^ mask`` of the warp (CUDA; every lane of the warp must call it); ``v`` on the CPU."""
    ...


@wp.func
def warp_sum(x: wp.float64) -> wp.float64:
    """The sum of ``x`` over the warp's 32 lanes, by an xor butterfly: lane l adds lane ``l ^ 16``, then ``l ^ 8`` …
    ``l ^ 1``. Each addition's two terms are the same on both lanes, only swapped (exact in IEEE), so every lane
    ends with the same bits: the pairwise tree ``((x_0 + x_16) + (x_8 + x_24)) + …`` (CUDA; ``x`` on the CPU)."""
    y = x
    for s in range(5):
        y = y + shfl_xor(y, 16 >> s)
    return y


@wp.func
def warp_max(x: wp.float64) -> wp.float64:
    """The largest ``x`` of the warp's 32 lanes, every lane (CUDA; ``x`` on the CPU)."""
    y = x
    for s in range(5):
        y = wp.max(y, shfl_xor(y, 16 >> s))
    return y
