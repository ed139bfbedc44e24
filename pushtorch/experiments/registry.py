"""The experiments by name: the one table of what ``experiment=<name>`` runs and of the parts a suite is made of
(paper, Experimental Results: one entry per experiment of its tables and figures, and this library's own).

Two tables, in the style of nerfstudio's ``method_configs``:

* :data:`EXPERIMENTS`: the name a config gives (``experiment.name``, one config per name in
  ``conf/experiment/``) → the function that runs it, ``run(cfg, out_dir, overrides) -> dict``. One function may
  serve several names: ``friction_biasing`` and ``mass_biasing`` both run :func:`pushtorch.experiments.biasing.run`,
  their configs naming the biased parameter.
* :data:`PARTS`: a part's kind (the ``kind`` of a quickstart part, the first item of each of
  :func:`pushtorch.experiments.suite.run_suite`'s parts) → ``run_part(cfg, part, ctx, model_cfg) -> (records,
  extras)``.

Each entry names its function as ``"module:function"``, imported only when it runs (:func:`experiment_runner`,
:func:`part_runner`): the app and the config check read the names without importing every experiment, and no
experiment module is imported by this one.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pushtorch.errors import InvalidParameterError

__all__ = ["EXPERIMENTS", "PARTS", "Entry", "experiment_names", "experiment_runner", "part_runner"]


@dataclass(frozen=True)
class Entry:
    """One runnable thing: the function ``target`` names (``"package.module:function"``) and what it is for.

    Attributes:
        target: where the function is, ``"<module>:<function>"``.
        paper: the paper's section (and table or figure) it reproduces, or what it is instead.
        summary: what it runs, in one line.
    """

    target: str
    paper: str
    summary: str

    def load(self) -> Callable[..., Any]:
        """The function itself (its module imported now)."""
        module, _, function = self.target.partition(":")
        return getattr(importlib.import_module(module), function)


#: Experiment name (``experiment.name``) → the function that runs it: ``run(cfg, out_dir, overrides) -> dict``.
EXPERIMENTS: dict[str, Entry] = {
    "quickstart": Entry("pushtorch.experiments.quickstart:run", "Experimental Results, all of it at small sizes",
                        "every part in experiment.parts into one run (make demo)"),
    "quickstart_transfer": Entry("pushtorch.experiments.quickstart:run",
                                 "§Conclusion's transfer by local contact models, at the quickstart's size",
                                 "transfer from many shapes, left out of the main job for time"),
    "model_selection": Entry("pushtorch.experiments.model_selection:run",
                             "§Contact Model Selection, Fig. adaptive_results",
                             "congruent / incongruent / adaptive models on the cube and the cylinder"),
    "pose_estimation": Entry("pushtorch.experiments.pose_estimation:run",
                             "§Pose Estimation Accuracy, Fig. position_accuracy_results",
                             "the position model against the centroid"),
    "friction_biasing": Entry("pushtorch.experiments.biasing:run",
                              "§Prediction Accuracy on Novel Contexts, friction table and figure",
                              "general / low / medium / high friction models × low / medium / high friction "
                              "conditions × the six test objects"),
    "mass_biasing": Entry("pushtorch.experiments.biasing:run",
                          "§Prediction Accuracy on Novel Contexts, mass table and figure",
                          "general / low / medium / high mass models × low / medium / high mass conditions × "
                          "the six test objects"),
    "online_adaptation": Entry("pushtorch.experiments.online_adaptation:run", "§Conclusions and future work",
                               "predictions conditioned on k observed pushes of the test object"),
    "shape_transfer": Entry("pushtorch.experiments.shape_transfer:run",
                            "§Test Set, §Prediction Accuracy on Novel Contexts; §Conclusion's transfer",
                            "one model pooled over many generated shapes against the two-object model"),
    "engine_gap": Entry("pushtorch.experiments.quickstart:run", "§Conclusions and future work: transfer to new shapes",
                        "pushtorch, the residual model and the physics peers with the truth in MuJoCo, the peers in "
                        "pybullet"),
    "engine_gap_pybullet": Entry("pushtorch.experiments.quickstart:run", "§Conclusions and future work",
                                 "the engine gap with the truth in pybullet, the peers in MuJoCo"),
    "engine_gap_same": Entry("pushtorch.experiments.quickstart:run", "§Conclusions and future work",
                             "the engine gap with one engine, pybullet, for the truth and the peers"),
    "perception_demo": Entry("pushtorch.experiments.perception_demo:run",
                             "Experimental Setup and Surface Features",
                             "the catalogue's objects, clouds and surface features in one recording"),
}


#: Part kind → the function that runs one part: ``run_part(cfg, part, ctx, model_cfg) -> (records, extras)``.
PARTS: dict[str, Entry] = {
    "model_selection": Entry("pushtorch.experiments.model_selection:run_part",
                             "§Contact Model Selection", "the model-selection part"),
    "pose_estimation": Entry("pushtorch.experiments.pose_estimation:run_part",
                             "§Pose Estimation Accuracy", "the pose-estimation part"),
    "biasing": Entry("pushtorch.experiments.biasing:run_part", "§Prediction Accuracy on Novel Contexts",
                     "a friction- or mass-biasing part (its config names the biased parameter)"),
    "online_adaptation": Entry("pushtorch.experiments.online_adaptation:run_part", "§Conclusions and future work",
                               "the online-adaptation part"),
    "shape_transfer": Entry("pushtorch.experiments.shape_transfer:run_part",
                            "§Test Set, §Prediction Accuracy on Novel Contexts", "the shape-transfer part"),
}


def experiment_names() -> list[str]:
    """The names ``experiment.name`` may take, sorted."""
    return sorted(EXPERIMENTS)


def experiment_runner(name: str) -> Callable[..., Any]:
    """The run function of the experiment ``name``.

    Raises:
        InvalidParameterError: no experiment of that name (the message lists the known ones).
    """
    if name not in EXPERIMENTS:
        raise InvalidParameterError(f"experiment.name {name!r} is not an experiment; known: "
                                    f"{', '.join(experiment_names())}")
    return EXPERIMENTS[name].load()


def part_runner(kind: str) -> Callable[..., Any]:
    """The ``run_part`` function of the part kind ``kind``.

    Raises:
        InvalidParameterError: no part of that kind (the message lists the known ones).
    """
    if kind not in PARTS:
        raise InvalidParameterError(f"unknown experiment part {kind!r}; use {', '.join(PARTS)}")
    return PARTS[kind].load()
