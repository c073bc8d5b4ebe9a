#!/bin/bash
# #63: the prototype check (mining_checked.yaml's verify_by_prototypes) on the shape-only data, 2 seeds
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
ARM=chk
for S in ${SEEDS:-0 1}; do
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  V=runs/shapes_vp/seed$S
  W=runs/shp_${ARM}_s$S; mkdir -p $W
  for d in 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do [ -e $W/$d ] || cp -r runs/shp_floor_s$S/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --viewpred_ckpt $V/epoch=8-step=1700.ckpt \
    --mining_config mining_$ARM.yaml --quantizer_config q1.yaml $EXTRA --resume true > $W.log 2>&1
  echo shapes_seed$S >> /tmp/mj/${ARM}.progress
done
echo done > /tmp/mj/${ARM}.done
