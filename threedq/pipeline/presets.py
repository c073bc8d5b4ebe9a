"""The stage presets a dataset asks for: which stage config serves its kind of data.

A DataModule class names its presets (``PRESETS``: stage -> config), and a data config may name its own with a
top-level ``presets:`` mapping, which wins:

    presets:
      detector: stages/detector_scene.yaml
      mining: stages/mining_occupancy_pairs.yaml
      quantizer: stages/quantizer_multiview.yaml

``threedq em --data_config X`` runs X's presets unless a ``--<stage>_config`` is given.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import yaml

from threedq.pipeline.lightning_cli import DEFAULT_DATA_CONFIG, ConfigError, expand_configs
from threedq.pipeline.overrides import class_of

__all__ = ["STAGES", "stage_presets"]

#: the stages a preset can name
STAGES = ("detector", "mining", "quantizer")


def stage_presets(configs: Sequence[str | Path]) -> dict[str, str]:
    """``{stage: config}`` for a run of ``configs`` (the data config and any others; none: the default data's): the
    DataModule class's ``PRESETS``, then each config's ``presets:`` mapping in order (bases first).

    Raises:
        ConfigError: a ``presets`` that is not a mapping of a known stage to a config path (naming file and field).
    """
    files = expand_configs(list(configs) or [DEFAULT_DATA_CONFIG])
    out = dict(getattr(class_of(files, "data"), "PRESETS", {}))
    for path in files:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
        given = doc.get("presets")
        if given is None:
            continue
        if not isinstance(given, dict):
            raise ConfigError(f"{path}: field 'presets': expected a mapping of stage to config, got {given!r}")
        for stage, config in given.items():
            if stage not in STAGES or not isinstance(config, str) or not config:
                raise ConfigError(f"{path}: field 'presets.{stage}': expected one of the stages {STAGES} set to a "
                                  f"config path, got {stage}: {config!r}")
            out[stage] = config
    return out


#: The measurements of each mining preset on each kind of data that the results page shows: (preset, data, rows file
#: under the source tree, arm in it, how each round's bank was fitted). Machine and seeds are the rows' own.
PRESET_MEASUREMENTS = (
    ("stages/mining.yaml", "embedded", "benchmarks/results/input_pairs_default_amd_2026-12-05/rows.jsonl",
     "in10_fresh_restarts", "fresh, best of 4 (today's)"),
    ("stages/mining.yaml", "embedded", "benchmarks/results/occupancy_pairs_amd_2026-12-05/rows.jsonl", "in10",
     "warm-started"),
    ("stages/mining_occupancy_pairs.yaml", "embedded", "benchmarks/results/occupancy_pairs_amd_2026-12-05/rows.jsonl",
     "occ10", "warm-started"),
    ("stages/mining.yaml", "shape-only", "benchmarks/results/input_pairs_default_amd_2026-12-05/rows.jsonl",
     "in10_fresh_restarts", "fresh, best of 4 (today's)"),
    ("stages/mining_occupancy_pairs.yaml", "shape-only",
     "benchmarks/results/input_pairs_default_amd_2026-12-05/rows.jsonl", "occ10_fresh_restarts",
     "fresh, best of 4 (today's)"),
)


def preset_results_markdown(root: str | Path) -> str:
    """A table of the round-4 numbers of each mining preset on each kind of data (:data:`PRESET_MEASUREMENTS`), mean
    and range over the seeds; ``""`` where the source tree's rows are not there (an installed package)."""
    import json

    lines = ["| preset | data | bank of each round | seeds | strict p@10 | paper p@10 | Hungarian | few-shot | "
             "machine; runs |", "|---|---|---|---|---|---|---|---|---|"]
    for preset, data, rows, arm, bank in PRESET_MEASUREMENTS:
        path = Path(root) / rows
        if not path.is_file():
            return ""
        runs = [r for r in map(json.loads, path.read_text().splitlines()) if r.get("arm") == arm
                and r.get("data") == data]
        cells = []
        for key in ("precision_at_10", "precision_at_10_paper", "hungarian_acc", "fewshot_acc"):
            v = [r[key][-1] for r in runs]
            cells.append(f"{sum(v) / len(v):.3f} ({min(v):.3f}-{max(v):.3f})")
        machine = runs[0]["machine"].split(" (")[0]
        folder = "../" + rows.rsplit("/", 1)[0] + "/"
        lines.append(f"| `{preset}` | {data} | {bank} | {len(runs)} | {' | '.join(cells)} | {machine}; "
                     f"[{arm}]({folder}) |")
    return "\n".join(lines)
