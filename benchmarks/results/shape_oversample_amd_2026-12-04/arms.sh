#!/bin/bash
# #63, twentieth session (AMD EPYC Genoa, 2 vCPU, AVX512-BF16): shape_oversample 2 against the default on the
# shape-only data, 2 seeds; each arm's rounds 1-4 from its seed's default round 0 (same view prediction, detector,
# round-0 bank). Then the embedded seed 0 arm from the main job's round 0 (runs/em).
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
for S in ${SEEDS:-0 1}; do
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  D=runs/shp_def_s$S
  [ -e $D.done ] || { /usr/bin/time -v -o $D.time threedq em --rounds 4 --work_dir $D --data_config data/shapes.yaml $EXTRA --resume true > $D.log 2>&1 && touch $D.done; }
  for ARM in ${ARMS:-shape2}; do
    W=runs/shp_${ARM}_s$S; mkdir -p $W
    for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do [ -e $W/$d ] || cp -r $D/$d $W/; done
    /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --mining_config mining_$ARM.yaml \
      $EXTRA --resume true > $W.log 2>&1 && touch $W.done
  done
  echo seed$S >> /tmp/mj/arms.progress
done
echo done > /tmp/mj/arms.done
