"""The marginalized particle filter's kernels, by what they do (:mod:`warptan.kernels.mpf` gathers them)."""
