#!/bin/bash
# After arms.sh: shape_oversample 4 (the nineteenth session's arm) on the shape-only data, 2 seeds, from the same
# round 0s; then the embedded seed 0: both arms from the main job's round 0 (runs/em).
while [ ! -e /tmp/mj/arms.done ]; do sleep 20; done
SEEDS="0 1" ARMS=shape bash /tmp/mj/arms.sh
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
for ARM in shape2 shape; do
  W=runs/emb_${ARM}_s0; mkdir -p $W
  for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do [ -e $W/$d ] || cp -r runs/em/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --mining_config mining_$ARM.yaml --resume true > $W.log 2>&1 && touch $W.done
done
echo done > /tmp/mj/arms2.done
