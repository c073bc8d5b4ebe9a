#!/bin/bash
# The GPU check of a lent device machine (docs/usage.md, "On a GPU"), run from the repository root there:
#   bash benchmarks/device_check/run.sh [seconds for the main job, default 420] [view-prediction checkpoint]
# Prepared here first (both folders ignored by git, carried with the device tool's `carry`):
#   .whl/     wheels the device image lacks, for its Python 3.12: kornia, kornia_rs, jsonargparse,
#             docstring_parser, typeshed_client (`pip download --no-deps --only-binary=:all: --python-version 3.12 ...`)
#   .devdata/p128/  the embedded data packed by benchmarks/device_copy.py (17 MB)
# A checkpoint of this machine's view prediction (e.g. runs/em/00_viewpred/checkpoints/last.ckpt copied into a
# carried folder) skips the 85 s of view prediction there and leaves more of the budget to the rounds.
# Writes to $OUT: cuda_vs_cpu.txt, bench_infonce.txt, em.log, em.time, run.tgz (the run folder without checkpoints).
BUDGET=${1:-420}
VP=${2:+--viewpred_ckpt $2}
source benchmarks/device_check/setup.sh || exit 1
timeout 60 python3 benchmarks/device_check/cuda_vs_cpu.py 2>&1 | tee $OUT/cuda_vs_cpu.txt
timeout 100 python3 benchmarks/bench_infonce.py --device cuda > $OUT/bench_infonce.txt 2>&1
python3 benchmarks/device_copy.py unpack .devdata/p128 data/clevr_veggie --workers 16 2>&1 | tail -c 100
left=$((BUDGET - SECONDS)); echo "main job, $left s"
/usr/bin/time -v -o $OUT/em.time timeout $left \
  threedq em --rounds 4 --work_dir runs/gpu --extra_configs trainer/gpu.yaml $VP > $OUT/em.log 2>&1
echo "em rc=$?"; tr '\r' '\n' < $OUT/em.log | grep '^\[em\]\|error'
tar czf $OUT/run.tgz --exclude='*.ckpt' --exclude='*.pt' --exclude='*.npz' --exclude='*tfevents*' runs/gpu 2>/dev/null
