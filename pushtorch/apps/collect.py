"""Combine the ``results.json`` of runs and sweeps into one tidy table: ``pushtorch-collect``.

Not a paper section: the step after a Hydra multirun (README, "A sweep over training priors"). Each job of a
sweep writes its own ``results.json`` (records of the paper's tables) with the command-line overrides it ran
with; this module finds them under the folders it is given and writes

    collected.csv                 one row per (job, record): the job folder, the experiment, one column per
                                  override key (the swept values), then the record's fields
    collected.md                  the same table in markdown
    collected_<experiment>.png    per experiment, prediction H_acc by object, one bar per job

Usage::

    pushtorch-collect runs/multirun/2026-11-25/10-00-00-000000 [more folders] [--out folder]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pushtorch.errors import PushtorchError

__all__ = ["CollectedRun", "collect", "find_results", "main", "parse_override", "parser", "write_tables"]

_LEADING = ("++", "+", "~")  # Hydra's add / force-add / delete prefixes, not part of the key


@dataclass(frozen=True)
class CollectedRun:
    """One run's ``results.json``: where it is, its experiment, its overrides as ``{key: value}``, its records."""

    folder: Path
    experiment: str
    overrides: dict[str, str]
    records: list[dict]


def parse_override(text: str) -> tuple[str, str]:
    """``"model.friction=low"`` → ``("model.friction", "low")``; ``"~a.b"`` → ``("a.b", "<deleted>")``."""
    body = text
    for prefix in _LEADING:
        if body.startswith(prefix):
            body = body[len(prefix):]
            break
    key, sep, value = body.partition("=")
    return key, value if sep else "<deleted>"


def _overrides_of(results_path: Path, payload: Mapping[str, Any]) -> list[str]:
    """The run's overrides: from ``results.json``, else (runs made before it carried them) ``.hydra/``."""
    if "overrides" in payload:
        return [str(o) for o in payload["overrides"]]
    hydra_file = results_path.parent / ".hydra" / "overrides.yaml"
    if hydra_file.is_file():
        from omegaconf import OmegaConf

        return [str(o) for o in OmegaConf.load(hydra_file)]
    return []


def find_results(folders: Sequence[str | Path]) -> list[CollectedRun]:
    """Every ``results.json`` at or below ``folders``, in folder order then path order.

    Raises:
        PushtorchError: a folder does not exist, holds no ``results.json``, or one is not a pushtorch
            results file.
    """
    runs: list[CollectedRun] = []
    seen: set[Path] = set()
    for folder in folders:
        folder = Path(folder)
        if not folder.exists():
            raise PushtorchError(f"{folder}: no such folder")
        paths = [folder] if folder.is_file() else sorted(folder.rglob("results.json"))
        if not paths:
            raise PushtorchError(f"{folder}: holds no results.json (is it a run or sweep folder?)")
        for path in paths:
            path = path.resolve()
            if path in seen:
                continue
            seen.add(path)
            try:
                payload = json.loads(path.read_text())
                records = [dict(r) for r in payload["records"]]
                experiment = str(payload["experiment"])
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise PushtorchError(f"{path}: not a pushtorch results.json ({exc})") from exc
            overrides = dict(parse_override(o) for o in _overrides_of(path, payload))
            runs.append(CollectedRun(path.parent, experiment, overrides, records))
    return runs


def _job_name(run: CollectedRun, roots: Sequence[Path]) -> str:
    for root in roots:
        try:
            relative = run.folder.relative_to(root)
        except ValueError:
            continue
        return str(relative) if str(relative) != "." else run.folder.name
    return str(run.folder)


def collect(folders: Sequence[str | Path]) -> tuple[list[str], list[dict[str, Any]]]:
    """The tidy table of every record under ``folders``: ``(columns, rows)``.

    Columns: ``job``, ``experiment``, the override keys (those whose values differ between jobs first, in
    order of first appearance; one named like a record field, e.g. ``model=quick``, as ``override:model``),
    then the record fields in order of first appearance. A job lacking an override key gets an empty cell.
    """
    runs = find_results(folders)
    roots = [Path(f).resolve() for f in folders]
    override_keys: list[str] = []
    for run in runs:
        override_keys += [k for k in run.overrides if k not in override_keys]
    varying = [k for k in override_keys if len({run.overrides.get(k) for run in runs}) > 1]
    override_columns = varying + [k for k in override_keys if k not in varying]
    record_keys = list(dict.fromkeys(k for run in runs for record in run.records for k in record))
    # an override key named like a record field (`model=quick`, `object=mesh`) must not overwrite the field
    column_of = {k: f"override:{k}" if k in record_keys or k in ("job", "experiment") else k
                 for k in override_columns}
    rows: list[dict[str, Any]] = []
    for run in runs:
        job = _job_name(run, roots)
        for record in run.records:
            row = {"job": job, "experiment": run.experiment}
            row.update({column_of[k]: run.overrides.get(k, "") for k in override_columns})
            row.update(record)
            rows.append(row)
    return ["job", "experiment", *column_of.values(), *record_keys], rows


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.4g}"
    if isinstance(value, (dict, list)):
        return json.dumps(value, separators=(",", ":"))
    return str(value)


