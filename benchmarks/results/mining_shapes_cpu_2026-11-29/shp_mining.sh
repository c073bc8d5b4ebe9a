#!/bin/bash
# #63 on shape-only data: the default miner (object check + falling rate) against the paper's, 2 seeds,
# the shapes view-prediction encoders of shape.md (1700 steps); each paper-miner run reuses its seed's detector and round 0.
cd /tmp/mj; source /tmp/mjvenv/bin/activate
for S in 0 1; do
  VP=/work/main/runs/shapes_vp/seed$S/epoch=8-step=1700.ckpt
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  W=runs/shp_em_s$S
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --viewpred_ckpt $VP $EXTRA > $W.log 2>&1
  P=runs/shp_em_s${S}_paper; mkdir -p $P
  for d in 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r $W/$d $P/; done
  /usr/bin/time -v -o $P.time threedq em --rounds 4 --work_dir $P --data_config data/shapes.yaml --viewpred_ckpt $VP $EXTRA --mining_config mining_paper.yaml --resume true > $P.log 2>&1
done
echo done > runs/shp_mining.done
