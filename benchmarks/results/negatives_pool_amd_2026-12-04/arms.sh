#!/bin/bash
# #63, twenty-first session (AMD EPYC, AVX512-BF16, 2 vCPU): negatives from the pool (keys not enqueued), with
# the default positives (pool) and the occupancy positives (shape_pool); rounds 1-4 from each seed's default round 0.
# RUNS: "data:seed:arm[:qarm] ..." with data shp|emb; arm names mining_<arm>.yaml; the optional qarm (twenty-fifth
# session) names a quantizer config q_<qarm>.yaml, whose arm then fits its own round 0 bank (work dir
# runs/<data>_<arm>_q<qarm>_s<seed>). Also optional (twenty-fifth session): EMX, more `threedq em` arguments, with
# SUFFIX appended to the work dir's name; SAME_UNTIL=<tag> copies rounds 0-1 from runs/<data>_<tag>_s<seed> (for an
# arm whose first change is in round 2, e.g. EMX="--bank_warm_start false": round 1 fits an empty bank either way).
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
for R in $RUNS; do
  IFS=: read DATA S ARM QARM <<< "$R"
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  if [ $DATA = shp ]; then D=runs/shp_def_s$S; DC="--data_config data/shapes.yaml"; else
    D=runs/em; [ $S = 1 ] && D=runs/em_s1; DC=""; fi
  QC=""; TAG=$ARM; KEEP="00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer"
  if [ -n "$QARM" ]; then QC="--quantizer_config q_$QARM.yaml"; TAG=${ARM}_q$QARM; KEEP=${KEEP% r00_eval*}; fi
  W=runs/${DATA}_${TAG}${SUFFIX}_s$S; mkdir -p $W
  [ -e $W.done ] && continue
  for d in $KEEP; do [ -e $W/$d ] || cp -r $D/$d $W/; done
  if [ -n "$SAME_UNTIL" ]; then for d in runs/${DATA}_${SAME_UNTIL}_s$S/r0[01]_*; do
    [ -e $W/$(basename $d) ] || cp -r $d $W/; done; fi
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W $DC --mining_config mining_$ARM.yaml $QC \
    $EXTRA $EMX --resume true > $W.log 2>&1 && touch $W.done
  echo "$R $(date +%T)" >> /tmp/mj/arms4.progress
done
echo done >> /tmp/mj/arms4.progress
