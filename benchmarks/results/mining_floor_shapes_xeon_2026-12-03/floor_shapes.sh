#!/bin/bash
# #63 on the shape-only data: retrieval_occupancy_floor 0.2 alone (the quantizer's em_restarts 1, the default), 2 seeds,
# from each seed's view prediction, detector and its evaluation of the "both" runs (shapes.sh); round 0 rerun with em_restarts 1.
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
for S in 0 1; do
  V=runs/shapes_vp/seed$S
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  W=runs/shp_floor_s$S; mkdir -p $W
  for d in 01_viewpred_eval 02_detector 03_detector_eval; do cp -r runs/shp_new_s$S/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --viewpred_ckpt $V/epoch=8-step=1700.ckpt \
    --quantizer_config q1.yaml $EXTRA --resume true > $W.log 2>&1
done
echo done > /tmp/mj/floor_shapes.done
