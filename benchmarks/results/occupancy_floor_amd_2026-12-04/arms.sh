#!/bin/bash
# #63, twenty-first session (AMD EPYC, AVX512-BF16, 2 vCPU): negatives from the pool (keys not enqueued), with
# the default positives (pool) and the occupancy positives (shape_pool); rounds 1-4 from each seed's default round 0.
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
