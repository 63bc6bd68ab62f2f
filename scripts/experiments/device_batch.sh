#!/usr/bin/env bash
# Several `scripts/device_train.py train` runs side by side on one lent GPU machine, each with
# its own log, then the results bundled into at most 8 files under $OUT (what the device tool
# brings back): one tar of the small runs (the rod checkpoints, histories, curves, logs) and
# each large slim checkpoint in 15 MiB pieces (a file brought back is at most 16 MiB).
#
#   bash scripts/experiments/device_batch.sh MINUTES RUN...
#   RUN = name:packed.npz:config[:extra device_train.py flags, comma-separated][:keep]
#
# `keep` brings the run's slim checkpoint back (the paper's encoder is about 15 MiB in float16);
# without it only its history, curves and log come back. Example:
#   bash scripts/experiments/device_batch.sh 6 \
#       cyl_sph:runs/packed/cylinder.npz:cpu_spheres:--batch-size,128,--spheres,6:keep
set -u
minutes=$1
shift
out=${OUT:-runs/device_batch}
work=runs/device_batch
mkdir -p "$out" "$work"
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1
pids=()
for spec in "$@"; do
    IFS=: read -r name packed config extra keep <<< "$spec"
    IFS=, read -r -a flags <<< "$extra"
    python3 scripts/device_train.py train --packed "$packed" --config "$config" \
        --minutes "$minutes" --out "$work/$name" --device cuda --half --quiet "${flags[@]}" \
        > "$work/$name.log" 2>&1 &
    pids+=($!)
done
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv > "$work/gpu.csv" 2>&1
for pid in "${pids[@]}"; do wait "$pid"; done
small=()
for spec in "$@"; do
    IFS=: read -r name packed config extra keep <<< "$spec"
    tail -3 "$work/$name.log"
    small+=("$work/$name.log")
    for f in log.jsonl summary.json curves.png; do
        [ -e "$work/$name/$f" ] && small+=("$work/$name/$f")
    done
    if [ "$keep" = keep ]; then
        size=$(stat -c %s "$work/$name/slim.pt" 2>/dev/null || echo 0)
        if [ "$size" -gt 4000000 ]; then  # in 15 MiB pieces: `cat NAME.slim.pt.* > slim.pt`
            split -b 15M -d "$work/$name/slim.pt" "$out/$name.slim.pt."
        else small+=("$work/$name/slim.pt"); fi
    fi
done
tar czf "$out/small.tgz" "$work/gpu.csv" "${small[@]}"
ls -la "$out"
