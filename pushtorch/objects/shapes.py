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
from pushtorch.objects.object_model import ObjectModel, centred
from pushtorch.objects.symmetry_detection import detect_symmetry

__all__ = ["HELD_OUT_FIRST_SEED", "SHAPE_KINDS", "held_out_shapes", "random_shape", "resolve_training_objects",
           "training_shape_seeds", "training_shapes"]

SHAPE_KINDS = ("polygon", "superellipse", "box")
#: Seeds from here on are the held-out set's (:func:`held_out_shapes`): no training shape may use one.
HELD_OUT_FIRST_SEED = 1000
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


def held_out_shapes(count: int = 9, first_seed: int = HELD_OUT_FIRST_SEED) -> list[ObjectModel]:
    """``count`` shapes cycling through the kinds, seeds ``first_seed, first_seed + 1, …``: the held-out set
    of the tests and docs/experiments.md (seeds from 1000 on are reserved for it: tune on others)."""
    return [random_shape(first_seed + i, SHAPE_KINDS[i % len(SHAPE_KINDS)]) for i in range(int(count))]


def training_shape_seeds(spec: str) -> list[tuple[int, str]]:
    """The ``(seed, kind)`` of every shape a ``model.training_objects`` entry names, without building them:
    ``shapes:<kind>:<count>`` or ``shapes:<kind>:<count>:<first seed>`` (default first seed 1), seeds ``first,
    first + 1, …``; ``<kind>`` is one of :data:`SHAPE_KINDS` or ``mixed`` (the kinds in turn, as the held-out set
    cycles them).

    Raises:
        InvalidParameterError: a malformed entry, an unknown kind, a count < 1, or a seed of the held-out set
            (:data:`HELD_OUT_FIRST_SEED` and above): a model trained on it would be tested on its own shapes.
    """
    fields = str(spec).split(":")
    if len(fields) not in (3, 4) or fields[0] != "shapes":
        raise InvalidParameterError(f"a generated training entry is shapes:<kind>:<count>[:<first seed>], got "
                                    f"{spec!r}")
    kind = fields[1]
    if kind != "mixed" and kind not in SHAPE_KINDS:
        raise InvalidParameterError(f"unknown shape kind {kind!r} in {spec!r}; use mixed or one of "
                                    f"{', '.join(SHAPE_KINDS)}")
    try:
        count = int(fields[2])
        first = int(fields[3]) if len(fields) == 4 else 1
    except ValueError as exc:
        raise InvalidParameterError(f"{spec!r}: the count and first seed must be integers") from exc
    if count < 1 or first < 0:
        raise InvalidParameterError(f"{spec!r}: the count must be >= 1 and the first seed >= 0")
    if first + count > HELD_OUT_FIRST_SEED:
        raise InvalidParameterError(
            f"{spec!r} reaches seed {first + count - 1}: seeds from {HELD_OUT_FIRST_SEED} on are the held-out "
            "shapes', never trained on")
    kinds = SHAPE_KINDS if kind == "mixed" else (kind,)
    return [(first + i, kinds[i % len(kinds)]) for i in range(count)]


def training_shapes(spec: str) -> list[ObjectModel]:
    """The generated training shapes a ``model.training_objects`` entry names (:func:`training_shape_seeds`).

    Raises:
        InvalidParameterError: as :func:`training_shape_seeds`.
    """
    return [random_shape(seed, kind) for seed, kind in training_shape_seeds(spec)]


#: File endings a ``training_objects`` entry is read as a mesh file by.
_MESH_ENDINGS = (".stl", ".obj", ".ply")


def resolve_training_objects(entries) -> list[ObjectModel]:
    """The objects a ``model.training_objects`` list names, in order: catalogue names, mesh files (a path
    ending in one of :data:`_MESH_ENDINGS`, read as ``object=mesh`` reads it) and generated shapes
    (:func:`training_shapes`).

    Raises:
        InvalidParameterError: an empty list, an unknown entry, or two objects of one name.
    """
    from pushtorch.objects.catalogue import load_object
    from pushtorch.objects.meshes import load_mesh_file

    if isinstance(entries, str):
        entries = [entries]
    entries = [str(e) for e in (entries or [])]
    if not entries:
        raise InvalidParameterError("training_objects must name at least one object")
    objects: list[ObjectModel] = []
    for entry in entries:
        if entry.startswith("shapes:"):
            objects.extend(training_shapes(entry))
        elif entry.lower().endswith(_MESH_ENDINGS):
            objects.append(load_mesh_file(entry))
        else:
            objects.append(load_object(entry))
    names = [o.name for o in objects]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise InvalidParameterError(f"training_objects names {', '.join(repeated)} more than once")
    return objects
