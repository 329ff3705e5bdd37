"""The reach benchmark's table and figure from the cells that ``run.py`` wrote.

    python benchmarks/reach/report.py            # benchmarks/results/reach/{table.json,table.md,table.png}
    python benchmarks/reach/report.py --cells benchmarks/results/reach/levers --name levers

``table.json``: per problem, mesh size and network, the relative L2 error's mean and standard
deviation over seeds (and the seeds), the parameter count, the training steps and the seconds
per training step and per prediction. ``table.md``: the same as a Markdown table, with the
AMPN's ratio to each other network. The figure: the error against mesh size per problem, and
against the hop distance from the data at the largest size.
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import defaultdict
from pathlib import Path

RESULTS = Path("benchmarks/results/reach")
ORDER = ["ampn", "flat", "flat_deep", "graph_unet"]
LABELS = {
    "ampn": "AMPN",
    "flat": "flat, equal parameters",
    "flat_deep": "flat, as deep as the AMPN's layer calls",
    "graph_unet": "PyG GraphUNet",
}


def collect(cells: Path) -> dict:
    """``{(problem, size, network + tag): [cell, ...]}`` of every cell file.

    The tag (``run.py --tag``, a lever's name such as ``_norm``) comes from the file name,
    ``PROBLEM_SIZE_NETWORK{TAG}_sSEED.json``, so that tagged cells never merge with untagged ones.
    """
    out = defaultdict(list)
    for path in sorted(cells.glob("*.json")):
        cell = json.loads(path.read_text())
        prefix = f"{cell['problem']}_{cell['size']}_"
        name = path.stem[len(prefix) : path.stem.rindex("_s")]
        out[(cell["problem"], cell["size"], name)].append({**cell, "tag": name[len(cell["network"]) :]})
    return out


def summarise(groups: dict) -> list[dict]:
    """One row per (problem, size, network): mean and std over seeds."""
    rows = []
    for (problem, size, network), cells in sorted(groups.items()):
        errors = [c["rel_l2"] for c in cells]
        rows.append(
            {
                "problem": problem,
                "size": size,
                "nodes": cells[0]["nodes"],
                "levels": cells[0]["levels"],
                "network": network,
                "tag": cells[0]["tag"],
                "seeds": sorted(c["seed"] for c in cells),
                "rel_l2_mean": statistics.fmean(errors),
                "rel_l2_std": statistics.stdev(errors) if len(errors) > 1 else 0.0,
                "parameters": cells[0]["parameters"],
                "budget_seconds": cells[0]["budget_seconds"],
                "steps_mean": statistics.fmean(c["steps"] for c in cells),
                "seconds_per_step": statistics.fmean(c["seconds_per_step"] for c in cells),
                "seconds_per_prediction": statistics.fmean(c["seconds_per_prediction"] for c in cells),
                "by_hop": cells[0]["by_hop"] if len(cells) == 1 else _mean_by_hop(cells),
                "date": max(c["date"] for c in cells),
            }
        )
    return rows


def _mean_by_hop(cells: list[dict]) -> list[dict]:
    bins = defaultdict(list)
    for cell in cells:
        for b in cell["by_hop"]:
            bins[b["hops_from"]].append(b)
    return [
        {"hops_from": h, "nodes": bs[0]["nodes"], "rel_l2": statistics.fmean(b["rel_l2"] for b in bs)}
        for h, bs in sorted(bins.items())
    ]


def markdown(rows: list[dict]) -> str:
    """The table: one line per problem, size and network, the AMPN's error over each network's."""
    by_name = {(r["problem"], r["size"], r["network"]): r for r in rows}
    lines = [
        "| problem | nodes | network | parameters | relative L2 error | seeds | AMPN / this | steps "
        "| s / step | s / prediction |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    rank = {name: i for i, name in enumerate(ORDER)}
    for r in sorted(rows, key=lambda r: (r["problem"], r["size"], rank.get(r["network"], 99), r["network"])):
        # the AMPN with the same lever (tag), else the plain one
        ref = by_name.get((r["problem"], r["size"], "ampn" + r["tag"])) or by_name.get(
            (r["problem"], r["size"], "ampn")
        )
        ratio = f"{ref['rel_l2_mean'] / r['rel_l2_mean']:.2f}" if ref else "-"
        err = f"{r['rel_l2_mean']:.3f}" + (f" ± {r['rel_l2_std']:.3f}" if len(r["seeds"]) > 1 else "")
        lines.append(
            f"| {r['problem']} | {r['nodes']:,} | {LABELS.get(r['network'], r['network'])} "
            f"| {r['parameters']:,} | "
            f"{err} | {len(r['seeds'])} | {ratio} | {r['steps_mean']:.0f} | {r['seconds_per_step']:.3f} | "
            f"{r['seconds_per_prediction']:.3f} |"
        )
    return "\n".join(lines) + "\n"


COLORS = {"ampn": "C0", "flat": "C1", "flat_deep": "C2", "graph_unet": "C3"}


def _rank(network: str) -> tuple:
    """Sort key: the four networks of :data:`ORDER` first, in order, then the others by name."""
    return (network not in ORDER, ORDER.index(network) if network in ORDER else 0, network)


def figure(rows: list[dict], path: Path) -> None:
    """Error against mesh size (one panel per problem), and against hop distance at the size where
    the AMPN's error is lowest (its reach is then not limited by training)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    problems = sorted({r["problem"] for r in rows})
    fig, axes = plt.subplots(2, len(problems), figsize=(4.2 * len(problems), 7), squeeze=False)
    for col, problem in enumerate(problems):
        mine = [r for r in rows if r["problem"] == problem]
        networks = sorted(
            {r["network"] for r in mine},
            key=lambda n: (n not in ORDER, ORDER.index(n) if n in ORDER else 0, n),
        )
        ampn = [r for r in mine if r["network"] == "ampn"] or mine
        at = min(ampn, key=lambda r: r["rel_l2_mean"])["size"]
        for i, network in enumerate(networks):
            style = dict(
                color=COLORS.get(network, f"C{4 + i}"), marker="o", label=LABELS.get(network, network)
            )
            line = sorted((r for r in mine if r["network"] == network), key=lambda r: r["size"])
            axes[0, col].errorbar(
                [r["nodes"] for r in line],
                [r["rel_l2_mean"] for r in line],
                yerr=[r["rel_l2_std"] for r in line],
                capsize=3,
                **style,
            )
            for r in line:
                if r["size"] == at:
                    hop = r["by_hop"]
                    axes[1, col].plot([b["hops_from"] for b in hop], [b["rel_l2"] for b in hop], **style)
        nodes = next(r["nodes"] for r in mine if r["size"] == at)
        axes[0, col].set(xscale="log", yscale="log", xlabel="mesh nodes", title=problem)
        axes[1, col].set(xscale="symlog", yscale="log", xlabel=f"hops from the data ({nodes:,}-node meshes)")
        axes[0, col].grid(True, which="both", alpha=0.3)
        axes[1, col].grid(True, which="both", alpha=0.3)
    axes[0, 0].set_ylabel("relative L2 error")
    axes[1, 0].set_ylabel("relative L2 error (hop bin)")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cells", type=Path, default=RESULTS / "cells")
    parser.add_argument("--name", default="table", help="output file stem in benchmarks/results/reach/")
    parser.add_argument("--no-figure", action="store_true")
    args = parser.parse_args()
    rows = summarise(collect(args.cells))
    if not rows:
        raise SystemExit(f"report: no cell files in {args.cells} (run benchmarks/reach/run.py first)")
    (RESULTS / f"{args.name}.json").write_text(json.dumps(rows, indent=1))
    table = markdown(rows)
    (RESULTS / f"{args.name}.md").write_text(table)
    print(table)
    if not args.no_figure:
        figure(rows, RESULTS / f"{args.name}.png")


if __name__ == "__main__":
    main()
