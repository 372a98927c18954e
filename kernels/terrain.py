"""Terrain kernels: the height grid as a Warp struct and its samplers (design notes §2).

The grid has posts at ``north = n0 + i*dn``, ``east = e0 + j*de`` (``i`` grows north, ``j`` east);
``heights[i, j]`` is metres above MSL (positive up), NaN where the DEM has no data. A *cell* is the
square between posts ``(i, j)`` and ``(i+1, j+1)``; a cell is valid only when its four posts are valid.

Two interpolants of the same posts are offered:

* :func:`grid_bilinear` — bilinear inside a cell (the sampler of the sliding-grid and altimeter models);
* :func:`grid_surface` — the piecewise-planar surface of the triangulated grid (two triangles per cell,
  diagonal from post ``(i, j)`` to ``(i+1, j+1)``), i.e. exactly the surface that ``wp.Mesh`` holds and
  that ray casts hit.

Both agree on posts and along cell edges. Off the grid, on a NaN coordinate, or in an invalid cell they
return NaN; they never clamp to the border.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

BLOCK_CELLS = wp.constant(8)
"""Cells per side of a :attr:`HeightGrid.block_top` block."""


@wp.func
def is_nan(x: float) -> bool:
    """``x`` is NaN, as ``x != x`` inline: ``wp.isnan`` is an out-of-line call on the CPU (Warp's ``_wp_isnan`` of a
    double), whose saved and restored registers cost the sliding kernel's loop, two tests a point, ~15 %."""
    return x != x


@wp.func
def is_finite(x: float) -> bool:
    """``x`` is neither NaN nor infinite, inline (``x - x`` is 0 exactly for a finite ``x``, NaN otherwise; see
    :func:`is_nan`)."""
    return x - x == 0.0


@wp.struct
class HeightGrid:
    """A regular height grid on the device (all lengths in metres, NED horizontal coordinates)."""

    heights: wp.array2d(dtype=wp.float32)
    """(rows, cols) post heights above MSL in m, positive up; NaN = nodata."""
    cell_max: wp.array2d(dtype=wp.float32)
    """(rows-1, cols-1) highest post of each cell in m; +inf for a cell with a nodata post."""
    n0: wp.float32
    """North coordinate of post row 0 in m."""
    e0: wp.float32
    """East coordinate of post column 0 in m."""
    dn: wp.float32
    """Post spacing north in m (> 0)."""
    de: wp.float32
    """Post spacing east in m (> 0)."""
    h_min: wp.float32
    """Lowest valid post in m."""
    h_max: wp.float32
    """Highest valid post in m."""
    inv_dn: wp.float32
    """``1 / dn`` in 1/m: the gradients multiply by it (a division sat on the CPU sliding kernel's per-point path from
    the slope to the point's σ). The cell is still located by dividing: exactly on the last post a product may
    round past the grid's edge."""
    inv_de: wp.float32
    """``1 / de`` in 1/m."""
    block_top: wp.array2d(dtype=wp.float32)
    """Per block of ``BLOCK_CELLS`` × ``BLOCK_CELLS`` cells, the highest post (m) of it and its eight neighbours; +inf
    where one of those cells has a nodata post (:meth:`warptan.terrain.grid.Terrain.grid`)."""


@wp.func
def grid_bilinear(grid: HeightGrid, north: float, east: float) -> float:
    """Bilinear height in m at ``(north, east)``; NaN off the grid or in a cell with a nodata post."""
    u = (north - grid.n0) / grid.dn
    v = (east - grid.e0) / grid.de
    rows = grid.heights.shape[0]
    cols = grid.heights.shape[1]
    # Written so that NaN coordinates fail every comparison and land in the "off grid" branch.
    if u >= 0.0 and u <= float(rows - 1) and v >= 0.0 and v <= float(cols - 1):
        i = wp.min(int(u), rows - 2)  # int() truncates, = floor for u >= 0
        j = wp.min(int(v), cols - 2)
        fu = u - float(i)
        fv = v - float(j)
        # NaN posts propagate (0 * NaN = NaN), which is what marks the whole cell invalid.
        return (1.0 - fu) * ((1.0 - fv) * grid.heights[i, j] + fv * grid.heights[i, j + 1]) + fu * (
            (1.0 - fv) * grid.heights[i + 1, j] + fv * grid.heights[i + 1, j + 1])
    return wp.nan


