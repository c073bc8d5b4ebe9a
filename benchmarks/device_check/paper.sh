#!/bin/bash
# The paper preset's view prediction on a lent GPU for a fixed time, its step time beside the estimate
# (docs/paper-scale.md), run from the repository root there with .whl/ carried (see run.sh):
#   bash benchmarks/device_check/paper.sh [minutes, default 3]
# Writes $OUT/paper_steps.txt.
source benchmarks/device_check/setup.sh || exit 1
timeout $(( ${1:-3} * 60 + 240 )) python3 benchmarks/paper_scale.py --minutes ${1:-3} 2>&1 | tee $OUT/paper_steps.txt
