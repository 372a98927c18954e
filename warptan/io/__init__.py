"""Flight-log layer: the log format (:mod:`~warptan.io.flightlog`), CSV tables (:mod:`~warptan.io.logcsv`) and ROS
bags (:mod:`~warptan.io.rosbag`). Imports the layers below (common, terrain, nav, sensing, filter); replaying a log
through the filter is simulation (:mod:`warptan.sim.replay`)."""
