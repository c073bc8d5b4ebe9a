#!/bin/bash
# #63: view prediction kept during mining at a quarter weight (mining_vp025.yaml: view_prediction_weight 0.25,
# num_target_views 1, otherwise today's defaults), 2 seeds on the embedded data and on the shape-only data, rounds 1-4
# from each seed's round 0 of the default runs (embedded: em_def_s0r0 refits round 0, em_def_s1; shape-only:
# shp_floor_s{0,1}, whose round 0 is the default's). Order: seed 0 on both, then seed 1 on both.
# Other arms: ARM=<name> runs mining_<name>.yaml; SEEDS="0" runs seed 0 alone (seventeenth session:
# ARM=vpocc and ARM=vpocc10, benchmarks/results/vpocc_xeon_2026-12-03/).
# DATA=shapes (or embedded) runs one data set alone (eighteenth session: ARM=chk DATA=shapes,
# benchmarks/results/prototype_check_shapes_xeon_2026-12-03/; ARM=proj,
# benchmarks/results/projection_head_xeon_2026-12-03/). Nineteenth session: ARM=shape and ARM=shape1
# (benchmarks/results/shape_positives_xeon_2026-12-03/).
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
ARM=${ARM:-vp025}
DATA=${DATA:-both}
for S in ${SEEDS:-0 1}; do
  if [ $DATA != shapes ]; then
  # embedded
  W=runs/emb_${ARM}_s$S; mkdir -p $W
  if [ $S = 0 ]; then EXTRA=""; SRC=runs/em_def_s0r0; DIRS="00_viewpred 01_viewpred_eval 02_detector 03_detector_eval"
  else EXTRA="--extra_configs seed1.yaml"; SRC=runs/em_def_s1; DIRS="00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer"; fi
  for d in $DIRS; do [ -e $W/$d ] || cp -r $SRC/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --mining_config mining_$ARM.yaml --quantizer_config q1.yaml \
    $EXTRA --resume true > $W.log 2>&1
  fi
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  [ $DATA = embedded ] && { echo seed$S >> /tmp/mj/${ARM}.progress; continue; }
  # shape-only
  V=runs/shapes_vp/seed$S
  W=runs/shp_${ARM}_s$S; mkdir -p $W
  for d in 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do [ -e $W/$d ] || cp -r runs/shp_floor_s$S/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --viewpred_ckpt $V/epoch=8-step=1700.ckpt \
    --mining_config mining_$ARM.yaml --quantizer_config q1.yaml $EXTRA --resume true > $W.log 2>&1
  echo seed$S >> /tmp/mj/${ARM}.progress
done
echo done > /tmp/mj/${ARM}.done
