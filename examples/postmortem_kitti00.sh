#!/usr/bin/env bash
# Post-mortem on field data: KITTI 00 with DLoopDetector loop candidates at alpha 0.50
# (robustslam_kitti). The data folder is $LCV_SHARED_DATA, else ../shared/data beside the
# repository (the project's checkout layout). Walk-through: examples/postmortem_kitti00.md.
set -euo pipefail
DATA="${LCV_SHARED_DATA:-$(dirname "$0")/../../shared/data}/robustslam_kitti/00"
OUT="${1:-kitti00}"
mkdir -p "$OUT"

# 1. Record the pose graph into a log: /odom (libviso2 stereo VO), /loop_candidates (337
#    DLoopDetector candidates), /ground_truth/pose and /ground_truth/loops (120 true pairs) are
#    picked up from the sibling files kitti_00_GT.g2o and kitti_00_alpha_0.50_GT_LC.txt.
lcv-replay record g2o "$DATA/kitti_00_alpha_0.50.g2o" -o "$OUT/kitti00_a050.mcap" --force

# 2. Replay it with the paper's method and with the improved one (ilv+, the default).
#    Each also writes its results for other tools (--export) and an HTML report (--report).
lcv-replay "$OUT/kitti00_a050.mcap" --method ilv --save "$OUT/kitti00_ilv.rrd" --export "$OUT/kitti00_ilv" --report "$OUT/kitti00_ilv.html" --force
lcv-replay "$OUT/kitti00_a050.mcap" --method ilv+ --save "$OUT/kitti00_ilvplus.rrd" --export "$OUT/kitti00_ilvplus" --report "$OUT/kitti00_ilvplus.html" --force

# 3. The wrong loop closures, and when they entered, straight from the recording.
python "$(dirname "$0")/list_wrong_loops.py" "$OUT/kitti00_ilv.rrd"

# 4. evo agrees with the summary's ATE (evo is in the test extra).
if command -v evo_ape >/dev/null; then evo_ape tum "$OUT/kitti00_ilv/ground_truth.tum" "$OUT/kitti00_ilv/trajectory.tum" -a; fi

# 5. Look at them: rerun "$OUT/kitti00_ilv.rrd", or at the first wrong acceptance:
echo "open the recordings with: rerun $OUT/kitti00_ilv.rrd (and $OUT/kitti00_ilvplus.rrd),"
echo "or at the first wrong acceptance: lcv-replay open $OUT/kitti00_ilv.rrd --first-wrong"