@wp.func
def grid_cell(grid: HeightGrid, north: float, east: float):
    """The cell under ``(north, east)``: (inside the grid, fractions ``fu`` north and ``fv`` east within the cell,
    corner heights ``h00, h10, h01, h11``); off the grid (or a NaN coordinate) ``inside`` is False."""
    u = (north - grid.n0) / grid.dn
    v = (east - grid.e0) / grid.de
    rows = grid.heights.shape[0]
    cols = grid.heights.shape[1]
    if u >= 0.0 and u <= float(rows - 1) and v >= 0.0 and v <= float(cols - 1):
        i = wp.min(int(u), rows - 2)
        j = wp.min(int(v), cols - 2)
        return (True, u - float(i), v - float(j), grid.heights[i, j], grid.heights[i + 1, j], grid.heights[i, j + 1],
                grid.heights[i + 1, j + 1])
    return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0


@wp.func
def grid_surface(grid: HeightGrid, north: float, east: float) -> float:
    """Height in m of the triangulated surface (the mesh) at ``(north, east)``; NaN where invalid."""
    inside, fu, fv, h00, h10, h01, h11 = grid_cell(grid, north, east)
    if not inside or is_nan(h00 + h10 + h01 + h11):
        return wp.nan
    if fu >= fv:
        # triangle (i,j) (i+1,j) (i+1,j+1)
        return h00 + fu * (h10 - h00) + fv * (h11 - h10)
    # triangle (i,j) (i,j+1) (i+1,j+1)
    return h00 + fv * (h01 - h00) + fu * (h11 - h01)


@wp.func
def grid_height(grid: HeightGrid, surface: int, north: float, east: float) -> float:
    """Bilinear height (``surface == 0``) or triangulated-surface height (``surface == 1``), NaN = invalid."""
    if surface == 0:
        return grid_bilinear(grid, north, east)
    return grid_surface(grid, north, east)


@wp.func
def grid_gradient(grid: HeightGrid, surface: int, north: float, east: float) -> wp.vec2:
    """``(∂h/∂north, ∂h/∂east)`` of the bilinear (``surface == 0``) or triangulated surface at ``(north, east)``;
    NaN where the height is invalid."""
    inside, fu, fv, h00, h10, h01, h11 = grid_cell(grid, north, east)
    if not inside:
        return wp.vec2(wp.nan, wp.nan)
    if surface == 0:
        return wp.vec2(((1.0 - fv) * (h10 - h00) + fv * (h11 - h01)) * grid.inv_dn,
                       ((1.0 - fu) * (h01 - h00) + fu * (h11 - h10)) * grid.inv_de)
    if fu >= fv:
        return wp.vec2((h10 - h00) * grid.inv_dn, (h11 - h10) * grid.inv_de)
    return wp.vec2((h11 - h01) * grid.inv_dn, (h01 - h00) * grid.inv_de)


@wp.func
def grid_height_gradient(grid: HeightGrid, surface: int, north: float, east: float):
    """(:func:`grid_height`, :func:`grid_gradient`) from one read of the cell's four posts (the same expressions;
    NaN height and gradient where invalid)."""
    inside, fu, fv, h00, h10, h01, h11 = grid_cell(grid, north, east)
    if not inside:
        return float(wp.nan), wp.vec2(wp.nan, wp.nan)
    if surface == 0:
        h = (1.0 - fu) * ((1.0 - fv) * h00 + fv * h01) + fu * ((1.0 - fv) * h10 + fv * h11)
        return h, wp.vec2(((1.0 - fv) * (h10 - h00) + fv * (h11 - h01)) * grid.inv_dn,
                          ((1.0 - fu) * (h01 - h00) + fu * (h11 - h10)) * grid.inv_de)
    if is_nan(h00 + h10 + h01 + h11):
        return float(wp.nan), wp.vec2(wp.nan, wp.nan)
    if fu >= fv:
        return h00 + fu * (h10 - h00) + fv * (h11 - h10), wp.vec2((h10 - h00) * grid.inv_dn, (h11 - h10) * grid.inv_de)
    return h00 + fv * (h01 - h00) + fu * (h11 - h01), wp.vec2((h11 - h01) * grid.inv_dn, (h01 - h00) * grid.inv_de)


@wp.kernel
def sample_heights_kernel(
    grid: HeightGrid,
    surface: int,
    north_m: wp.array(dtype=wp.float32),
    east_m: wp.array(dtype=wp.float32),
    heights_out: wp.array(dtype=wp.float32),
):
    """One thread per query point: bilinear (``surface == 0``) or surface height in m (NaN = invalid)."""
    k = wp.tid()
    heights_out[k] = grid_height(grid, surface, north_m[k], east_m[k])
