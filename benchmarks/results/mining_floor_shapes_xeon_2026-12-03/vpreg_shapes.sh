#!/bin/bash
# #63 on the shape-only data: view prediction kept as a regulariser during mining (view_prediction_weight 1.0,
# num_target_views 1) on the default miner (retrieval_occupancy_floor null) and bank (em_restarts 1), 2 seeds, from each
# seed's view prediction, detector and round 0 of floor_shapes.sh (round 0 is the default's there).
# mining_vpreg.yaml: sed -e 's/^    view_prediction_weight: 0.0/    view_prediction_weight: 1.0/'
#   -e 's/^    num_target_views: 0/    num_target_views: 1/' mining_def.yaml
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
while [ ! -f /tmp/mj/floor_shapes.done ]; do sleep 20; done
for S in 0 1; do
  V=runs/shapes_vp/seed$S
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  W=runs/shp_vpreg_s$S; mkdir -p $W
  for d in 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r runs/shp_floor_s$S/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --viewpred_ckpt $V/epoch=8-step=1700.ckpt \
    --mining_config mining_vpreg.yaml --quantizer_config q1.yaml $EXTRA --resume true > $W.log 2>&1
done
echo done > /tmp/mj/vpreg_shapes.done
