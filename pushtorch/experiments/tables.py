"""The report's helpers on records: which records a table reads, in which order, under which labels, laid out
as markdown (paper, Experimental Results: the tables and figures lay our numbers out as the paper's do).

Every report module (:mod:`~pushtorch.experiments.results`, :mod:`~pushtorch.experiments.markdown`,
:mod:`~pushtorch.experiments.figures`, :mod:`~pushtorch.experiments.statistics`,
:mod:`~pushtorch.experiments.online_report`, :mod:`~pushtorch.experiments.transfer_report`) reads records
through these functions; this module imports none of them.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

__all__ = [
    "ORACLES",
    "frame_scores",
    "method_label",
    "ordered",
    "primary",
    "select",
    "table",
]


#: Baselines that see more than the method (the true mesh; the true pose): labelled so, never in "beats the
#: baselines". ``nominal_physics`` is the name runs before issue 15 gave the true-mesh baseline.
ORACLES = frozenset({"oracle_physics", "nominal_physics"})


def select(records: Iterable[Mapping[str, Any]], **keys: Any) -> list[Mapping[str, Any]]:
    """The records whose every key in ``keys`` has that value (a missing key reads as None), in their order."""
    return [r for r in records if all(r.get(k) == v for k, v in keys.items())]


def primary(records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The records every table, figure and check reads: pose records, and prediction and selection records
    scored on the predicted displacement (``metric: displacement``); ``metric: frame`` records (the
    estimated frame's final pose as it is) are the secondary score, shown beside the primary one."""
    return [r for r in records if r.get("metric", "displacement") == "displacement"]


def frame_scores(records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The secondary (``metric: frame``) records."""
    return [r for r in records if r.get("metric") == "frame"]


def ordered(values: Iterable[str], order: Sequence[str] = ()) -> list[str]:
    """The distinct ``values``: those named in ``order`` first, in its order, then the rest as first seen."""
    seen = list(dict.fromkeys(values))
    return [v for v in order if v in seen] + [v for v in seen if v not in order]


def method_label(predictor: str) -> str:
    """A predictor's name in tables and legends: baselines that see more than the method (:data:`ORACLES`) are
    marked."""
    return f"{predictor} (oracle)" if predictor in ORACLES else predictor


def table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    """A markdown table's lines (each cell its ``str``), followed by an empty line."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines + [""]
