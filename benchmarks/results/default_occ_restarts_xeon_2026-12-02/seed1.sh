#!/bin/bash
# #63 on the Xeon: seed 1 of the new default and of the old default (floor null, 1 restart), rounds 1-4 from the main job's
# view prediction and detector; round 0 of each arm at seed 0 (shared by its seeds, as in the references).
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
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
