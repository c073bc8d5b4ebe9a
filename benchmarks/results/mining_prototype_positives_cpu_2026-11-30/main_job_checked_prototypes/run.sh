#!/bin/bash
# fresh clone of 9f5ad77 in /tmp/fc8/main, ../shared beside it; mining_checked_proto.yaml = configs/stages/mining_checked.yaml with prototype_weight: 1.0
d=/tmp/fc8; cd $d/main
python -m venv $d/venv; source $d/venv/bin/activate
pip install -q torch==2.13.0 -e . > $d/install.log 2>&1 || exit 1
/usr/bin/time -v -o $d/time.log threedq em --rounds 4 --mining_config $d/mining_checked_proto.yaml > $d/em.log 2>&1
echo $? > $d/em.rc
