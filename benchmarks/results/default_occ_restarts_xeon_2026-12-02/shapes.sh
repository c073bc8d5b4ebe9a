#!/bin/bash
# #63 on the shape-only data, the new default miner and bank: shape.md's view prediction (1700 steps) per seed, then the loop.
cd /tmp/mj/main && source /tmp/mj/venv/bin/activate
while [ ! -f /tmp/mj/seed1.done ]; do sleep 20; done
for S in 0 1; do
  V=runs/shapes_vp/seed$S
  /usr/bin/time -v -o runs/shapes_vp_s$S.time threedq fit --config stages/viewpred.yaml --config data/shapes.yaml --seed_everything=$S --trainer.max_steps=1700 \
    --trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint --trainer.callbacks.every_n_train_steps=1700 \
    --trainer.callbacks.save_top_k=-1 --trainer.callbacks.save_weights_only=true \
    --trainer.callbacks.dirpath=$V --trainer.default_root_dir=$V > runs/shapes_vp_s$S.log 2>&1
  EXTRA=""; [ $S = 1 ] && EXTRA="--extra_configs seed1.yaml"
  W=runs/shp_new_s$S
  /usr/bin/time -v -o $W.time threedq em --rounds 4 --work_dir $W --data_config data/shapes.yaml --viewpred_ckpt $V/epoch=8-step=1700.ckpt $EXTRA > $W.log 2>&1
done
echo done > /tmp/mj/shapes.done
