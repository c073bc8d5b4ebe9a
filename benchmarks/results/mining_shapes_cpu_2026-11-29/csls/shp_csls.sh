#!/bin/bash
# #63: the CSLS miner (csls_k 10 on today's default) on the shape-only data, rounds 1-4 from each seed's shapes round 0
cd /tmp/mj; source /tmp/mjvenv/bin/activate
grep -q "csls_k: 10" mining_csls.yaml || exit 1
for S in 0 1; do
  VP=/work/main/runs/shapes_vp/seed$S/epoch=8-step=1700.ckpt
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  B=runs/shp_em_s$S; W=runs/shp_em_s${S}_csls; mkdir -p $W
  for d in 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r $B/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --viewpred_ckpt $VP $EXTRA --mining_config mining_csls.yaml --resume true > $W.log 2>&1
done
echo done > runs/shp_csls.done
