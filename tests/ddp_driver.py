"""Run several ``threedq`` Lightning commands one after the other in the same DDP processes.

Launched by ``torchrun`` (as a user would on a cluster): every process runs each command of the plan with
:class:`~threedq.pipeline.lightning_cli.ThreeDQCLI`; rank 0 writes what each command logged (the trainer's
``callback_metrics``) to the plan's ``out`` file. Used by ``tests/test_ddp.py``::

    python -m torch.distributed.run --standalone --nproc_per_node 2 tests/ddp_driver.py plan.json
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import torch

from threedq.cli import end_process_group
from threedq.pipeline.lightning_cli import ThreeDQCLI


def main(plan_path: str) -> None:
    torch.set_num_threads(1)
    plan = json.loads(Path(plan_path).read_text())
    results = []
    for args in plan["commands"]:
        cli = ThreeDQCLI(args=args)
        results.append({k: float(v) for k, v in cli.trainer.callback_metrics.items()})
    if int(os.environ.get("RANK", "0")) == 0:
        Path(plan["out"]).write_text(json.dumps(results, indent=1))
    end_process_group()  # as the threedq command does: a group left standing can abort the process at exit


if __name__ == "__main__":
    main(sys.argv[1])
