#!/bin/bash
# #63 on the shape-only data, the control of vpreg_shapes.sh: the same stage with the mined pairs' InfoNCE out of the
# loss (mining_vponly.yaml = mining_vpreg.yaml + correspondence_weight: 0.0), so view prediction alone trains the encoder
# on the mined scenes; 2 seeds, from the floor runs' view prediction, detector and round 0 (today's default round 0).
# (Run as queue.sh / queue2.sh in /tmp/mj; seed 0 then seed 1, alone on the machine.)
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
for S in 0 1; do
  V=runs/shapes_vp/seed$S
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  W=runs/shp_vponly_s$S; mkdir -p $W
  for d in 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r runs/shp_floor_s$S/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --viewpred_ckpt $V/epoch=8-step=1700.ckpt \
    --mining_config mining_vponly.yaml --quantizer_config q1.yaml $EXTRA --resume true > $W.log 2>&1
done
