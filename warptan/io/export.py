"""Flight logs made by warptan: a simulated run's inputs written as logs (:func:`logs_from_record`, ``warptan run
--export-log``), and a log's positions, velocities and attitudes carried into another frame (:func:`convert_log`)."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np

from warptan.filter.prior import InitialErrors, prior_sigma
from warptan.io.flightlog import FlightLog
from warptan.nav.geoframe import FrameChange, GeoFrame, corners, frame_change
from warptan.nav.imu import imu_grade
from warptan.sensing.likelihood import Likelihood


def dem_reference(spec) -> tuple[str, str | None]:
    """(the spec a log names its DEM by, the SHA-256 of its file): a DEM file's path made absolute (its ``#band=N``
    kept) with its checksum; a named or synthetic terrain as it is, without one. A relative path had been stored as
    given, so a replay from another folder read another file of that name."""
    from warptan.terrain.grid import NAMED_TERRAINS, terrain_source_file

    text = str(spec)
    file = terrain_source_file(text)
    if file is None or text in NAMED_TERRAINS:
        return text, None
    _, sep, band = text.rpartition("#band=")
    return str(Path(file).resolve()) + (f"#band={band}" if sep and not Path(text).exists() else ""), file_sha256(file)


def file_sha256(path) -> str:
    """The SHA-256 of a file's bytes, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def logs_from_record(record: dict, flight, config: dict, likelihood: Likelihood, total_seeds: list[int],
                     seeds: list[int], terrain_spec: str, terrain=None) -> list[FlightLog]:
    """One :class:`FlightLog` per seed of a simulated batch (``run_filter(record=...)``): the IMU samples, scans or
    altimeter/barometer readings the filter received, the truth, the prior and the run's settings. With a
    georeferenced ``terrain`` (the DEM the flight is over) the log's frame is the geodetic frame at the DEM's NED
    origin (:class:`~warptan.nav.geoframe.GeoFrame`; positions, velocities and attitudes converted into it when the
    DEM's grid is not that tangent frame, e.g. a UTM DEM); without one, the DEM's grid (kind dem-grid)."""
    ie, s = config["initial_error"], config["sensor"]
    terrain_spec, dem_sha256 = dem_reference(terrain_spec)
    geo = GeoFrame.of_terrain(terrain) if terrain is not None else None
    change = None if geo is None else frame_change(terrain, geo, corners(flight.pos_n))
    dem = getattr(terrain, "base", None) or terrain  # a World's: the DEM it was made from, the one the log names
    posts = None  # the DEM's posts, when its grid is the log's frame
    if change is not None and change.identity and dem.crs_wkt == terrain.crs_wkt:
        posts = np.array([dem.n0, dem.e0, dem.dn, dem.de, *dem.heights_m.shape], dtype=np.float64)
    k_total = record["f"].shape[0]
    t_imu = np.asarray(flight.t_s[:k_total], dtype=np.float64)
    t_meas = np.asarray(flight.t_s[np.array(record["epochs"])], dtype=np.float64)
    sigma = prior_sigma(InitialErrors(tuple(ie["pos_m"]), ie["vel_mps"], tuple(ie["att_deg"])),
                        imu_grade(config["imu"]["grade"]))
    logs = []
    for b, (total, seed) in enumerate(zip(total_seeds, seeds, strict=True)):
        nominal0 = record["nominal0"][b]
        bias = record["true_bias"][b][np.minimum(np.arange(k_total + 1), k_total - 1)]
        meas = [epoch[b] for epoch in record["measurements"]]
        kw: dict = {}
        if s["model"] == "altimeter":
            kw.update(alt_t=t_meas, alt_range=np.array([m.range_m for m in meas]),
                      altimeter_sigma_m=s["altimeter_sigma_m"], baro_t=t_meas,
                      baro_alt=np.array([m.baro_alt_m for m in meas]), baro_sigma_m=s["baro_sigma_m"])
        else:
            ranges = np.array([m.ranges_m for m in meas])
            kw.update(scan_t=t_meas, scan_dirs=np.array([m.dirs_s for m in meas]), scan_ranges=ranges,
                      scan_valid=np.isfinite(ranges), range_sigma_m=s["range_sigma_m"])
        settings = {"config": config, "likelihood": dataclasses.asdict(likelihood), "seed": int(total),
                    "scenario_seed": int(seed), "terrain_spec": terrain_spec,
                    **({"dem_sha256": dem_sha256} if dem_sha256 else {})}
        log = FlightLog(
            imu_t=t_imu, imu_f=record["f"][:, b], imu_w=record["w"][:, b], imu_rate_hz=float(flight.rate_hz),
            imu_grade=str(config["imu"]["grade"]), t_end=float(flight.t_s[k_total]), init_t=float(t_imu[0]),
            init_pos=nominal0.pos_n, init_vel=nominal0.vel_n, init_quat=nominal0.quat_nb,
            init_accel_bias=nominal0.accel_bias, init_gyro_bias=nominal0.gyro_bias,
            init_sigma=sigma,
            truth_t=np.asarray(flight.t_s[:k_total + 1], dtype=np.float64), truth_pos=flight.pos_n[:k_total + 1],
            truth_vel=flight.vel_n[:k_total + 1], truth_quat=flight.quat_nb[:k_total + 1],
            truth_accel_bias=bias[:, 0:3], truth_gyro_bias=bias[:, 3:6],
            dem_reference=terrain_spec, dem_posts=posts, settings=settings, name=f"{config['id']}_seed{seed}", **kw)
        logs.append(log if change is None else convert_log(log, change, frame=geo))
    return logs


def convert_log(log: FlightLog, change: FrameChange, frame: GeoFrame | None = None) -> FlightLog:
    """``log`` with its initial state and truth moved by ``change`` (positions point by point, velocities and
    attitudes turned; :mod:`warptan.nav.geoframe`) and its frame set to ``frame``; the sensors' body-frame data are
    unchanged. The identity change returns the same arrays' values (the same bits)."""
    kw: dict = {"frame": frame}
    if not change.identity:
        p0 = log.init_pos[None]
        kw.update(init_pos=change.positions(p0)[0], init_vel=change.vectors(p0, log.init_vel[None])[0],
                  init_quat=change.attitudes(p0, log.init_quat[None])[0])
        if log.has_truth:
            kw.update(truth_pos=change.positions(log.truth_pos), truth_vel=change.vectors(log.truth_pos, log.truth_vel),
                      truth_quat=change.attitudes(log.truth_pos, log.truth_quat))
    return dataclasses.replace(log, **kw)


# ---------------------------------------------------------------------- timeline
