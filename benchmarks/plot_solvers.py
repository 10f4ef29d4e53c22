"""Plot the raw output of ``benchmarks/solvers.py`` (a Markdown file) as PNGs.

Run by hand::

    python benchmarks/plot_solvers.py benchmarks/results/solvers-2026-11-22.md --out benchmarks/results

Writes ``<stem>-xpbd.png`` (XPBD ns per tet-iteration vs mesh size: our Jacobi and
Gauss-Seidel and the peers measured in the same run, and the peerbench figures of
``/work/shared/peerbench/README.md`` as quoted in that file's ratio table) and
``<stem>-gradient.png`` (unrolled gradient / forward ratios). Only parses the file: nothing is
re-measured.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path


def _tables(text: str) -> list[list[list[str]]]:
    tables, cur = [], []
    for line in text.splitlines():
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if not all(re.fullmatch(r"-+", c) for c in cells):
                cur.append(cells)
        elif cur:
            tables.append(cur)
            cur = []
    if cur:
        tables.append(cur)
    return tables


def parse(path: Path) -> dict:
    tabs = _tables(path.read_text())
    out: dict = {"xpbd": {}, "peers": {}, "gradient": []}
    for t in tabs:
        head = t[0]
        if head[:3] == ["n", "tets", "implementation"]:
            for row in t[1:]:
                out["xpbd"].setdefault(row[2], []).append((int(row[1]), float(row[3])))
        elif head[0].startswith("peer"):
            sizes = [int(h.split("=")[1]) for h in head[1:]]
            for row in t[1:]:
                vals = [float(c.split("/")[0]) for c in row[1:]]
                out["peers"][row[0]] = list(zip(sizes, vals))
        elif head[:3] == ["method", "iterations", "tets"]:
            for row in t[1:]:
                out["gradient"].append((row[0], int(row[1]), float(row[5]), float(row[7])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path)
    ap.add_argument("--out", type=Path, default=None, help="directory of the PNGs (default: beside the results)")
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    data = parse(args.results)
    out = args.out or args.results.parent
    stem = args.results.stem
    tets_of_n = {}
    for pts in data["xpbd"].values():
        for tets, _ in pts:
            n = round((tets / 6) ** (1 / 3))
            tets_of_n[n] = tets
    fig = Figure(figsize=(9.0, 4.4), layout="constrained")
    ax = fig.subplots()
    for i, (name, pts) in enumerate(sorted(data["xpbd"].items())):
        x, y = zip(*sorted(pts))
        bold = name.startswith("difftissue")
        ax.plot(x, y, "o-", lw=2.0 if bold else 1.2, color=f"C{i}", label=f"{name} (same run)")
    for i, (name, pts) in enumerate(sorted(data["peers"].items())):
        x = [tets_of_n.get(n, 6 * n**3) for n, _ in pts]
        ax.plot(x, [v for _, v in pts], "s--", mfc="none", lw=1.0, color=f"C{i + 5}", label=f"peerbench: {name}")
    ax.set_xscale("log")
    ticks = sorted(tets_of_n.values())
    ax.set_xticks(ticks, [f"{t:,}" for t in ticks])
    ax.minorticks_off()
    ax.set_ylim(0, None)
    ax.set_xlabel("tets")
    ax.set_ylabel("ns per tet-iteration (lower is better)")
    ax.set_title("XPBD, one CPU thread, float32 (peerbench workload)")
    ax.legend(frameon=False, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    xpbd_png = out / f"{stem}-xpbd.png"
    fig.savefig(xpbd_png, dpi=110)
    print(xpbd_png)
    if data["gradient"]:
        fig = Figure(figsize=(5.6, 3.8), layout="constrained")
        ax = fig.subplots()
        labels = [f"{m}\n{it} it." for m, it, _, _ in data["gradient"]]
        x = range(len(labels))
        ax.bar([i - 0.2 for i in x], [g for _, _, g, _ in data["gradient"]], 0.4, label="jax.grad / forward")
        ax.bar([i + 0.2 for i in x], [j for _, _, _, j in data["gradient"]], 0.4, label="jax.jacfwd / forward")
        ax.axhline(3.0, color="C3", lw=1, ls=":", label="target 3x")
        ax.set_xticks(list(x), labels, fontsize=8)
        ax.set_ylabel("time ratio to the forward pass")
        ax.set_title("Unrolled XPBD gradient, 3,072 tets")
        ax.legend(frameon=False, fontsize=8)
        grad_png = out / f"{stem}-gradient.png"
        fig.savefig(grad_png, dpi=110)
        print(grad_png)


if __name__ == "__main__":
    main()
