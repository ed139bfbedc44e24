"""Rerun logging of a run's numbers: each group's H_acc as a plottable series, and markdown summaries.

Paper, Experimental Setup (H_acc, the accuracy measure every experiment reports): results.json holds one
record per group (part, object, model, test condition, method); here each group's ``hacc_mean`` becomes
a point of a scalar series, so the viewer plots every group of a part side by side, coloured by method,
and a markdown summary per part lists the same groups as a table (with their index on the timeline, their
H_acc and mean nll) beside the logged example predictions (each with its own H_acc and nll).

Entity paths:
    metrics/<part>/hacc/<object>[/<model>][/<condition>]/<method>[/<metric>]   ``Scalars``: the group's mean H_acc
        on the ``group`` sequence timeline, at the record's index in results.json; ``SeriesPoints``
        (static): the method's name and colour
    metrics/<part>/summary                                          ``TextDocument`` (markdown)
    metrics/summary                                                 the predict app's summary
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import rerun as rr

from pushtorch.viz.core import entity_name

__all__ = [
    "GROUP_TIMELINE",
    "METRICS",
    "SUMMARY",
    "hacc_root",
    "log_group_hacc",
    "log_markdown",
    "part_summary",
    "part_summary_path",
]

#: Root of every run-level number.
METRICS = "metrics"
#: The predict app's summary document.
SUMMARY = f"{METRICS}/summary"
#: Sequence timeline of the groups: a group's index in results.json's ``records``.
GROUP_TIMELINE = "group"

# the group levels of a results.json record, outermost first (absent ones are skipped)
_GROUP_LEVELS = ("object", "model", "condition", "method", "observed", "metric")


def hacc_root(part: str) -> str:
    """Root of a part's H_acc series."""
    return f"{METRICS}/{entity_name(part)}/hacc"


def part_summary_path(part: str) -> str:
    """Entity path of a part's summary document."""
    return f"{METRICS}/{entity_name(part)}/summary"


def _method_colours(records: Sequence[Mapping[str, Any]]) -> dict[str, tuple[int, int, int]]:
    """Each method's colour as in the report's figures (:func:`pushtorch.viz.colours.colour_of`)."""
    from matplotlib.colors import to_rgb

    from pushtorch.viz.colours import colour_of

    return {m: tuple(round(255 * c) for c in to_rgb(colour_of(m))) for m in {str(r["method"]) for r in records}}


def log_group_hacc(
    rec: rr.RecordingStream, part: str, records: Sequence[Mapping[str, Any]], first_group: int = 0
) -> list[str]:
    """Each group's mean H_acc as one point of its own series, on the ``group`` timeline.

    Args:
        rec: an open recording.
        part: the experiment part the records belong to.
        records: results.json records (keys ``object``, ``method``, ``hacc_mean``; ``model`` and
            ``condition`` may be None).
        first_group: index of ``records[0]`` in results.json (the parts' records are concatenated).

    Returns:
        The entity path of every record's series, in order.
    """
    colours = _method_colours(records)
    paths = []
    for k, record in enumerate(records):
        levels = [(f"k{record[level]}" if level == "observed" else str(record[level]))
                  for level in _GROUP_LEVELS if record.get(level) is not None]
        path = f"{hacc_root(part)}/{entity_name('/'.join(level.replace('/', '_') for level in levels))}"
        method = str(record["method"])
        # one point per entity: markers, since a line needs two points to show
        name = method if record.get("metric") in (None, "displacement") else f"{method} ({record['metric']})"
        # the secondary (frame) score as smaller marks beside the primary one
        size = 4.0 if name == method else 2.0
        rec.log(path, rr.SeriesPoints(names=name, colors=colours[method], marker_sizes=size), static=True)
        rec.send_columns(
            path,
            indexes=[rr.TimeColumn(GROUP_TIMELINE, sequence=[first_group + k])],
            columns=rr.Scalars.columns(scalars=[float(record["hacc_mean"])]),
        )
        paths.append(path)
    return paths


def part_summary(
    part: str, records: Sequence[Mapping[str, Any]], first_group: int = 0, examples: Sequence[str] = ()
) -> str:
    """A part's markdown summary: its groups' H_acc and mean nll (``nll_mean``, displacement records) as a
    table, then the logged example predictions."""
    lines = [f"# {part}", "", f"{len(records)} groups; the `group` column is the index on the "
             f"`{GROUP_TIMELINE}` timeline (and in results.json).", ""]
    if records:
        lines += ["| group | object | model | condition | method | metric | n | H_acc | nll (nats) | linear cm | "
                  "angular deg |",
                  "|---:|---|---|---|---|---|---:|---|---:|---:|---:|"]
        for k, r in enumerate(records):
            nll = r.get("nll_mean")
            lines.append(
                f"| {first_group + k} | {r.get('object')} | {r.get('model') or '–'} | "
                f"{r.get('condition') or '–'} | {r.get('method')} | {r.get('metric') or '–'} | {r.get('n')} | "
                f"{float(r['hacc_mean']):.3f} ± {float(r.get('hacc_std', 0.0)):.3f} | "
                f"{'–' if nll is None else f'{float(nll):.2f}'} | "
                f"{float(r.get('linear_cm', float('nan'))):.2f} | {float(r.get('angular_deg', float('nan'))):.1f} |"
            )
    if examples:
        lines += ["", "## Logged predictions", ""] + [f"- {text}" for text in examples]
    return "\n".join(lines) + "\n"


def log_markdown(rec: rr.RecordingStream, entity_path: str, text: str) -> None:
    """A static markdown document (a summary the blueprint shows in a text view)."""
    rec.log(entity_path, rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
