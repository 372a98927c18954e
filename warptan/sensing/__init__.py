"""Sensing layer: the simulated sensors (:mod:`~warptan.sensing.sensors`) and the measurement models with their
likelihoods (:mod:`~warptan.sensing.measurement`). Imports the common modules, terrain and nav."""
