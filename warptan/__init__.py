"""warptan: terrain-aided navigation with a point-cloud sensor, as kernels on NVIDIA Warp.

Conventions (SPEC §1), used everywhere in the package:

* Navigation frame n: local-level NED (x north, y east, z down), metres, flat earth, origin at the
  terrain's reference point; gravity ``g_n = [0, 0, 9.80665]`` m/s².
* Body frame b = sensor frame s: FRD (x forward, y right, z down); a nadir ray is ``+z``.
* Attitude: Hamilton unit quaternion, scalar first ``[w, x, y, z]``, ``q = q_nb``; ``R(q)`` maps body to
  navigation vectors; Euler angles are ZYX (``R = Rz(yaw) Ry(pitch) Rx(roll)``).
* Terrain height ``h(N, E)`` is metres above MSL, positive up; a point ``p`` is on the terrain when
  ``p_z = -h(p_x, p_y)``.
* SI units inside; degrees, deg/h, mg, µg/√Hz only at the configuration boundary.
* float32 on the device for kernels; float64 on the host for the INS and the filter covariance.

``import warptan`` needs only numpy and warp; rasterio, trimesh and matplotlib are imported where used.
"""

from warptan.checks import FilterError, FilterWarning
from warptan.device import resolve_device
from warptan.filter.config import FilterConfig
from warptan.filter.mpf import MarginalizedParticleFilter
from warptan.filter.prior import InitialErrors
from warptan.nav import frames
from warptan.nav.imu import IMU_GRADES, ImuModel
from warptan.nav.ins import Ins, NavState
from warptan.nav.trajectory import Climb, Orbit, Straight, Trajectory, Turn
from warptan.outputs import OutputError
from warptan.sensing.likelihood import Likelihood
from warptan.sensing.measurement import AltimeterModel, RaycastModel, SlidingModel, make_model
from warptan.sensing.sensors import (
    AltimeterReading,
    Barometer,
    PointCloud,
    PointCloudSensor,
    RadarAltimeter,
    ScanPattern,
)
from warptan.sim.campaign import Campaign, CampaignError
from warptan.sim.campaign_report import write_campaign
from warptan.sim.campaign_run import run_campaign
from warptan.sim.runner import run_filter
from warptan.sim.scenario_config import ScenarioError
from warptan.sim.scenarios import run_scenario, run_scenario_batch
from warptan.terrain.grid import Terrain
from warptan.terrain.raster import TerrainError
from warptan.terrain.raycast import RayCaster, raycast

__version__ = "0.2.0"

__all__ = [
    "IMU_GRADES",
    "AltimeterModel",
    "AltimeterReading",
    "Barometer",
    "Campaign",
    "CampaignError",
    "Climb",
    "FilterConfig",
    "FilterError",
    "FilterWarning",
    "ImuModel",
    "InitialErrors",
    "Ins",
    "Likelihood",
    "MarginalizedParticleFilter",
    "NavState",
    "Orbit",
    "OutputError",
    "PointCloud",
    "PointCloudSensor",
    "RadarAltimeter",
    "RayCaster",
    "RaycastModel",
    "ScanPattern",
    "ScenarioError",
    "SlidingModel",
    "Straight",
    "Terrain",
    "TerrainError",
    "Trajectory",
    "Turn",
    "__version__",
    "frames",
    "make_model",
    "raycast",
    "resolve_device",
    "run_campaign",
    "run_filter",
    "run_scenario",
    "run_scenario_batch",
    "write_campaign",
]
