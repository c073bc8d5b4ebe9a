#!/bin/bash
# #63 on the embedded data: view prediction kept as a regulariser during mining (mining_vpreg.yaml: view_prediction_weight
# 1.0, num_target_views 1, otherwise today's defaults), 2 seeds, from each seed's default view prediction, detector and
# (seed 1) round 0 of the default runs em_def_s0r0 / em_def_s1; seed 0 refits round 0 (the default's, em_restarts 1).
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
ARM=${ARM:-vpreg}
for S in 0 1; do
  W=runs/emb_${ARM}_s$S; mkdir -p $W
  if [ $S = 0 ]; then EXTRA=""; SRC=runs/em_def_s0r0; DIRS="00_viewpred 01_viewpred_eval 02_detector 03_detector_eval"
  else EXTRA="--extra_configs seed1.yaml"; SRC=runs/em_def_s1; DIRS="00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer"; fi
  for d in $DIRS; do [ -e $W/$d ] || cp -r $SRC/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --mining_config mining_$ARM.yaml --quantizer_config q1.yaml \
    $EXTRA --resume true > $W.log 2>&1
done
echo done > /tmp/mj/${ARM}_emb.done
