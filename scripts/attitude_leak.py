#!/usr/bin/env python3
"""What a correlated map error leaks into the Kalman part's attitude update (issue 70: where the information goes).

Along a scenario's flight over a world whose only difference from the map is a correlated error field (on the map's
own posts, ``world_refine = 1``), the sensor's noiseless scan at the true pose each measurement epoch is scored by the
model at the true pose: its attitude information ``(Λ_k, b_k)`` (:func:`warptan.kernels.likelihood.
attitude_information`). At the truth every ``b_k`` is the field's doing, so the Kalman update's accumulated reading
``(Σ Λ_k)⁻¹ Σ b_k`` against its own claimed σ ``diag((Σ Λ_k)⁻¹)^½`` is the attitude error the field would drive a
filter to, in σ (a static accumulation: the filter's process noise forgets, so this is an upper end). A float64 oracle
of the same sums (finite-difference Jacobians, the model's mode table, Woodbury with the table's attitude weights
``cᵃ``, Schur against the position) checks the kernel, then re-weights the modes to show which ones leak: the modes
whose along-track sharing is 1 (``κ = 1``: shaped like a derivative along the track), those past the ninth (small
one-scan variance), all of them (each fully removed from the attitude information).

    python scripts/attitude_leak.py --scenario S8 --error-m 5 --corr-m 1000 --json out.json
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from warptan.device import quiet_warp
from warptan.meta import run_meta


def _rotation(d: np.ndarray) -> np.ndarray:
    """The rotation matrix of the small rotation vector ``d`` (Rodrigues)."""
    a = float(np.linalg.norm(d))
    if a == 0.0:
        return np.eye(3)
    k = d / a
    skew = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(a) * skew + (1.0 - np.cos(a)) * skew @ skew


def _information(u, weights, z, ht, hp):
    """(Λ, b) of the attitude in float64: Woodbury with the modes ``u`` at ``weights``, then the Schur complement
    against the position (its prior precision 1e-4 m⁻², as the kernels)."""
    w = np.eye(len(z)) - u @ np.diag(weights) @ u.T
    ltp, lpp = ht.T @ w @ hp, hp.T @ w @ hp + 1e-4 * np.eye(3)
    gain = ltp @ np.linalg.inv(lpp)
    return ht.T @ w @ ht - gain @ ltp.T, ht.T @ w @ z - gain @ (hp.T @ w @ z)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="S8")
    parser.add_argument("--error-m", type=float, default=5.0)
    parser.add_argument("--corr-m", type=float, default=1000.0)
    parser.add_argument("--from-s", type=float, default=30.0, help="first epoch accumulated, s")
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
    quiet_warp()
    import warp as wp

    from warptan.kernels.likelihood import MODE_CA
    from warptan.nav.frames import quat_to_mat
    from warptan.sensing.sensors import PointCloudSensor, ScanPattern
    from warptan.sim.scenarios import map_terrain, prepare, scenario_likelihood, scenario_model

    kw = {"world_error_rms_m": args.error_m, "world_error_corr_m": args.corr_m, "world_seed": 2000, "world_refine": 1,
          "map_error_learn": False, "map_error_rms_m": args.error_m, "map_error_corr_m": args.corr_m}
    scenario, world, flight = prepare(args.scenario, seeds=[0], device="cpu", batched=True, **kw)
    the_map = map_terrain(world, scenario, int(scenario.run.seed))
    model = scenario_model(scenario, the_map, scenario_likelihood(scenario, the_map, world))
    s = scenario.sensor
    if s.model == "altimeter":
        raise SystemExit("attitude_leak: an altimeter reads no attitude")
    sensor = PointCloudSensor(ScanPattern.grid(s.scan_nx, s.scan_ny, s.scan_half_angle_deg), range_sigma_m=0.0)
    sigma = float(model.sigma_m)

    def residuals(p, rot, scan):  # the sliding residual: the point's height above the map (m)
        pts = p + (scan.dirs_s * scan.ranges_m[:, None]) @ rot.T
        return -pts[:, 2] - np.array([the_map.surface_height_at(a, b) for a, b in pts[:, :2]]).ravel()

    sums: dict[str, list] = {}
    step = max(round(flight.rate_hz / s.rate_hz), 1)
    for k in range(int(args.from_s * flight.rate_hz), len(flight.t_s), step):
        p, q = flight.pos_n[k], flight.quat_nb[k]
        scan = sensor.measure(world, p, q, None)
        out = model.evaluate(wp.array(p[None].astype(np.float32), dtype=wp.vec3),
                             wp.array(q[None].astype(np.float32), dtype=wp.vec4), scan)
        terms = {"kernel": (np.array(out.lam.numpy()[0], np.float64), np.array(out.info.numpy()[0], np.float64))}
        rot = quat_to_mat(q)
        r0 = residuals(p, rot, scan)
        h_t, h_p = np.zeros((len(r0), 3)), np.zeros((len(r0), 3))
        for i in range(3):
            e = np.eye(3)[i]
            h_t[:, i] = -(residuals(p, _rotation(1e-5 * e) @ rot, scan) - r0) / 1e-5
            h_p[:, i] = -(residuals(p + 1e-3 * e, rot, scan) - r0) / 1e-3
        table, n = model.mode_table.numpy(), int(model.modes_info["n_modes"])
        u = table[:len(r0), :n].astype(np.float64)
        c_att = table[len(r0) + MODE_CA, :n].astype(np.float64)
        shared_once = np.asarray(model.modes_info["sharing"]) <= 1.0 + 1e-9
        z, ht, hp = r0 / sigma, h_t / sigma, h_p / sigma

        terms["oracle"] = _information(u, c_att, z, ht, hp)
        terms["kappa-1 modes out"] = _information(u, np.where(shared_once, 1.0, c_att), z, ht, hp)
        terms["modes past 9 out"] = _information(u, np.where(np.arange(n) >= 9, 1.0, c_att), z, ht, hp)
        terms["all modes out"] = _information(u, np.ones(n), z, ht, hp)
        for name, (lam, info) in terms.items():
            acc = sums.setdefault(name, [np.zeros((3, 3)), np.zeros(3)])
            acc[0] += lam
            acc[1] += info
    rows = []
    for name, (lam, info) in sums.items():
        theta = np.linalg.solve(lam, info)
        sd = np.sqrt(np.diag(np.linalg.inv(lam)))
        rows.append({"weights": name, "theta_deg": np.degrees(theta).tolist(), "sigma_deg": np.degrees(sd).tolist(),
                     "z": (theta / sd).tolist()})
        print(f"{name:18s} dθ {np.degrees(theta).round(4)} deg, claimed σ {np.degrees(sd).round(4)}, z "
              f"{(theta / sd).round(1)}")
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump({"meta": run_meta(), "scenario": args.scenario, "error_m": args.error_m,
                       "corr_m": args.corr_m, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
