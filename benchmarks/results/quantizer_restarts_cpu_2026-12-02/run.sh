#!/bin/bash
# #63 / docs/studies/quantizer.md, "Restarts of an empty bank": the commands behind metrics_*.json and
# em_iterations_round4_seed0.json. Machine: 2 vCPU AMD EPYC with AVX2 only, torch 2.13.0 CPU, 2026-12-02.
# seed 0 = the README's main job from a fresh clone of 11feda6 (git clone, new venv, pip install torch==2.13.0 -e .):
#   /usr/bin/time -v threedq em --rounds 4                                  -> runs/em (metrics_default_seed0.json)
# seed 1 = its rounds 1-4 again with seed_everything 1, from the same view prediction, detector and round 0:
echo "seed_everything: 1" > seed1.yaml
mkdir -p runs/em_s1
for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r runs/em/$d runs/em_s1/; done
threedq em --rounds 4 --work_dir runs/em_s1 --extra_configs seed1.yaml --resume true   # metrics_default_seed1.json
# the fit on one encoder (2afc860): round 4 of seed 0, the loop's bank and empty banks of seeds 0-2, every 10 iterations
python em_iterations_diag.py runs/em 04 0,1,2 4                                         # em_iterations_round4_seed0.json
# the loop with em_restarts 4 (2afc860): the same mining and self-labelling stages, quantizers and evaluations redone
sed 's/^    em_restarts: 1$/    em_restarts: 4/' configs/stages/quantizer.yaml > q_restarts4.yaml
for S in 0 1; do
  B=runs/em; EXTRA=""; [ $S = 1 ] && B=runs/em_s1 && EXTRA="--extra_configs seed1.yaml"
  W=runs/chainR_s$S; mkdir -p $W
  for d in $B/*/; do n=$(basename $d); case $n in r0?_quantizer|r0?_eval) ;; *) cp -r $d $W/;; esac; done
  threedq em --rounds 4 --work_dir $W --quantizer_config q_restarts4.yaml $EXTRA --resume true   # metrics_restarts4_seed$S.json
done
# both checks + prototype positives + restarts, from the start (ae44cd0, fresh clone; 2026-12-02, tenth session):
sed 's/^    prototype_weight: 0.0 /    prototype_weight: 1.0 /' configs/stages/mining_checked.yaml > mining_checked_proto.yaml
/usr/bin/time -v threedq em --rounds 4 --work_dir runs/em_cpr --mining_config mining_checked_proto.yaml \
  --quantizer_config q_restarts4.yaml                               # metrics_checked_proto_restarts4_seed0.json
mkdir -p runs/em_cpr_s1
for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r runs/em_cpr/$d runs/em_cpr_s1/; done
threedq em --rounds 4 --work_dir runs/em_cpr_s1 --mining_config mining_checked_proto.yaml --quantizer_config q_restarts4.yaml \
  --extra_configs seed1.yaml --resume true                          # metrics_checked_proto_restarts4_seed1.json
# em_restarts 4 with today's miner from the start (self-labelling after each round's restarted quantizer), seed 0:
mkdir -p runs/em_r4
for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r runs/em_cpr/$d runs/em_r4/; done
threedq em --rounds 4 --work_dir runs/em_r4 --quantizer_config q_restarts4.yaml --resume true   # metrics_restarts4_fromstart_seed0.json
