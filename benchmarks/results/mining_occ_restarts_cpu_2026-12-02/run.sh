#!/bin/bash
# #63 / docs/studies/mined-pairs.md, "Occupancy-weighted retrieval with restarts of the bank": the commands behind the
# files here. Machine: 2 vCPU AMD EPYC with AVX2 only (float32 throughout), torch 2.13.0 CPU, 2026-12-02 (twelfth
# session), code at 563d465 (the default path unchanged since the reference runs).
# runs/em = the README's main job from a fresh clone of 28440ce (../mining_occupancy_retrieval_cpu_2026-12-02/run.sh);
# its metrics equal ../quantizer_restarts_cpu_2026-12-02/metrics_default_seed0.json to the last digit.
# 1. One refresh replayed (round 1's pool, round 0's encoder), two pool draws: the occupancy-weighted retrieval with
#    ranking by CSLS (csls_k 10, the sixth session's value, not tuned here); embedded data on the detector's boxes,
#    the shape-only data on GT boxes (shapes_r01_mining.yaml of ../mining_occupancy_retrieval_cpu_2026-12-02):
for S in 0 1; do
  python benchmarks/mining_refresh_probe.py runs/em/r01_mining/config.yaml --seed $S --out refresh_probe_csls.jsonl \
    --settings '{"weighted 0.2": {"retrieval_occupancy_floor": 0.2}, "weighted 0.2 + csls 10": {"retrieval_occupancy_floor": 0.2, "csls_k": 10}, "plain + csls 10": {"csls_k": 10}}'
  python benchmarks/mining_refresh_probe.py runs/em/r01_mining/config.yaml --seed $S --out refresh_probe_csls.jsonl \
    --settings '{"weighted 0.2 + csls 10 + mutual 10": {"retrieval_occupancy_floor": 0.2, "csls_k": 10, "mutual_k": 10}, "weighted 0.2 + csls 5": {"retrieval_occupancy_floor": 0.2, "csls_k": 5}}'
  python benchmarks/mining_refresh_probe.py shapes_r01_mining.yaml --seed $S --out refresh_probe_shapes_csls.jsonl \
    --settings '{"weighted 0.2 + csls 10": {"retrieval_occupancy_floor": 0.2, "csls_k": 10}, "plain + csls 10": {"csls_k": 10}}'
done
# 2. Rounds 1-4 from the same view prediction, detector and round 0, seeds 0 and 1, with the mining config of
#    ../mining_occupancy_retrieval_cpu_2026-12-02 (retrieval_occupancy_floor 0.2) and the quantizer with restarts:
sed 's/^    retrieval_occupancy_floor: null .*$/    retrieval_occupancy_floor: 0.2/' configs/stages/mining.yaml > mining_occ.yaml
sed 's/^    csls_k: null  /    csls_k: 10    /' mining_occ.yaml > mining_occ_csls.yaml
sed 's/^    em_restarts: 1$/    em_restarts: 4/' configs/stages/quantizer.yaml > q_restarts4.yaml
echo "seed_everything: 1" > seed1.yaml
for A in oq ocq; do
  M=mining_occ.yaml; [ $A = ocq ] && M=mining_occ_csls.yaml
  for S in 0 1; do
    mkdir -p runs/em_${A}_s$S
    for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r runs/em/$d runs/em_${A}_s$S/; done
    EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
    threedq em --rounds 4 --work_dir runs/em_${A}_s$S --mining_config $M --quantizer_config q_restarts4.yaml $EXTRA \
      --resume true                                                              # metrics_${A}_seed$S.json
  done
done
# 3. Table and picture (runs/ref_s1 and runs/r_s{0,1}: folders holding only the metrics.json of
#    ../quantizer_restarts_cpu_2026-12-02; runs/em_occ_s{0,1}: the runs of ../mining_occupancy_retrieval_cpu_2026-12-02):
python benchmarks/em_seeds.py --arm "default miner=runs/em runs/ref_s1" --arm "restarts (em_restarts 4)=runs/r_s0 runs/r_s1" \
  --arm "occupancy-weighted retrieval=runs/em_occ_s0 runs/em_occ_s1" \
  --arm "occupancy-weighted retrieval + restarts=runs/em_oq_s0 runs/em_oq_s1" --png docs/img/em_seeds_occupancy_restarts.png
# (ocq: seed 0 only this session; seed 1 was not run for time.)
# 4. Table 2 on GT boxes (487 test objects; banks fitted with the settings of the oq seed-0 round-4 quantizer, em_restarts 4):
threedq eval --ckpt runs/em_oq_s0/r04_quantizer/checkpoints/last.ckpt --out runs/fid_gt_oq --curve_k '[]' --baselines false \
  --encoders '{"view prediction": "runs/em/00_viewpred/checkpoints/last.ckpt", "round 4, default miner, seed 0": "runs/em/r04_mining/checkpoints/last.ckpt", "round 4, occupancy-weighted retrieval + restarts, seed 0": "runs/em_oq_s0/r04_mining/checkpoints/last.ckpt", "round 4, occupancy-weighted retrieval + restarts, seed 1": "runs/em_oq_s1/r04_mining/checkpoints/last.ckpt", "round 4, + CSLS, seed 0": "runs/em_ocq_s0/r04_mining/checkpoints/last.ckpt"}'
# -> table2_gt_boxes.md / .json (9.6 min, 17.3 GiB peak)
