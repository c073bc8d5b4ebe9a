#!/bin/bash
# after the shapes mining runs: the main job from a fresh clone (timed, alone), then the CSLS miner (csls_k 10) on
# the embedded data, rounds 1-4 from each seed's main-job round 0
while [ ! -f /tmp/mj/runs/shp_mining.done ]; do sleep 10; done
bash /tmp/fc6/run.sh
cd /tmp/mj; source /tmp/mjvenv/bin/activate
git pull -q /work/main main
sed 's/^    csls_k: null .*/    csls_k: 10/' configs/stages/mining.yaml > mining_csls.yaml
grep -q "csls_k: 10" mining_csls.yaml || exit 1
for S in 0 1; do
  if [ $S = 0 ]; then B=runs/em; EXTRA=""; else B=runs/em_s1base; EXTRA="--extra_configs seed1.yaml"; fi
  W=runs/em_csls_s$S; rm -rf $W; mkdir -p $W
  for d in 00_viewpred 01_viewpred_eval 02_detector 03_detector_eval r00_eval r00_quantizer; do cp -r $B/$d $W/; done
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --mining_config mining_csls.yaml $EXTRA --resume true > $W.log 2>&1
done
echo done > runs/csls.done
