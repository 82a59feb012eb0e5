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
lcv-replay "$OUT/kitti00_a050.mcap" --method ilv --save "$OUT/kitti00_ilv.rrd" --summary-json "$OUT/kitti00_ilv.json" --force
lcv-replay "$OUT/kitti00_a050.mcap" --method ilv+ --save "$OUT/kitti00_ilvplus.rrd" --summary-json "$OUT/kitti00_ilvplus.json" --force

# 3. The wrong loop closures, and when they entered, straight from the recording.
python "$(dirname "$0")/list_wrong_loops.py" "$OUT/kitti00_ilv.rrd"

# 4. Look at them: rerun "$OUT/kitti00_ilv.rrd"
echo "open the recordings with: rerun $OUT/kitti00_ilv.rrd   (and $OUT/kitti00_ilvplus.rrd)"
