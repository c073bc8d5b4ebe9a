#!/bin/bash
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
date -u +%FT%TZ > /tmp/mj/start
pip install torch==2.13.0 -e . > /tmp/mj/pip.log 2>&1
date -u +%FT%TZ > /tmp/mj/em_start
/usr/bin/time -v threedq em --rounds 4 > /tmp/mj/em.log 2> /tmp/mj/em.err
echo $? > /tmp/mj/rc
date -u +%FT%TZ > /tmp/mj/end
