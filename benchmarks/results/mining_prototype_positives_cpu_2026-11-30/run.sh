#!/bin/bash
# #63: prototype positives (prototype_weight 1.0), rounds 1-4 from each seed's round 0 (runs/em, runs/em_s1base: the
# reference runs' view prediction, detector and round 0), on today's default miner (mining_proto.yaml) and on the
# miner with the prototype check (mining_checked_proto.yaml); then Table 2 on GT boxes for the round-4 encoders.
# Frozen copy of 6ba08a6 in /tmp/mp; seed1.yaml = "seed_everything: 1". (The checked runs were named em_ckproto_s$S.)
sed 's/^    prototype_weight: 0.0 .*/    prototype_weight: 1.0/' configs/stages/mining.yaml > mining_proto.yaml
sed 's/^    prototype_weight: 0.0 .*/    prototype_weight: 1.0/' configs/stages/mining_checked.yaml > mining_checked_proto.yaml
for C in proto checked_proto; do
  for S in 0 1; do
    if [ $S = 0 ]; then B=runs/em; EXTRA=""; else B=runs/em_s1base; EXTRA="--extra_configs seed1.yaml"; fi
    W=runs/em_${C}_s$S; rm -rf $W; mkdir -p $W
    for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r $B/$d $W/; done
    threedq em --rounds 4 --work_dir $W --mining_config mining_$C.yaml $EXTRA --resume true
  done
done
# the shape-only data (today's miner + prototype positives only)
for S in 0 1; do
  VP=runs/shapes_vp/seed$S/epoch=8-step=1700.ckpt
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  B=runs/shp_em_s$S; W=runs/shp_em_proto_s$S; rm -rf $W; mkdir -p $W
  for d in 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r $B/$d $W/; done
  threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --viewpred_ckpt $VP $EXTRA --mining_config mining_proto.yaml --resume true
done
threedq eval --ckpt runs/em_proto_s0/r04_quantizer/checkpoints/last.ckpt --out runs/fid_gt_proto --curve_k '[]' --baselines false \
  --encoders '{"view prediction": "runs/em/00_viewpred/checkpoints/last.ckpt", "round 4, default miner, seed 0": "runs/em_obj/r04_mining/checkpoints/last.ckpt", "round 4, default miner, seed 1": "runs/em_s1obj/r04_mining/checkpoints/last.ckpt", "round 4, prototype positives, seed 0": "runs/em_proto_s0/r04_mining/checkpoints/last.ckpt", "round 4, prototype positives, seed 1": "runs/em_proto_s1/r04_mining/checkpoints/last.ckpt"}'
threedq eval --ckpt runs/em_checked_proto_s0/r04_quantizer/checkpoints/last.ckpt --out runs/fid_gt_ckproto --curve_k '[]' --baselines false \
  --encoders '{"round 4, both checks, seed 0": "runs/em_ck_lr/r04_mining/checkpoints/last.ckpt", "round 4, both checks, seed 1": "runs/em_s1ck_lr/r04_mining/checkpoints/last.ckpt", "round 4, both checks + prototype positives, seed 0": "runs/em_checked_proto_s0/r04_mining/checkpoints/last.ckpt", "round 4, both checks + prototype positives, seed 1": "runs/em_checked_proto_s1/r04_mining/checkpoints/last.ckpt"}'
# python fresh_bank_diag.py runs/em_ckproto_s0 runs/em_ckproto_s1 runs/em_obj runs/em_s1obj   (in /tmp/mp, after the runs)
