# Sourced by the device checks: installs the carried wheels (.whl/, see run.sh) and threedq into /tmp/site.
export PYTHONUNBUFFERED=1
nvidia-smi -L
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
  .whl/*.whl || return 1
python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir --target /tmp/site . \
  || return 1
export PYTHONPATH=/tmp/site PATH=/tmp/site/bin:$PATH
python3 -c "import torch, lightning, kornia; print(torch.__version__, lightning.__version__, kornia.__version__)"
