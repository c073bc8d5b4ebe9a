#!/bin/bash
# embedded seed 1: today's default from scratch, then oversample 4 from its round 0
while [ ! -e /tmp/ci_last.done ]; do sleep 10; done
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
D=runs/em_s1
/usr/bin/time -v -o $D.time threedq em --rounds 4 --work_dir $D --extra_configs seed1.yaml --resume true > $D.log 2>&1 && touch $D.done
W=runs/emb_shape_s1; mkdir -p $W
for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do [ -e $W/$d ] || cp -r $D/$d $W/; done
/usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --mining_config mining_shape.yaml --extra_configs seed1.yaml \
  --resume true > $W.log 2>&1 && touch $W.done
echo done > /tmp/mj/arms3.done
