"""Filter layer: the marginalized particle filter (:mod:`~warptan.filter.mpf`) and its prior
(:mod:`~warptan.filter.prior`). Imports the common modules, terrain, nav and sensing."""
