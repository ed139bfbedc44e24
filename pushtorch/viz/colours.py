"""One colour per method and per training prior, the same in every figure and in every recording.

The report's figures (:mod:`pushtorch.experiments.report`) and the Rerun recordings
(:mod:`pushtorch.viz.scores`) draw a method or a prior in the same colour, so a reader who learns it in one
place recognises it in the other. No paper section.
"""

from __future__ import annotations

import zlib

__all__ = ["METHOD_COLOURS", "PRIOR_COLOURS", "colour_of"]

#: One colour per method, the same in every figure. Hues away from the priors' (tab10's purple, brown,
#: pink and cyan, then shades of tab20b/c), so no colour means a method in one figure and a prior in another.
METHOD_COLOURS: dict[str, str] = {
    "pushtorch": "#9467bd",
    "no_motion": "#8c564b",
    "mean_motion": "#17becf",
    "nominal_physics": "#e377c2",
    "nearest_push": "#393b79",
    "physics_from_cloud": "#9edae5",
    "oracle_physics": "#7b4173",
    "online": "#c49c94",
    "general": "#bd9e39",
    "congruent": "#5254a3",
    "incongruent": "#e7ba52",
    "adaptive": "#ce6dbd",
    "position_model": "#6b6ecf",
    "centroid": "#8c6d31",
}
#: One colour per training prior, the same in every figure. The paper's figures draw the general
#: (unbiased) models in green; low, medium and high keep the colours of the committed paper training
#: figures (docs/results/paper), which cannot be redrawn (their training pushes are not committed).
PRIOR_COLOURS: dict[str, str] = {
    "general": "#2ca02c",
    "low": "#1f77b4",
    "medium": "#ff7f0e",
    "high": "#d62728",
    "paper_default": "#7f7f7f",
    "selection": "#bcbd22",
}
# Colours for names in neither map, one palette per kind, none in the maps above: an unknown method still
# never takes a prior's colour (or a known method's).
_SPARE_METHOD_COLOURS = ("#76b7b2", "#edc948", "#ff9da7", "#b07aa1", "#9c755f", "#843c39", "#de9ed6",
                         "#cedb9c")
_SPARE_PRIOR_COLOURS = ("#4e79a7", "#f28e2b", "#e15759", "#59a14f", "#aec7e8", "#ffbb78")


def colour_of(name: str | None, kind: str = "method") -> str:
    """The colour of a method (``kind="method"``) or of a training prior (``kind="prior"``).

    A prior may be given as its results label (``"friction:low"`` is ``low``). A name in neither map gets
    a colour from a spare palette of its kind, picked by the CRC-32 of the name: the same in every run and
    on every machine (Python's own ``hash`` of a string changes between runs).

    Raises:
        ValueError: ``kind`` is neither ``"method"`` nor ``"prior"``.
    """
    if kind == "method":
        table, spare, key = METHOD_COLOURS, _SPARE_METHOD_COLOURS, name or ""
    elif kind == "prior":
        table, spare, key = PRIOR_COLOURS, _SPARE_PRIOR_COLOURS, (name or "").split(":", 1)[-1]
    else:
        raise ValueError(f"colour kind must be 'method' or 'prior', not {kind!r}")
    if key in table:
        return table[key]
    return spare[zlib.crc32(key.encode()) % len(spare)]
