"""The integrity monitor (MBARI TRN style) and the re-spread of a filter it judges lost."""

import warp as wp

from warptan.kernels.filter.common import (
    IN_MEAN,
    IN_RESPREADS,
    IN_RING,
    IN_SINCE,
    ST_MEAN_DP,
    ST_NIS_MIN,
    ST_RESPREAD,
    ST_SKIP,
    UpdateParams,
    gaussian3,
)

wp.set_module_options({"enable_backward": False})

@wp.func
def integrity_step(b: int, params: UpdateParams, stats: wp.array2d(dtype=wp.float64),
                   integrity: wp.array2d(dtype=wp.float64), kernel_chol: wp.array(dtype=wp.mat33)):
    """One thread per filter, after the last stage (MBARI TRN style): the mean over the last ``integrity_window``
    informative updates of the smallest NIS of any particle — large only when no hypothesis explains the scan,
    whereas a wide but healthy cloud (acquisition, a flat likelihood) still holds particles that do; above
    ``integrity_threshold`` (after ``integrity_min_updates``
    informative updates, so that acquisition is not judged) the filter is lost: flag it for a re-spread and
    restart the window."""
    if stats[b, ST_SKIP] != wp.float64(0.0):
        return
    w = params.integrity_window
    k = int(integrity[b, IN_SINCE])
    integrity[b, IN_RING + k % w] = stats[b, ST_NIS_MIN]
    k += 1
    count = wp.min(k, w)
    total = wp.float64(0.0)
    for j in range(count):
        total += integrity[b, IN_RING + j]
    mean = total / wp.float64(count)
    integrity[b, IN_MEAN] = mean
    if k >= params.integrity_min_updates and mean > wp.float64(params.integrity_threshold):
        stats[b, ST_RESPREAD] = wp.float64(1.0)
        kernel_chol[b] = params.bandwidth * params.respread_chol  # the re-spread cloud's kernel
        integrity[b, IN_RESPREADS] = integrity[b, IN_RESPREADS] + wp.float64(1.0)
        k = 0
    integrity[b, IN_SINCE] = wp.float64(k)


@wp.kernel
def integrity_kernel(params: UpdateParams, stats: wp.array2d(dtype=wp.float64),
                     integrity: wp.array2d(dtype=wp.float64), kernel_chol: wp.array(dtype=wp.mat33)):
    """One thread per (b): :func:`integrity_step`."""
    b = wp.tid()
    integrity_step(b, params, stats, integrity, kernel_chol)



@wp.func
def respread_particle(
    i: int,
    n_per: int,
    offset: int,
    seeds: wp.array(dtype=wp.int32),
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    logw: wp.array(dtype=wp.float32),
):
    """A filter flagged lost re-spreads dp, uniform weights (Kalman means kept; stream ``offset + j``), over the two
    hypotheses it has left: its own estimate, half the slots (even j) around its weighted mean with the re-spread
    covariance, and the INS alone, the other half around ``dp = 0`` horizontally (the unaided INS; the mean's
    altitude, which a barometer or the scans keep) with that covariance's horizontal part grown to the unaided INS's
    variance (plus one prior's: ``params.free_var``, the regularisation's cap) where that is larger. Around its mean
    alone, a filter lost far from the truth could not come back: the altimeter over a biased world (S9, seed 2,
    120 s) was 1.4 km off at 60 s and 3.3 km at the end after 9 re-spreads, its INS a few hundred metres from the
    truth; with the INS's half, one re-spread, 8 m at 60 s. That is for a model that cannot fix the position with one
    reading (``params.respread_ins``: the altimeter, whose estimate can sit on a wrong contour hundreds of metres off
    while the INS is not far). A point cloud fixes the position with each scan: a filter flagged lost is mostly near
    the truth with a likelihood that does not fit (the paper's scalar one, flagged over and over on map = world runs:
    S2, 8 seeds, 27.0 m with every slot around the estimate, 36.9 m with the INS's half), so its INS half runs only
    where the estimate lies beyond what the INS allows (``|dp_h|²`` above χ²₂'s 99.73 % point of ``free_var / 2``
    per axis)."""
    b = i // n_per
    if stats[b, ST_RESPREAD] == wp.float64(0.0):
        return
    state = wp.rand_init(seeds[b], offset + i % n_per)
    centre = wp.vec3(wp.float32(stats[b, ST_MEAN_DP]), wp.float32(stats[b, ST_MEAN_DP + 1]),
                     wp.float32(stats[b, ST_MEAN_DP + 2]))
    c = params.respread_chol
    g = c * gaussian3(state)
    tr_h = c[0, 0] * c[0, 0] + c[1, 0] * c[1, 0] + c[1, 1] * c[1, 1]  # the re-spread's horizontal trace
    # the estimate beyond what the INS allows: |dp_h|² / (free_var / 2) above χ²₂'s 99.73 % point
    implausible = centre[0] * centre[0] + centre[1] * centre[1] > 5.915 * params.free_var[b]
    if (implausible or params.respread_ins != 0) and (i % n_per) % 2 == 1:  # the INS's half
        k = wp.sqrt(wp.max(params.free_var[b] / tr_h, 1.0))
        centre = wp.vec3(0.0, 0.0, centre[2])
        g = wp.vec3(k * g[0], k * g[1], g[2])
    dp[i] = centre + g
    logw[i] = -wp.log(float(n_per))


@wp.kernel
def respread_kernel(
    n_per: int,
    offset: int,
    seeds: wp.array(dtype=wp.int32),
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    logw: wp.array(dtype=wp.float32),
):
    """One thread per (i): :func:`respread_particle`."""
    i = wp.tid()
    respread_particle(i, n_per, offset, seeds, params, stats, dp, logw)
