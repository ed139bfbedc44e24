"""Random convex shapes of the paper objects' size: a held-out set the method is never tuned on (issue 17).

Paper, §Test Set: six objects (a cube, two prisms, two cylinders, a hybrid), all about 0.2 m. A predictor
tuned until those six look good can still fail on the next object a robot meets, so the experiments and
tests also measure on shapes drawn from this generator, which nobody looks at while tuning:

* ``polygon``: a convex polygon of 3–9 vertices at random angles and radii 0.06–0.15 m, extruded;
* ``superellipse``: ``|x/a|^m + |y/b|^m = 1`` with semi-axes 0.05–0.15 m and ``m`` in 1.5–6 (from a rounded
  diamond to a rounded box), extruded;
* ``box``: a box with random aspect ratio, 0.08–0.3 m by 0.1–0.3 m.

Every shape stands 0.15–0.25 m tall, is centred at its centre of mass, and gets its own detected
symmetries (:func:`pushtorch.objects.detect_symmetry`). A shape is a pure function of its kind and seed:
``random_shape(7, "polygon")`` is the same mesh on every machine.
"""

from __future__ import annotations

import numpy as np
import trimesh

from pushtorch.errors import InvalidParameterError
from pushtorch.objects.model import ObjectModel, centred
from pushtorch.objects.symmetry import detect_symmetry

__all__ = ["SHAPE_KINDS", "held_out_shapes", "random_shape"]

SHAPE_KINDS = ("polygon", "superellipse", "box")
_HEIGHT = (0.15, 0.25)
_OUTLINE_POINTS = 48  # of a superellipse's outline


def _extruded(outline: np.ndarray, height: float) -> trimesh.Trimesh:
    points = np.concatenate([np.c_[outline, np.full(len(outline), -height / 2)],
                             np.c_[outline, np.full(len(outline), height / 2)]])
    return trimesh.convex.convex_hull(points)


def _polygon(rng: np.random.Generator) -> np.ndarray:
    count = int(rng.integers(3, 10))
    # angles spread round the circle (each in its own sector), so the polygon keeps its centre inside
    angles = (np.arange(count) + rng.uniform(0.1, 0.9, count)) * 2 * np.pi / count
    radii = rng.uniform(0.06, 0.15, count)
    return np.stack([radii * np.cos(angles), radii * np.sin(angles)], -1)


def _superellipse(rng: np.random.Generator) -> np.ndarray:
    a, b = rng.uniform(0.05, 0.15, 2)
    m = rng.uniform(1.5, 6.0)
    t = np.linspace(0.0, 2 * np.pi, _OUTLINE_POINTS, endpoint=False)
    cos, sin = np.cos(t), np.sin(t)
    return np.stack([a * np.sign(cos) * np.abs(cos) ** (2 / m), b * np.sign(sin) * np.abs(sin) ** (2 / m)], -1)


def _box(rng: np.random.Generator) -> np.ndarray:
    x, y = rng.uniform(0.08, 0.3), rng.uniform(0.1, 0.3)
    return np.array([[-x, -y], [x, -y], [x, y], [-x, y]]) / 2


def random_shape(seed: int, kind: str | None = None) -> ObjectModel:
    """A random convex object named ``<kind>_<seed>`` (module docstring).

    Args:
        seed: any non-negative integer; the same seed and kind give the same shape.
        kind: one of :data:`SHAPE_KINDS`, or None to draw it from the seed too.

    Raises:
        InvalidParameterError: an unknown kind or a negative seed.
    """
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise InvalidParameterError(f"a shape seed must be a non-negative integer, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    chosen = SHAPE_KINDS[int(rng.integers(len(SHAPE_KINDS)))] if kind is None else kind
    outlines = {"polygon": _polygon, "superellipse": _superellipse, "box": _box}
    if chosen not in outlines:
        raise InvalidParameterError(f"unknown shape kind {chosen!r}; use one of {', '.join(SHAPE_KINDS)}")
    mesh = _extruded(outlines[chosen](rng), float(rng.uniform(*_HEIGHT)))
    mesh, _ = centred(mesh)
    return ObjectModel(f"{chosen}_{int(seed)}", mesh, detect_symmetry(mesh))


def held_out_shapes(count: int = 9, first_seed: int = 1000) -> list[ObjectModel]:
    """``count`` shapes cycling through the kinds, seeds ``first_seed, first_seed + 1, …``: the held-out set
    of the tests and docs/experiments.md (seeds from 1000 on are reserved for it: tune on others)."""
    return [random_shape(first_seed + i, SHAPE_KINDS[i % len(SHAPE_KINDS)]) for i in range(int(count))]
