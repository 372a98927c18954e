"""Sensing layer: the simulated sensors (:mod:`~warptan.sensing.sensors`), the measurement models with their
likelihoods (:mod:`~warptan.sensing.measurement`) and the map error learned in flight (:mod:`~warptan.sensing.learner`).
Imports the common modules, terrain and nav."""
