"""Curves of the evaluation: Table 3 against the EM round, Hungarian accuracy against K (paper Fig. 3a).

- :func:`table3_figure`: ``table3.png`` of a ``threedq em`` run, written by ``threedq.pipeline.em``;
- :func:`accuracy_vs_k_figure`: ``fig3a_accuracy_vs_k.png``, by ``threedq eval`` (``threedq.pipeline.report``);
- :func:`runs_figure`: runs against rounds or steps, a line per run, by ``benchmarks/em_seeds.py`` and
  ``benchmarks/feature_recipes.py``.

Convention: matplotlib pictures are ``Figure`` objects for :func:`~threedq.viz.png.write_png`.
"""

from __future__ import annotations

from typing import Any

from threedq.viz.png import new_figure

__all__ = ["accuracy_vs_k_figure", "runs_figure", "table3_figure"]


def table3_figure(rows: list[dict[str, Any]]) -> Any:
    """Features (precision@k, both protocols), quantization (Hungarian accuracy) and detection (mAP@0.5) per round.

    Args:
        rows: Table 3's rows (``round``, ``k``, ``precision_at_10``, ``precision_at_10_paper``, ``hungarian_acc``,
            ``map_50``; a missing or ``None`` value is left out).
    """
    fig = new_figure(figsize=(5, 3.2), dpi=120)
    ax = fig.add_subplot(1, 1, 1)
    k = next((r["k"] for r in rows if r.get("k")), 10)
    for key, label in (("precision_at_10", f"features: precision@{k}, strict"),
                       ("precision_at_10_paper", f"features: precision@{k}, paper protocol"),
                       ("hungarian_acc", "quantization: Hungarian acc."), ("map_50", "detection: mAP@0.5")):
        pts = [(r["round"], r[key]) for r in rows if r.get(key) is not None]
        if pts:
            ax.plot(*zip(*pts), marker="o", label=label)
    ax.set_xlabel("EM round")
    ax.set_xticks([r["round"] for r in rows])
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def accuracy_vs_k_figure(curve: dict[str, dict[str, float]], labels: dict[str, str], num_categories: int) -> Any:
    """Hungarian accuracy of each method against the number of prototypes K.

    Args:
        curve: ``{method: {str(K): accuracy}}``. labels: display name per method (the method's key otherwise).
        num_categories: drawn as a dashed line.
    """
    fig = new_figure(figsize=(5, 3.5))
    ax = fig.add_subplot(1, 1, 1)
    for m, v in curve.items():
        ks = sorted(int(k) for k in v)
        ax.plot(ks, [v[str(k)] for k in ks], marker="o", label=labels.get(m, m))
    ax.axvline(num_categories, color="grey", lw=0.8, ls="--")
    ax.set_xlabel("number of prototypes K (dashed: number of categories)")
    ax.set_ylabel("Hungarian accuracy (test)")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    ax.set_title("Unsupervised classification accuracy vs K", fontsize=9)
    return fig


#: one colour a group of runs in :func:`runs_figure`
GROUP_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def runs_figure(panels: list[tuple[str, dict[str, list[list[tuple[float, float]]]], list[tuple[Any, ...]]]],
                xlabel: str, xticks: list[float] | None = None) -> Any:
    """Several runs of each group (an arm, a recipe) against a common axis (EM round, training steps), side by side.

    Args:
        panels: per panel ``(title, curves, references)``: ``curves`` maps a group's name to its runs, each a list of
            ``(x, y)`` points (an empty run is skipped); one colour a group, one line a run, the group named once in
            the legend; ``references`` are horizontal lines ``(y, linestyle, label)``, grey, or ``(y, linestyle,
            label, group)`` in that group's colour.
        xlabel: the x axis' name.
        xticks: the x axis' ticks (default: matplotlib's).
    """
    fig = new_figure(figsize=(3.3 * len(panels), 3.1), dpi=110)
    for p, (title, curves, references) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), p + 1)
        for g, (group, runs) in enumerate(curves.items()):
            drawn = [run for run in runs if run]
            for i, run in enumerate(drawn):
                ax.plot(*zip(*run), marker="o", ms=3, lw=1, color=GROUP_COLOURS[g % len(GROUP_COLOURS)],
                        label=group if i == 0 else None)
        for y, style, label, *group in references:
            colour = "grey"
            if group and group[0] in curves:  # a group's own reference, in its colour
                colour = GROUP_COLOURS[list(curves).index(group[0]) % len(GROUP_COLOURS)]
            ax.axhline(y, color=colour, ls=style, lw=1, label=label)
        if xticks is not None:
            ax.set_xticks(xticks)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        if p == 0:
            ax.legend(fontsize=7)
    return fig
