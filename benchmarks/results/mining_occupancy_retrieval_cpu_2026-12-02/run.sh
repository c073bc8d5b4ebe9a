#!/bin/bash
# #63 / docs/studies/mined-pairs.md, "Retrieval on occupancy-weighted crops": the commands behind the files here.
# Machine: 2 vCPU AMD EPYC with AVX2 only (float32 throughout), torch 2.13.0 CPU, 2026-12-02, alone on the machine.
# Reference seed 0 = the README's main job from a fresh clone of 28440ce (git clone, new venv, pip install
# torch==2.13.0 -e .): /usr/bin/time -v threedq em --rounds 4 -> runs/em; its metrics.json equals
# ../quantizer_restarts_cpu_2026-12-02/metrics_default_seed0.json to the last digit, so that file and its seed 1
# (metrics_default_seed1.json) are the reference rows.
# 1. One refresh replayed (round 1's pool, round 0's encoder, the detector's boxes), two pool draws, three retrievals:
for S in 0 1; do
  python benchmarks/mining_refresh_probe.py runs/em/r01_mining/config.yaml --seed $S --out refresh_probe.jsonl \
    --settings '{"plain": {}, "weighted 0.2": {"retrieval_occupancy_floor": 0.2}, "weighted 0": {"retrieval_occupancy_floor": 0.0}}'
done
# 2. Rounds 1-4 with retrieval_occupancy_floor 0.2 (the quantizer's floor, not tuned), from the same view prediction,
#    detector and round 0 (code at 0ddc417):
sed 's/^    retrieval_occupancy_floor: null .*$/    retrieval_occupancy_floor: 0.2/' configs/stages/mining.yaml > mining_occ.yaml
echo "seed_everything: 1" > seed1.yaml
for S in 0 1; do
  mkdir -p runs/em_occ_s$S
  for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r runs/em/$d runs/em_occ_s$S/; done
done
threedq em --rounds 4 --work_dir runs/em_occ_s0 --mining_config mining_occ.yaml --resume true        # metrics_occ_seed0.json
threedq em --rounds 4 --work_dir runs/em_occ_s1 --mining_config mining_occ.yaml --extra_configs seed1.yaml \
  --resume true                                                                                       # metrics_occ_seed1.json
# 3. The shape-only data (configs/data/shapes.yaml; made on first use): the same replay on GT boxes with round 0's
#    encoder (trained on the embedded data): shapes_r01_mining.yaml = runs/em/r01_mining/config.yaml with the data
#    section of configs/data/shapes.yaml and boxes: gt.
for S in 0 1; do
  python benchmarks/mining_refresh_probe.py shapes_r01_mining.yaml --seed $S --out refresh_probe_shapes.jsonl \
    --settings '{"plain": {}, "weighted 0.2": {"retrieval_occupancy_floor": 0.2}}'
done
# 4. Table and picture (runs/ref_s1 holds only ../quantizer_restarts_cpu_2026-12-02/metrics_default_seed1.json as metrics.json):
python benchmarks/em_seeds.py --arm "default miner=runs/em runs/ref_s1" \
  --arm "retrieval on occupancy-weighted crops=runs/em_occ_s0 runs/em_occ_s1" --png docs/img/em_seeds_occupancy_retrieval.png
