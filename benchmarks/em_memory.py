"""Resident memory of a ``threedq em`` run, stage by stage (Linux: it reads ``/proc``).

Runs a command (by default the main job), samples the RSS of its whole process tree every ``--interval`` seconds, and
gives each sample to the first stage of the run folder whose marker (``stage.json``, ``results.json`` or
``metrics.json``) was written after it. Prints a markdown table (stage, when it ended, peak GiB) and the run's peak,
and draws the per-stage peaks (``--png``; ``--compare`` adds the bars of an earlier run's ``--json``).

    python benchmarks/em_memory.py --work_dir runs/em --json runs/em_memory.json --png docs/img/em_memory.png \\
        -- threedq em --rounds 4
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from threedq.machine import cpu_name

MARKERS = ("stage.json", "results.json", "metrics.json")


def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])  # the command name may hold spaces and parentheses
        kids.setdefault(ppid, []).append(int(d.name))
    return kids


def tree_rss_bytes(pid: int) -> int:
    """The summed VmRSS of ``pid`` and all its descendants (0 for those that ended meanwhile)."""
    kids, todo, total = _children(), [pid], 0
    while todo:
        p = todo.pop()
        todo += kids.get(p, [])
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
                    break
        except OSError:
            continue
    return total


def stage_ends(work_dir: Path) -> list[tuple[float, str]]:
    """``(end time, folder name)`` of every stage folder of a run that has a marker, in order of end."""
    ends = []
    for d in sorted(p for p in work_dir.iterdir() if p.is_dir()):
        times = [(d / m).stat().st_mtime for m in MARKERS if (d / m).is_file()]
        if times:
            ends.append((max(times), d.name))
    return sorted(ends)


def per_stage_peaks(samples: list[tuple[float, int]], ends: list[tuple[float, str]], start: float) -> list[dict]:
    """Each stage's peak over the samples taken before it ended and after the stage before it ended."""
    rows, i = [], 0
    bounds = [*ends, (float("inf"), "after the last stage (report)")]
    for end, name in bounds:
        peak = 0
        while i < len(samples) and samples[i][0] <= end:
            peak = max(peak, samples[i][1])
            i += 1
        if peak or end != float("inf"):
            rows.append({"stage": name, "ended_s": None if end == float("inf") else round(end - start),
                         "peak_gib": round(peak / 2**30, 2)})
    return rows


def bar_chart(rows: list[dict], compare: list[dict] | None, labels: tuple[str, str]) -> bytes:
    from threedq.viz.png import figure_png, new_figure

    names = [r["stage"] for r in rows]
    fig = new_figure(figsize=(max(6.0, 0.32 * len(names) + 2), 3.4), dpi=120)
    ax = fig.add_subplot(1, 1, 1)
    x = list(range(len(names)))
    if compare:
        old = {r["stage"]: r["peak_gib"] for r in compare}
        ax.bar([i - 0.2 for i in x], [old.get(n, 0.0) for n in names], width=0.4, label=labels[1], color="#bbbbbb")
        ax.bar([i + 0.2 for i in x], [r["peak_gib"] for r in rows], width=0.4, label=labels[0], color="#1f77b4")
        ax.legend(fontsize=8)
    else:
        ax.bar(x, [r["peak_gib"] for r in rows], color="#1f77b4")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=70, fontsize=7)
    ax.set_ylabel("peak resident memory (GiB)")
    ax.grid(axis="y", alpha=0.3)
    return figure_png(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work_dir", required=True, help="the run folder the command writes (its stage folders)")
    ap.add_argument("--interval", type=float, default=1.0, help="seconds between samples")
    ap.add_argument("--json", help="write the table here (JSON)")
    ap.add_argument("--png", help="draw the per-stage peaks here")
    ap.add_argument("--compare", help="a --json table of an earlier run, drawn beside this one")
    ap.add_argument("--labels", nargs=2, default=("this run", "earlier run"), help="legend of the two runs")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="after '--': the command (default: threedq em --rounds 4)")
    args = ap.parse_args()
    command = [c for c in args.command if c != "--"] or ["threedq", "em", "--rounds", "4"]
    start = time.time()
    proc = subprocess.Popen(command)
    samples: list[tuple[float, int]] = []
    while proc.poll() is None:
        samples.append((time.time(), tree_rss_bytes(proc.pid)))
        time.sleep(args.interval)
    if proc.returncode:
        sys.exit(f"{' '.join(command)}: exit status {proc.returncode}")
    seconds = time.time() - start
    rows = per_stage_peaks(samples, stage_ends(Path(args.work_dir)), start)
    peak = max((s for _, s in samples), default=0) / 2**30
    print(f"# {' '.join(command)}: {seconds:.0f} s, peak resident memory {peak:.2f} GiB "
          f"({len(samples)} samples every {args.interval:g} s; cpu: {cpu_name()}, {os.cpu_count()} cores, "
          f"{time.strftime('%Y-%m-%d')})\n")
    print("| stage | ended (s from start) | peak GiB |\n|---|---:|---:|")
    for r in rows:
        print(f"| {r['stage']} | {'' if r['ended_s'] is None else r['ended_s']} | {r['peak_gib']:.2f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"command": command, "seconds": round(seconds), "peak_gib": round(peak, 2),
                                               "stages": rows}, indent=1) + "\n")
    if args.png:
        compare = json.loads(Path(args.compare).read_text())["stages"] if args.compare else None
        Path(args.png).write_bytes(bar_chart(rows, compare, tuple(args.labels)))


if __name__ == "__main__":
    main()
