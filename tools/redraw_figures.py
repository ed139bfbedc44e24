"""Redraw a run's figures from its saved outputs, with the current figure code (pushtorch/experiments/report.py).

A run directory holds ``results.json`` (every group's n, mean and std) and, for runs made since it was
added, ``figure_data.npz`` (per-sample H_acc and the training pushes). From both, every figure is redrawn
as a fresh run would draw it; from ``results.json`` alone, the bar figures are redrawn with intervals from
each group's n, mean and std, and the training figures cannot be (their pushes were not kept): those PNGs
are left as they are and listed. ``report.md`` is not rewritten (it needs the run's other extras); the
figures keep their names, so its links stay valid.

    .venv/bin/python tools/redraw_figures.py docs/results/paper/*/
    .venv/bin/python tools/redraw_figures.py runs/quickstart
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from a checkout without installing
    sys.path.insert(0, str(ROOT))

from pushtorch.experiments.report import FIGURE_DATA, make_figures, read_figure_data  # noqa: E402


def redraw(run_dir: Path) -> dict[str, list[str]]:
    """Redraw ``run_dir``'s figures; returns the names redrawn and those left as they were.

    Raises:
        SystemExit: ``run_dir`` has no results.json.
    """
    results = run_dir / "results.json"
    if not results.is_file():
        raise SystemExit(f"{run_dir}: no results.json; is it a run directory?")
    records = json.loads(results.read_text())["records"]
    data = run_dir / FIGURE_DATA
    extras = read_figure_data(data) if data.is_file() else {}
    before = {p.name for p in (run_dir / "figures").glob("*.png")}
    redrawn = sorted(p.name for p in make_figures(run_dir, records, extras))
    return {"redrawn": redrawn, "left as they were": sorted(before - set(redrawn)),
            "source": [f"results.json + {FIGURE_DATA}" if extras else "results.json only"]}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", type=Path, help="run directories (with results.json)")
    args = parser.parse_args(argv)
    for run_dir in args.run_dirs:
        outcome = redraw(run_dir)
        print(f"{run_dir} ({outcome['source'][0]})")
        print(f"  redrawn: {', '.join(outcome['redrawn']) or '—'}")
        if outcome["left as they were"]:
            print(f"  left as they were (their data are not in the run directory): "
                  f"{', '.join(outcome['left as they were'])}")


if __name__ == "__main__":
    main()
