"""The random convex shapes of the held-out set (issue 17 item 4): well-formed for every seed, deterministic,
of the paper objects' size, with their own symmetries, and pushable in pybullet."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pushtorch.errors import InvalidParameterError
from pushtorch.objects.shapes import SHAPE_KINDS, held_out_shapes, random_shape
from pushtorch.sim import place_robot_against
from pushtorch.sim.runner import simulate_pushes

ROOT = Path(__file__).resolve().parents[1]


@settings(max_examples=12)  # detect_symmetry takes 0.2-1 s a shape
@given(seed=st.integers(0, 2**31 - 1), kind=st.sampled_from(SHAPE_KINDS))
def test_every_shape_is_a_closed_convex_solid_of_the_paper_objects_size(seed, kind):
    shape = random_shape(seed, kind)
    mesh = shape.mesh
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.volume == pytest.approx(mesh.convex_hull.volume, rel=1e-6)
    assert np.abs(mesh.center_mass).max() < 1e-9  # the object frame sits at the centre of mass
    extents = np.asarray(mesh.extents)
    assert 0.15 - 1e-9 <= extents[2] <= 0.25 + 1e-9
    assert 0.02 < extents[:2].min() and extents[:2].max() <= 0.3 + 1e-9
    assert shape.name == f"{kind}_{seed}"


def test_a_shape_is_a_function_of_its_seed():
    a, b = random_shape(5, "polygon"), random_shape(5, "polygon")
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert not np.array_equal(a.mesh.vertices, random_shape(6, "polygon").mesh.vertices)
    assert random_shape(5).name.endswith("_5")
    with pytest.raises(InvalidParameterError, match="unknown shape kind"):
        random_shape(1, "torus")
    with pytest.raises(InvalidParameterError, match="non-negative"):
        random_shape(-1)


def test_boxes_have_a_box_symmetry_and_polygons_usually_none():
    box = random_shape(3, "box")
    assert box.symmetry.order == 4  # identity and three half turns (distinct sides)
    orders = [random_shape(s, "polygon").symmetry.order for s in range(5)]
    assert orders.count(1.0) >= 4, orders


def test_the_held_out_set_cycles_through_the_kinds_and_pushes_in_pybullet():
    shapes = held_out_shapes()
    assert len(shapes) >= 8 and {s.name.split("_")[0] for s in shapes} == set(SHAPE_KINDS)
    assert len({s.name for s in shapes}) == len(shapes)
    for shape in shapes[:3]:
        pose = shape.resting_pose()
        start = place_robot_against(shape.mesh, pose, gap=0.002)
        records = simulate_pushes(shape, start, pose, torch.tensor([0.1, math.radians(10.0)]), 0.5, 0.3)
        moved = float((records.object_final.p[0, :2] - pose.p[:2].double()).norm())
        assert bool(records.touched[0]) and not bool(records.tipped[0]) and moved > 0.2, (shape.name, moved)


@pytest.mark.slow
def test_pushtorch_beats_the_mean_motion_on_most_held_out_shapes(tmp_path):
    """Issue 17's acceptance on shapes nobody tuned on: tools/held_out.py (8 shapes, the quickstart's models,
    4 conditions each) must find pushtorch below the mean motion's displacement H_acc on at least 75 %."""
    result = subprocess.run([sys.executable, str(ROOT / "tools" / "held_out.py"), "--count", "8", "--out",
                             str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=3600)
    assert result.returncode == 0, result.stderr[-2000:]
    last = dict(item.split("=") for item in result.stdout.strip().splitlines()[-1].split())
    assert int(last["shapes"]) == 8
    assert float(last["beats_mean_motion"]) >= 0.75, result.stdout
