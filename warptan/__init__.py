"""warptan: terrain-aided navigation with a point-cloud sensor, as kernels on NVIDIA Warp.

Conventions (design notes §1), used everywhere in the package:

* Navigation frame n: local-level NED (x north, y east, z down), metres, flat earth, origin at the
  terrain's reference point; gravity ``g_n = [0, 0, 9.80665]`` m/s².
* Body frame b = sensor frame s: FRD (x forward, y right, z down); a nadir ray is ``+z``.
* Attitude: Hamilton unit quaternion, scalar first ``[w, x, y, z]``, ``q = q_nb``; ``R(q)`` maps body to
  navigation vectors; Euler angles are ZYX (``R = Rz(yaw) Ry(pitch) Rx(roll)``).
* Terrain height ``h(N, E)`` is metres above MSL, positive up; a point ``p`` is on the terrain when
  ``p_z = -h(p_x, p_y)``.
* SI units inside; degrees, deg/h, mg, µg/√Hz only at the configuration boundary.
* float32 on the device for kernels; float64 on the host for the INS and the filter covariance.

``import warptan`` needs only numpy and warp; rasterio, trimesh and matplotlib are imported where used. The public
names are loaded on first use (``warptan.run_scenario``, ``from warptan import Terrain``).
"""

import importlib

_EXPORTS = {
    "FilterError": "warptan.checks",
    "FilterWarning": "warptan.checks",
    "resolve_device": "warptan.device",
    "FilterConfig": "warptan.filter.config",
    "MarginalizedParticleFilter": "warptan.filter.mpf",
    "InitialErrors": "warptan.filter.prior",
    "frames": "warptan.nav",
    "IMU_GRADES": "warptan.nav.imu",
    "ImuModel": "warptan.nav.imu",
    "Ins": "warptan.nav.ins",
    "NavState": "warptan.nav.ins",
    "Climb": "warptan.nav.trajectory",
    "Orbit": "warptan.nav.trajectory",
    "Straight": "warptan.nav.trajectory",
    "Trajectory": "warptan.nav.trajectory",
    "Turn": "warptan.nav.trajectory",
    "OutputError": "warptan.outputs",
    "Likelihood": "warptan.sensing.likelihood",
    "AltimeterModel": "warptan.sensing.measurement",
    "RaycastModel": "warptan.sensing.measurement",
    "SlidingModel": "warptan.sensing.measurement",
    "make_model": "warptan.sensing.measurement",
    "AltimeterReading": "warptan.sensing.sensors",
    "Barometer": "warptan.sensing.sensors",
    "PointCloud": "warptan.sensing.sensors",
    "PointCloudSensor": "warptan.sensing.sensors",
    "RadarAltimeter": "warptan.sensing.sensors",
    "ScanPattern": "warptan.sensing.sensors",
    "Campaign": "warptan.sim.campaign",
    "CampaignError": "warptan.sim.campaign",
    "write_campaign": "warptan.sim.campaign_report",
    "run_campaign": "warptan.sim.campaign_run",
    "run_filter": "warptan.sim.runner",
    "ScenarioError": "warptan.sim.scenario_config",
    "run_scenario": "warptan.sim.scenarios",
    "run_scenario_batch": "warptan.sim.scenarios",
    "Terrain": "warptan.terrain.grid",
    "TerrainError": "warptan.terrain.raster",
    "RayCaster": "warptan.terrain.raycast",
    "raycast": "warptan.terrain.raycast",
}
"""Where each public name lives: imported on first use (PEP 562), so that ``import warptan`` and ``warptan --help`` do
not load Warp and every kernel module first."""


__version__ = "0.2.0"

__all__ = sorted([*_EXPORTS, "__version__"])


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'warptan' has no attribute {name!r}")
    found = importlib.import_module(module)
    # (a submodule, frames, is an attribute of its package once imported)
    value = getattr(found, name) if hasattr(found, name) else importlib.import_module(f"{module}.{name}")
    globals()[name] = value  # (the next access does not come here)
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
