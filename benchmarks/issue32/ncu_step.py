"""One scenario's filter stepped with eager launches on CUDA (``graph = False``: Nsight Compute cannot profile the
kernel nodes of a graph with conditional nodes), for ``ncu``; ``ncu_summary.py`` reads its report.

    ncu --clock-control none --cache-control none --launch-skip 1300 --launch-count 40 --section SpeedOfLight \
        --section LaunchStats --section Occupancy --section WarpStateStats -o s7 python3 ncu_step.py SCRIPTS_DIR S7 130
"""
import sys

sys.path.insert(0, sys.argv[1])
import bench_filter_step as bfs

from warptan.device import quiet_warp

quiet_warp()
sid, steps = sys.argv[2], int(sys.argv[3])
mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
mpf.graph = False
for _ in bfs.synchronised_steps(mpf, f, w, setup, steps):
    pass
print("done", sid, mpf._lean)