def write_tables(columns: Sequence[str], rows: Sequence[Mapping[str, Any]], out_dir: str | Path) -> list[Path]:
    """``collected.csv``, ``collected.md`` and one ``collected_<experiment>.png`` per experiment in ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = out_dir / "collected.csv"
    with open(csv_path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(columns), extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({c: (json.dumps(row[c]) if isinstance(row.get(c), (dict, list)) else row.get(c, ""))
                             for c in columns})
    md_path = out_dir / "collected.md"
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell(row.get(c)).replace("|", "\\|") for c in columns) + " |" for row in rows]
    md_path.write_text("\n".join(lines) + "\n")
    return [csv_path, md_path, *_figures(columns, rows, out_dir)]


def _figures(columns: Sequence[str], rows: Sequence[Mapping[str, Any]], out_dir: Path) -> list[Path]:
    """Per experiment: mean displacement H_acc of pushtorch's predictions (or of every method's, if pushtorch
    made none) by object, one bar per job, log axis when the values span more than a decade."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for experiment in dict.fromkeys(r["experiment"] for r in rows):
        chosen = [r for r in rows if r["experiment"] == experiment and r.get("task") in ("prediction", "selection")
                  and isinstance(r.get("hacc_mean"), (int, float))
                  and r.get("metric") in (None, "", "displacement")]  # the primary score (report.primary)
        if any(r.get("method") == "pushtorch" for r in chosen):
            chosen = [r for r in chosen if r.get("method") == "pushtorch"]
        if not chosen:
            continue
        objects = list(dict.fromkeys(str(r["object"]) for r in chosen))
        series = list(dict.fromkeys((r["job"], r.get("method")) for r in chosen))
        fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(objects) + 2.0), 4.0), constrained_layout=True)
        width = 0.8 / len(series)
        colours = plt.get_cmap("tab20")
        values = []
        for k, (job, method) in enumerate(series):
            xs, means, counts = [], [], []
            for i, obj in enumerate(objects):
                group = [r for r in chosen if r["job"] == job and r.get("method") == method and str(r["object"]) == obj]
                if not group:
                    continue
                n = sum(int(r.get("n") or 0) for r in group)
                mean = sum(float(r["hacc_mean"]) * int(r.get("n") or 1) for r in group) / max(
                    1, sum(int(r.get("n") or 1) for r in group))
                xs.append(i - 0.4 + width * (k + 0.5))
                means.append(mean)
                counts.append(n)
            label = job if len({m for _, m in series}) == 1 else f"{job} · {method}"
            ax.bar(xs, means, width, color=colours(k % 20), label=label)
            for x, m, n in zip(xs, means, counts, strict=True):
                ax.annotate(f"n={n}", (x, m), ha="center", va="bottom", fontsize=6, rotation=90)
            values += means
        positive = [v for v in values if v > 0]
        if positive and max(positive) / min(positive) > 10:
            ax.set_yscale("log")
        ax.set_xticks(range(len(objects)), objects)
        ax.set_ylabel("mean H_acc (lower is better)")
        ax.set_title(f"{experiment}: {len(series)} jobs")
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=7, frameon=False)
        path = out_dir / f"collected_{experiment}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        paths.append(path)
    return paths


class _OneLineParser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (as every pushtorch app's errors are) and exit 2."""

    def error(self, message: str):
        self.exit(2, f"pushtorch-collect: {message} (usage: {self.format_usage().strip().removeprefix('usage: ')})\n")


def parser() -> argparse.ArgumentParser:
    """The command line of ``pushtorch-collect``."""
    parser = _OneLineParser(prog="pushtorch-collect", description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", help="run or sweep folders (searched for results.json)")
    parser.add_argument("--out", default=None,
                        help="where to write the table and figures (default: the folder given, or . for several)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``pushtorch-collect FOLDER... [--out DIR]``; a user error exits with status 2 and one line."""
    args = parser().parse_args(argv)
    out = args.out if args.out is not None else (args.folders[0] if len(args.folders) == 1 else ".")
    try:
        columns, rows = collect(args.folders)
        written = write_tables(columns, rows, out)
    except PushtorchError as exc:
        print(f"pushtorch-collect: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"pushtorch-collect: {exc.filename or out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"rows: {len(rows)}")
    for path in written:
        print(f"wrote: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
