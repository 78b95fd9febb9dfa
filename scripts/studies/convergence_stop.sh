#!/usr/bin/env bash
# Before/after of the convergence stop: ns-train on each tilt-series directory given, with
# --pipeline.model.stop-when-converged False and True; prints wall time, the step it ended
# at and the scores, as a Markdown table.
set -euo pipefail
usage() { echo "usage: scripts/studies/convergence_stop.sh OUT DEVICE DATA_DIR...  (DEVICE: cpu or cuda; one table row per data directory and setting)"; }
case "${1:-}" in -h|--help) usage; exit 0 ;; esac
if [ $# -lt 3 ]; then usage >&2; exit 2; fi
bin="$(cd "$(dirname "$0")/../.." && pwd)/.venv/bin"
if [ -x "$bin/ns-train" ]; then PATH="$bin:$PATH"; fi
out=$1; device=$2; shift 2
mkdir -p "$out"
echo "| data | stop when converged | wall time (s) | steps | TPR | FP/atom | RMSD (pm) |"
echo "| --- | --- | --- | --- | --- | --- | --- |"
for data in "$@"; do
  for stop in False True; do
    run="$out/$(basename "$data")-stop$stop"
    start=$(date +%s.%N)
    ns-train gaussian-atoms --machine.device-type "$device" --vis tensorboard --output-dir "$run" \
      --experiment-name e --timestamp r --pipeline.model.stop-when-converged "$stop" \
      tilt-series --data "$data" > "$run.log" 2>&1
    end=$(date +%s.%N)
    dir="$run/e/gaussian-atoms/r"
    steps=$(ls "$dir/nerfstudio_models" | sed 's/step-0*\([0-9]*\).ckpt/\1/')
    python3 - "$dir/evaluation.json" "$(basename "$data")" "$stop" "$start" "$end" "$steps" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print(f"| {sys.argv[2]} | {sys.argv[3]} | {float(sys.argv[5]) - float(sys.argv[4]):.1f} | {sys.argv[6]} | {s['tpr']:.4f} | {s['fp_per_true_atom']:.4f} | {s['rmsd_pm']:.1f} |")
PY
  done
done
