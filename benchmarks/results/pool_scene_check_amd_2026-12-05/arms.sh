#!/bin/bash
# #63, twenty-fourth session (AMD EPYC, AVX512-BF16, 2 vCPU): the pool checked by the scene's fused pseudo-boxes
# (mining_scene.yaml) and, on top, at most 4 pairs per box (mining_scene_cap4.yaml); rounds 1-4 from each seed's
# default round 0 (runs/em, runs/em_s1, runs/shp_def_s{0,1}). The same script as ../negatives_pool_amd_2026-12-04/.
# RUNS: "data:seed:arm ..." with data shp|emb
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
for R in $RUNS; do
  IFS=: read DATA S ARM <<< "$R"
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  if [ $DATA = shp ]; then D=runs/shp_def_s$S; DC="--data_config data/shapes.yaml"; else
    D=runs/em; [ $S = 1 ] && D=runs/em_s1; DC=""; fi
  W=runs/${DATA}_${ARM}_s$S; mkdir -p $W
  [ -e $W.done ] && continue
  for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do [ -e $W/$d ] || cp -r $D/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W $DC --mining_config mining_$ARM.yaml \
    $EXTRA --resume true > $W.log 2>&1 && touch $W.done
  echo "$R $(date +%T)" >> /tmp/mj/arms4.progress
done
echo done >> /tmp/mj/arms4.progress
