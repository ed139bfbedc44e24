"""The Rerun blueprints every recording ships with, so a saved ``.rrd`` opens laid out for review.

Not a paper section: this is the layout a reviewer sees on ``rerun <file>.rrd`` (README, "Rerun
recordings"). Every layout is built here and sent with ``rec.send_blueprint`` before the recording is
closed, which stores it in the file as a separate *blueprint* store next to the recording store (same
application id; read it back with :func:`read_blueprint`).

Layouts:
    experiments (:func:`experiment_blueprint`)  a tab per experiment part: a 3D view of the part's subtree,
        its summary (text), its groups' H_acc (time series on ``group``) and the annealing series of its
        logged predictions (time series on ``anneal_step``, one view per annealing); then a tab of the
        trained models.
    predict app (:func:`predict_blueprint`)     a tab per predicted action, laid out as a part.
    simulate app (:func:`pushes_blueprint`)     one 3D view of ``world/sim``.
    perception demo (:func:`perception_blueprint`)  a 3D view of everything, then one per object.

Every layout puts the time panel on ``sim_time`` (the pushes' timeline), playing in a loop, so the
ground-truth pushes move when the file opens. A Rerun view plots on the time panel's timeline only (the
viewer has no per-view timeline): the H_acc and annealing views name the timeline to switch to.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import rerun.blueprint as rrb

from pushtorch.viz.annealing import ANNEAL_SERIES, ANNEAL_TIMELINE
from pushtorch.viz.contacts import TRAINING
from pushtorch.viz.core import WORLD
from pushtorch.viz.scores import GROUP_TIMELINE
from pushtorch.viz.sim import SIM, SIM_TIMELINE

__all__ = [
    "ReviewTab",
    "experiment_blueprint",
    "perception_blueprint",
    "predict_blueprint",
    "pushes_blueprint",
    "read_blueprint",
    "review_tab",
]


@dataclass(frozen=True)
class ReviewTab:
    """What one tab shows: a 3D scene and, beside it, whatever of the part's numbers were logged.

    Attributes:
        name: the tab's title.
        origin: root of the 3D view (the part's or prediction's subtree).
        prediction_roots: the logged predictions under ``origin`` whose annealing series are plotted.
        summary: entity path of a text document to show, or None.
        hacc: root of the part's H_acc series, or None.
    """

    name: str
    origin: str
    prediction_roots: Sequence[str] = field(default_factory=tuple)
    summary: str | None = None
    hacc: str | None = None


def _time_panel(timeline: str | None = SIM_TIMELINE) -> rrb.TimePanel:
    if timeline is None:
        return rrb.TimePanel(state="collapsed")
    return rrb.TimePanel(timeline=timeline, state="expanded", play_state="playing", loop_mode="all")


def review_tab(tab: ReviewTab) -> rrb.Container:
    """The views of one tab: the 3D scene left, a column of text and plots right (if there are any)."""
    scene = rrb.Spatial3DView(origin=tab.origin, name=tab.name)
    column: list[rrb.Container | rrb.View] = []
    if tab.summary is not None:
        column.append(rrb.TextDocumentView(origin=tab.summary, name=f"{tab.name}: summary"))
    if tab.hacc is not None:
        column.append(rrb.TimeSeriesView(origin=tab.hacc, name=f"H_acc per group (timeline: {GROUP_TIMELINE})"))
    if tab.prediction_roots:
        # a view per annealing: their log-likelihoods are on different scales
        column.append(rrb.Tabs(*[
            rrb.TimeSeriesView(
                origin=tab.origin,
                contents=[f"/{root}/{series}" for root in tab.prediction_roots],
                name=f"best log-likelihood, {what} (timeline: {ANNEAL_TIMELINE})",
            )
            for series, what in ANNEAL_SERIES.items()
        ], name="annealing"))
    if not column:
        return rrb.Horizontal(scene, name=tab.name)
    return rrb.Horizontal(scene, rrb.Vertical(*column), column_shares=[3, 2], name=tab.name)


def experiment_blueprint(parts: Sequence[ReviewTab], training: bool = True) -> rrb.Blueprint:
    """An experiment run: one tab per part (in run order), then the trained models if ``training``."""
    tabs = [review_tab(part) for part in parts]
    if training:
        tabs.append(rrb.Spatial3DView(origin=TRAINING, name="trained models"))
    return rrb.Blueprint(rrb.Tabs(*tabs, name="experiment"), _time_panel())


def predict_blueprint(prediction_roots: Sequence[str], summary: str | None = None) -> rrb.Blueprint:
    """The predict app: one tab per prediction (each its own 3D view: they share the initial pose)."""
    tabs = [
        review_tab(ReviewTab(name=root.rsplit("/", 1)[-1], origin=root, prediction_roots=[root], summary=summary))
        for root in prediction_roots
    ]
    return rrb.Blueprint(rrb.Tabs(*tabs, name="predictions"), _time_panel())


def pushes_blueprint(origin: str = SIM) -> rrb.Blueprint:
    """The simulate app's pushes, side by side in one 3D view, playing on ``sim_time``."""
    return rrb.Blueprint(rrb.Spatial3DView(origin=origin, name="pushes"), _time_panel())


def perception_blueprint(object_names: Sequence[str]) -> rrb.Blueprint:
    """The perception demo (all static): every object together, then each with its clouds and features."""
    views = [rrb.Spatial3DView(origin=WORLD, name="all objects")]
    views += [
        rrb.Spatial3DView(origin=WORLD, contents=[f"/{WORLD}/objects/{name}/**", f"/{WORLD}/clouds/{name}/**"],
                          name=name)
        for name in object_names
    ]
    return rrb.Blueprint(rrb.Tabs(*views, name="objects"), _time_panel(None))


def read_blueprint(path: str | Path) -> dict:
    """The blueprint stored in a saved ``.rrd``, read back with Rerun's own reader.

    Returns:
        ``{"views": [{"class", "origin", "name", "contents"}, ...], "timeline": str | None}``: every view
        (its class identifier such as ``3D``, ``TimeSeries`` or ``TextDocument``, its origin, its name and
        its content queries) and the time panel's timeline; no views if the file has no blueprint store.
    """
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    columns: dict[str, dict[str, list]] = {}  # entity path → component → every row logged
    for store in reader.blueprints():
        for chunk in reader.store(store=store).stream().to_chunks():
            batch = chunk.to_record_batch()
            entity = columns.setdefault(str(chunk.entity_path), {})
            for name in batch.schema.names:
                if ":" in name:  # components (Archetype:field); timelines and row ids are not needed
                    entity.setdefault(name, []).extend(batch.column(name).to_pylist())

    def last(entity: dict, name: str):
        """The last value logged (a one-element batch unwrapped), or None."""
        values = [v for v in entity.get(name, []) if v is not None]
        if not values:
            return None
        value = values[-1]
        return value[0] if isinstance(value, list) and value else value

    views = []
    for view_path, entity in sorted(columns.items()):
        kind = last(entity, "ViewBlueprint:class_identifier")
        if kind is None:
            continue
        queries = columns.get(f"{view_path}/ViewContents", {}).get("ViewContents:query", [])
        views.append({
            "class": kind,
            "origin": last(entity, "ViewBlueprint:space_origin"),
            "name": last(entity, "ViewBlueprint:display_name"),
            "contents": [q for row in queries if row for q in row],
        })
    timeline = last(columns.get("/time_panel", {}), "TimePanelBlueprint:timeline")
    return {"views": views, "timeline": timeline}
