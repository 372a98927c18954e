"""Terrain layer: DEM files (:mod:`~warptan.terrain.raster`), the height grid and its mesh
(:mod:`~warptan.terrain.grid`), ray casting (:mod:`~warptan.terrain.raycast`) and world models (a map that is not
the world, :mod:`~warptan.terrain.world`). Imports only the common modules and :mod:`warptan.kernels`."""
