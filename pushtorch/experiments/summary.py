"""The summary a run prints before its paths (paper, Experimental Results): per test object, pushtorch's H_acc
and linear error against the strongest peer that sees no more than the method, and whether each claim held.

The peer is the non-oracle baseline with the lowest pooled H_acc on the object's prediction records
(:data:`~pushtorch.experiments.tables.ORACLES` see the true mesh or physics and are left out); the claims are
the run's acceptance checks (:func:`~pushtorch.experiments.results.acceptance_checks`) that name the object.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from pushtorch.experiments.results import thrown_counts
from pushtorch.experiments.statistics import pool
from pushtorch.experiments.tables import ORACLES, ordered, primary, select

__all__ = ["summary_table"]

#: Records of these predictors are the method itself (or a variant of it), not its peers.
OURS = frozenset({"pushtorch", "pushtorch_shapes", "pushtorch_library"})


def summary_table(records: Sequence[Mapping[str, Any]], checks: Sequence[Mapping[str, Any]],
                  thrown: Sequence[Mapping[str, Any]] = ()) -> str:
    """A compact text table (one row per object that has prediction records), a line for the other claims and
    one counting the invalid conditions (predicted starts backed off too far) per method, as report.md does
    (``thrown``: results.json's entries); empty without prediction records."""
    predictions = select(primary(records), task="prediction")
    rows = []
    for obj in ordered(r["object"] for r in predictions):
        ours = pool(select(predictions, object=obj, method="pushtorch"))
        peers = {m: pool(select(predictions, object=obj, method=m))
                 for m in {r["method"] for r in predictions if r["object"] == obj} - OURS - ORACLES}
        peer = min(peers, key=lambda m: peers[m]["hacc_mean"]) if peers else None
        own = [c for c in checks if str(c["object"]).split(":")[0].split(",")[0] == obj]
        held = sum(c["passed"] for c in own)
        rows.append((obj, f"{ours['hacc_mean']:.3f}", f"{ours['linear_cm']:.2f}",
                     peer or "—", f"{peers[peer]['hacc_mean']:.3f}" if peer else "—",
                     f"{peers[peer]['linear_cm']:.2f}" if peer else "—", f"{held}/{len(own)}"))
    if not rows:
        return ""
    head = ("object", "pushtorch H_acc", "cm", "strongest peer", "H_acc", "cm", "claims held")
    widths = [max(len(str(row[i])) for row in [head, *rows]) for i in range(len(head))]
    lines = ["  ".join(str(cell).ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
             for row in [head, *rows]]
    others = [c for c in checks if not any(str(c["object"]).split(":")[0].split(",")[0] == row[0] for row in rows)]
    if others:
        lines.append(f"other claims held: {sum(c['passed'] for c in others)}/{len(others)} "
                     f"({', '.join(sorted({c['check'] for c in others}))})")
    invalid: dict[str, list[int]] = {}
    for (_, method), c in thrown_counts(thrown).items():
        if c["starts"]:
            counts = invalid.setdefault(method, [0, 0])
            counts[0] += c["invalid_starts"]
            counts[1] += c["starts"]
    if any(n for n, _ in invalid.values()):
        lines.append("invalid conditions (start backed off too far; scored all the same): "
                     + ", ".join(f"{m} {n}/{total}" for m, (n, total) in sorted(invalid.items())))
    return "\n".join(lines)
