"""The recording's examples a task keeps for the submitting process (paper, Fig. prediction_accuracy_methodology:
the predictions the recording shows; a cluster run's bookkeeping, beyond the paper).

A task that predicts a group of test conditions for a run that records keeps the conditions the recording logs
whole (every action's prediction with its annealing history, and the cloud's features) and writes them beside
the group's prediction set, with the draws the recording shows of each density
(:func:`pushtorch.viz.densities.draw_density`); the submitting process reads them, logs them and removes the file,
so it predicts, draws (and compiles) nothing only to log them. Written atomically
(:func:`pushtorch.io.atomic_write_bytes`).
"""

from __future__ import annotations

import io
import logging
import pickle
from pathlib import Path
from typing import Any

import torch

from pushtorch.io import atomic_write_bytes

__all__ = ["load_examples", "save_examples"]

log = logging.getLogger("pushtorch.experiments")


def save_examples(path: Path, made_from: str, wanted: set[int], kept: list[Any]) -> None:
    """Write a task's kept examples (``prediction_sets.Example``) of the set ``made_from`` and the conditions
    ``wanted`` to ``path``, atomically, each with the draws of its densities that the recording shows (its
    ``drawn`` and ``residual_drawn``; None where a density cannot be drawn from: the submitting process then
    tries and warns)."""
    for example in kept:
        example.drawn = _draws(example.prediction)
        example.residual_drawn = _draws(example.residual)
    buffer = io.BytesIO()
    torch.save({"made_from": made_from, "conditions": sorted(wanted), "examples": kept}, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def _draws(prediction) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The recording's draws of ``prediction``'s density, or None (no prediction, or none can be drawn)."""
    from pushtorch.errors import ModelError
    from pushtorch.viz.densities import draw_density

    if prediction is None:
        return None
    try:
        return draw_density(prediction.density)
    except ModelError:
        return None


def load_examples(path: Path, made_from: str, wanted: set[int]) -> list[Any] | None:
    """The examples a task kept at ``path`` for the set ``made_from`` and the conditions ``wanted``; None when
    there are none, or they were kept for another set or choice, or the file does not load (then they are
    predicted again)."""
    if not path.is_file():
        return None
    try:
        kept = torch.load(path, map_location="cpu", weights_only=False)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError) as exc:
        log.warning("predicting the logged examples again: %s does not load (%s)", path, exc)
        return None
    if kept.get("made_from") != made_from or kept.get("conditions") != sorted(wanted):
        return None
    return list(kept["examples"])
