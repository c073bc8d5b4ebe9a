#!/bin/bash
# #63 on the Xeon: seed 1 of the new default and of the old default (floor null, 1 restart), rounds 1-4 from the main job's
# view prediction and detector; round 0 of each arm at seed 0 (shared by its seeds, as in the references).
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
# the old defaults' configs and the seed, made in the clone of af37126 (where 0.2 and 4 were the defaults):
#   sed 's/^    retrieval_occupancy_floor: 0.2 .*/    retrieval_occupancy_floor: null/' configs/stages/mining.yaml > mining_def.yaml
#   sed 's/^    em_restarts: 4/    em_restarts: 1/' configs/stages/quantizer.yaml > q1.yaml
#   echo "seed_everything: 1" > seed1.yaml
# On main (defaults reverted) the new arm needs copies with retrieval_occupancy_floor: 0.2 and em_restarts: 4 instead.
while [ ! -f /tmp/mj/rc ]; do sleep 20; done
W=runs/em_new_s1; mkdir -p $W
for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r runs/em/$d $W/; done
/usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --extra_configs seed1.yaml --resume true > $W.log 2>&1
W=runs/em_def_s0r0; mkdir -p $W
for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval; do cp -r runs/em/$d $W/; done
/usr/bin/time -v -o $W.time threedq em --rounds 0 --work_dir $W --mining_config mining_def.yaml --quantizer_config q1.yaml --resume true > $W.log 2>&1
W=runs/em_def_s1; mkdir -p $W
for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r runs/em_def_s0r0/$d $W/; done
/usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --mining_config mining_def.yaml --quantizer_config q1.yaml --extra_configs seed1.yaml --resume true > $W.log 2>&1
echo done > /tmp/mj/seed1.done
