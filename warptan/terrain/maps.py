"""The world a simulated flight sees and the map its filter reads (a scenario's ``[terrain]`` and ``[world]``
tables): :class:`MapSpec` names the DEM and says how the filter's map differs from it; :func:`build_world` makes a
:class:`~warptan.terrain.world.World` from a DEM.

The filter's map is the world unless ``[terrain]`` says otherwise (:meth:`MapSpec.build`): another DEM file of the
same ground (``map_path``, resampled into the world's frame), a coarser grid (``map_spacing_m``, block means), white
post noise (``map_noise_m``, realisation ``map_seed``) and a vertical bias (``map_bias_m``), in that order. Loaded
DEMs and built worlds are cached (a campaign loads each once).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from warptan.terrain.grid import Terrain, TerrainError
from warptan.terrain.world import World, WorldModel

_TERRAIN_CACHE: dict[str, Terrain] = {}
_WORLD_CACHE: dict = {}


@dataclass(frozen=True)
class MapSpec:
    """A scenario's ``[terrain]`` table (validated by :mod:`warptan.sim.scenario_config`)."""

    kind: str
    """A named terrain (:data:`~warptan.terrain.grid.NAMED_TERRAINS`) or ``path`` (the DEM file ``path``)."""
    path: str
    """The DEM file when ``kind = "path"``."""
    map_path: str
    """Another DEM of the same ground as the filter's map (resampled into the world's frame); empty: none."""
    map_noise_m: float
    """White noise added to each post of the map, m (σ)."""
    map_spacing_m: float
    """The map's post spacing (block means of the world's posts), m; 0: the world's."""
    map_bias_m: float
    """The map reads this much higher than the world, m."""
    map_seed: int
    """The map noise's realisation; -1: each run's own seed."""

    @property
    def dem(self) -> str:
        """The spec the world's DEM loads from (a name, a path)."""
        return self.path if self.kind == "path" else self.kind

    @property
    def per_seed(self) -> bool:
        """Noise drawn per seed: every run reads its own map."""
        return bool(self.map_noise_m) and self.map_seed < 0

    def grid_differs(self, truth: Terrain) -> bool:
        """True when the filter's map is not sampled on the world's posts (another file, coarser posts, or a world
        made from the map on a finer grid)."""
        return bool(self.map_path) or coarsening(truth, self.map_spacing_m) != (1, 1) or (
            isinstance(truth, World) and truth.model.refine > 1)

    def build(self, truth: Terrain, seed: int) -> Terrain:
        """The filter's map of the world ``truth`` (``seed``: the run's, for ``map_seed = -1``). A world made from a
        DEM has that DEM as its map.

        Raises:
            TerrainError: ``map_path`` does not load, or ``map_spacing_m`` does not coarsen the map.
        """
        noise, bias = self.map_noise_m, self.map_bias_m
        if isinstance(truth, World):  # the world was made from the DEM: the DEM is the map
            truth = truth.base
        the_map = load_terrain(self.map_path, onto=truth) if self.map_path else truth
        try:
            the_map = the_map.coarsened(*coarsening(the_map, self.map_spacing_m))
        except TerrainError as err:
            raise TerrainError(f"terrain.map_spacing_m = {self.map_spacing_m}: {err}") from None
        if the_map is truth and not noise and not bias:
            return truth
        h = the_map.heights_m + bias
        if noise:
            noise_seed = seed if self.map_seed < 0 else self.map_seed
            h = h + np.random.default_rng([noise_seed, 0x3A9]).normal(0.0, noise, h.shape)
        parts = [p for p, on in ((f"noise {noise:g} m", noise), (f"bias {bias:+g} m", bias)) if on]
        # Noise and bias are deliberate: the map keeps every post (its world passed the plausibility range already).
        return Terrain(h, the_map.n0, the_map.e0, the_map.dn, the_map.de, crs_wkt=the_map.crs_wkt,
                       origin_xy=the_map.origin_xy, valid_range_m=(-math.inf, math.inf),
                       name=the_map.name + (f" ({', '.join(parts)})" if parts else ""),
                       description=the_map.description)


def coarsening(truth: Terrain, spacing_m: float) -> tuple[int, int]:
    """Posts per block along north and east that give about ``spacing_m`` (0: 1, 1)."""
    if not spacing_m:
        return 1, 1
    return max(1, round(spacing_m / truth.dn)), max(1, round(spacing_m / truth.de))


def load_terrain(spec: str | os.PathLike, onto: Terrain | None = None, posts=None) -> Terrain:
    """A DEM by spec (:meth:`~warptan.terrain.grid.Terrain.load`; ``onto``: resampled into that terrain's frame,
    ``posts``: onto a recorded post grid), cached.

    Raises:
        TerrainError: ``terrain 'SPEC' does not load: why``.
    """
    spec = os.fspath(spec)
    key = spec if onto is None else f"{spec} onto {onto.name} {onto.origin_xy} {onto.crs_wkt}"
    if posts is not None:
        key = f"{key} on posts {posts}"
    if key not in _TERRAIN_CACHE:
        try:
            _TERRAIN_CACHE[key] = (Terrain.load(spec, **({} if posts is None else {"posts": posts})) if onto is None
                                   else Terrain.from_raster(spec, onto=onto))
        except (ValueError, FileNotFoundError) as err:
            raise TerrainError(f"terrain {spec!r} does not load: {err}") from None
    return _TERRAIN_CACHE[key]


def build_world(dem: Terrain, model: WorldModel, seed: int) -> Terrain:
    """The world over ``dem``: ``dem`` itself when ``model`` is not active, else its
    :class:`~warptan.terrain.world.World` (``seed``: the run's, used when ``model.seed`` is -1), cached (the last
    few: a world is refine² × the DEM).

    Raises:
        TerrainError: the model does not fit the DEM (a correlation length shorter than a post).
    """
    if not model.active:
        return dem
    key = (id(dem), model, seed if model.seed < 0 else None)
    if key not in _WORLD_CACHE:
        if len(_WORLD_CACHE) >= 4:
            _WORLD_CACHE.pop(next(iter(_WORLD_CACHE)))
        _WORLD_CACHE[key] = (dem, model.build(dem, seed))  # (the DEM held: its id stays its own)
    return _WORLD_CACHE[key][1]
