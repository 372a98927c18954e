"""Navigation layer: frames and attitude (:mod:`~warptan.nav.frames`), a flight's frame on the Earth
(:mod:`~warptan.nav.geoframe`), IMU models (:mod:`~warptan.nav.imu`), the strapdown INS and its error model
(:mod:`~warptan.nav.ins`), reference trajectories (:mod:`~warptan.nav.trajectory`). Imports the common modules and
the terrain layer."""
