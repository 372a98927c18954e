"""Simulation layer: running a filter over a flight (:mod:`~warptan.sim.runner`), the paper's scenarios
(:mod:`~warptan.sim.scenarios`), replaying recorded flights (:mod:`~warptan.sim.replay`), campaigns
(:mod:`~warptan.sim.campaign`), reports and claims (:mod:`~warptan.sim.report`, :mod:`~warptan.sim.claims`). Imports
every layer below; only :mod:`warptan.cli` sits above it."""
