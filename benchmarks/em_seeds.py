"""Several ``threedq em`` runs per arm (one per seed) side by side: Table 3 per round, the mean and range over seeds.

Reads each run's ``metrics.json`` (Table 3's rows, few-shot accuracy, the mining stage's seconds from
``rNN_mining/stage.json``) or the rows kept in ``benchmarks/results/<folder>/rows.jsonl``; measures nothing itself.
Per arm and round it prints the mean (range) over the arm's runs, then per run whether every round's strict and
paper-protocol precision@10 stayed at or above its round 0, and with ``--png`` draws the per-seed curves.

    python benchmarks/em_seeds.py --arm "base=runs/em_s0 runs/em_s1" --arm "vp reg.=runs/vp_s0 runs/vp_s1" \\
        --png docs/img/em_seeds.png
    python benchmarks/em_seeds.py --rows benchmarks/results/occupancy_pairs_amd_2026-12-05/rows.jsonl
    R=benchmarks/results/occupancy_pairs_amd_2026-12-05/rows.jsonl
    python benchmarks/em_seeds.py --arm "occ10=$R#metrics_occ10_seed0.json $R#metrics_occ10_seed1.json" \\
        --arm "new=runs/new_s0 runs/new_s1"

A run is a work dir, a copy of its ``metrics.json`` (any name ending ``.json``), or ``ROWS.jsonl#RUN``: the row of a
results folder whose ``run`` is ``RUN``. ``--rows`` takes every row of a file, one arm per data set and arm.

Convention: rounds as in Table 3 (0 = the view-prediction encoder, 1..R = after each EM round); a value a run does
not have is left out of the mean.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from _common import machine, read_rows, table

#: (column, name in the table)
METRICS = (("precision_at_10", "strict p@10"), ("precision_at_10_paper", "paper p@10"),
           ("same_object_top1", "same-object top-1"), ("hungarian_acc", "Hungarian"), ("fewshot_acc", "few-shot"),
           ("map_50", "mAP@0.5"), ("mining_seconds", "mining s"))


def read_run(work_dir: str | Path) -> dict[int, dict[str, float | None]]:
    """``{round: {metric: value}}`` of one ``threedq em`` work dir (its ``metrics.json``), of a copy of a
    ``metrics.json`` under another name (a ``.json`` file), or of a kept row (``ROWS.jsonl#RUN``)."""
    rows_file, sep, name = str(work_dir).partition(".jsonl#")
    if sep:
        row = next((r for r in read_rows(rows_file + ".jsonl") if r["run"] == name), None)
        if row is None:
            raise SystemExit(f"em_seeds: {rows_file}.jsonl: no row of run {name!r}")
        return {r: {k: (row.get(k) or [None] * len(row["rounds"]))[i] for k, _ in METRICS}
                for i, r in enumerate(row["rounds"])}
    path = Path(work_dir) if str(work_dir).endswith(".json") else Path(work_dir) / "metrics.json"
    if not path.is_file():
        raise SystemExit(f"em_seeds: {path}: no metrics.json (a run writes it when its last round ends)")
    try:
        m = json.loads(path.read_text())
        rows = m["table3"]
    except (json.JSONDecodeError, KeyError) as e:
        raise SystemExit(f"em_seeds: {path}: not a threedq em metrics.json ({type(e).__name__}: {e})") from e
    results = [m.get("round0_result")] + list(m.get("round_results") or [])
    mining = list(m.get("mining_results") or [])
    out: dict[int, dict[str, float | None]] = {}
    for row in rows:
        r = int(row["round"])
        cells = {k: row.get(k) for k, _ in METRICS[:4] + METRICS[5:6]}
        res = results[r] if r < len(results) and results[r] else {}
        cells["fewshot_acc"] = res.get("quantization", {}).get("threedq", {}).get("fewshot_acc")
        stage = path.parent / f"r{r:02d}_mining" / "stage.json"
        if r and stage.is_file():
            cells["mining_seconds"] = json.loads(stage.read_text()).get("seconds")
        else:  # the copy of metrics.json alone: the seconds it recorded for the round's mining stage
            cells["mining_seconds"] = mining[r - 1].get("seconds") if 0 < r <= len(mining) else None
        out[r] = cells
    return out


def mean_range(values: list[float | None]) -> tuple[float, float, int] | None:
    """(mean, max - min, count) of the values that are not ``None``; ``None`` if there are none."""
    v = [float(x) for x in values if x is not None]
    if not v:
        return None
    return sum(v) / len(v), max(v) - min(v), len(v)


def holds_round0(run: dict[int, dict[str, float | None]], metric: str) -> bool | None:
    """Whether every round after 0 has ``metric`` >= round 0's (``None`` without round 0 or later rounds)."""
    base = run.get(0, {}).get(metric)
    later = [c.get(metric) for r, c in run.items() if r > 0 and c.get(metric) is not None]
    if base is None or not later:
        return None
    return all(v >= base for v in later)


def summary_markdown(arms: dict[str, list[str]], runs: dict[str, list[dict[int, dict[str, float | None]]]]) -> str:
    """Per round and arm the mean (range) over its runs; then each run's round-0 check."""
    body, checks = [], []
    for r in sorted({r for rs in runs.values() for run in rs for r in run}):
        for arm, rs in runs.items():
            stats = [(mean_range([run.get(r, {}).get(key) for run in rs]), 1 if key == "mining_seconds" else 3)
                     for key, _ in METRICS]
            if n := max((mr[2] for mr, _ in stats if mr is not None), default=0):
                body.append([r, arm, n, *("-" if mr is None else f"{mr[0]:.{d}f} ({mr[1]:.{d}f})" if mr[2] > 1
                                          else f"{mr[0]:.{d}f}" for mr, d in stats)])
    for arm, rs in runs.items():
        for d, run in zip(arms[arm], rs):
            checks.append([arm, d, *("-" if (h := holds_round0(run, k)) is None else ("yes" if h else "no")
                                     for k in ("precision_at_10", "precision_at_10_paper"))])
    return "\n".join([table(["round", "arm", "runs", *(name for _, name in METRICS)], body), "",
                      table(["arm", "run", "every round >= round 0, strict", "paper protocol"], checks)])


def figure(arms: dict[str, list[str]], runs: dict[str, list[dict[int, dict[str, float | None]]]]) -> Any:
    """Per-seed curves of strict and paper precision@10, same-object top-1 and Hungarian accuracy, one colour an arm."""
    from threedq.viz.curves import runs_figure

    panels = [(name, {arm: [sorted((r, c[key]) for r, c in run.items() if c.get(key) is not None) for run in rs]
                      for arm, rs in runs.items()}, []) for key, name in METRICS[:4]]
    return runs_figure(panels, "EM round", xticks=sorted({r for rs in runs.values() for run in rs for r in run}))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arm", action="append", default=[], metavar="NAME=DIR [DIR ...]",
                    help="an arm: its name and its runs' work dirs (or copies of their metrics.json, any name "
                         "ending .json, or ROWS.jsonl#RUN), separated by spaces (repeatable)")
    ap.add_argument("--rows", action="append", default=[], type=Path, metavar="ROWS.jsonl",
                    help="every run of a results folder's rows file, one arm per data set and arm (repeatable)")
    ap.add_argument("--png", type=Path, default=None, help="write the per-seed curves here")
    args = ap.parse_args(argv)
    arms: dict[str, list[str]] = {}
    for spec in args.arm:
        name, sep, dirs = spec.partition("=")
        if not sep or not name.strip() or not dirs.split():
            raise SystemExit(f"em_seeds: --arm {spec!r}: expected NAME=DIR [DIR ...]")
        arms[name.strip()] = dirs.split()
    for path in args.rows:
        for row in read_rows(path):
            arms.setdefault(f"{row['data']}: {row['arm']}", []).append(f"{path}#{row['run']}")
    if not arms:
        ap.error("give --arm or --rows")
    runs = {arm: [read_run(d) for d in dirs] for arm, dirs in arms.items()}
    print(f"# threedq em runs per arm: mean (range) over runs; {machine()} (where this table was printed, "
          "not necessarily where the runs ran)")
    print(summary_markdown(arms, runs))
    if args.png is not None:
        from threedq.viz.png import write_png

        write_png(args.png, figure(arms, runs))
        print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
