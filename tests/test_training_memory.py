"""Training in bounded memory (pushtorch.models.motion.fit_motion_model places its pushes block by block): the
same models, bit for bit, for every block size, on real pybullet pushes of the cube."""

from __future__ import annotations

import pytest
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.models import motion
from pushtorch.models.contact import (
    bumper_contact_patch,
    bumper_contact_patch_terms,
    patch_from_terms,
    sample_environment_contacts,
    sample_environment_contacts_in_blocks,
)
from pushtorch.models.settings import ModelSettings
from pushtorch.models.training import _in_object_frame, robot_motions, train_push_model, training_features
from pushtorch.robot import bumper_mesh

SMALL = ModelSettings(voxel_size=0.008, feature_radius=0.02, query_kernels=400, anneal_candidates=60, anneal_steps=15,
                      position_frames=800, environment_kernels=300, manipulator_kernels=40)


@pytest.fixture(scope="module")
def cube_pushes(cube_pushes_of):
    """The cube, 9 real pybullet pushes per action and the cube's training features in its object frame."""
    cube, records = cube_pushes_of(9, 0)
    pose, features = training_features(cube, SMALL)
    return cube, records, _in_object_frame(features, pose)


def _motion_arrays(model: motion.MotionModel) -> dict[str, torch.Tensor]:
    out = {"action": model.action, "mean_p": model.mean_motion.p, "mean_q": model.mean_motion.q}
    for kind in ("manipulator", "environment"):
        kernels = getattr(model, kind)
        out.update(kernels.arrays(kind))
        out[f"{kind}.push"] = kernels.push
    return out


def _assert_identical(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    different = [k for k in a if not (a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]))]
    assert not different, f"not bit-identical: {different}"


def test_training_blocks_cover_the_pushes_in_order():
    for n_push in (1, 2, 5, 17, 100):
        for block in (1, 2, 3, 7, 50, 200):
            blocks = motion.training_blocks(n_push, 1000, block)
            assert blocks[0].start == 0 and blocks[-1].stop == n_push
            assert all(a.stop == b.start for a, b in zip(blocks[:-1], blocks[1:], strict=True))
            sizes = [s.stop - s.start for s in blocks]
            assert len(blocks) == 1 or all(block <= size < 2 * block for size in sizes)
    # the default: as many pushes as make TRAINING_BLOCK_PAIRS pairs, so the memory of a block is bounded
    blocks = motion.training_blocks(100_000, 12_601)
    assert max(s.stop - s.start for s in blocks) * 12_601 < 2 * motion.TRAINING_BLOCK_PAIRS
    with pytest.raises(InvalidParameterError):
        motion.training_blocks(10, 100, 0)


def test_blocked_environment_draws_are_one_call_over_all_rows():
    """Slot by slot, block after block: the same contacts and the same generator afterwards as one call."""
    points = torch.rand(11, 300, 3, generator=torch.Generator().manual_seed(1))
    g = torch.Generator().manual_seed(7)
    whole = sample_environment_contacts(points, 6, g)
    for blocks in ([slice(0, 11)], [slice(0, 1), slice(1, 5), slice(5, 11)], [slice(k, k + 1) for k in range(11)]):
        g2 = torch.Generator().manual_seed(7)
        blocked = sample_environment_contacts_in_blocks(lambda block: points[block], 11, 6, blocks, g2)
        assert torch.equal(blocked, whole)
        assert torch.equal(g2.get_state(), g.get_state())


def test_contact_patch_from_its_terms(cube_pushes):
    _, _, features = cube_pushes
    start = se3.from_xy_yaw(-0.3, 0.02, 0.1)
    points = se3.apply(se3.inverse(start), features.p)
    assert torch.equal(patch_from_terms(*bumper_contact_patch_terms(points)), bumper_contact_patch(points))


@pytest.mark.parametrize("block_pushes", [1, 2, 4])
def test_motion_model_is_the_same_for_every_block_size(cube_pushes, block_pushes):
    """Real pushes of one action: blocks of ``block_pushes`` against all 9 in one block (the unblocked code)."""
    _, records, features = cube_pushes
    valid = records.take(records.valid).to(torch.float32)
    sel = valid.take(valid.action_index == valid.action_index[0])
    assert len(sel) >= 8

    def fit(block: int | None, seed: int = 3):
        g = torch.Generator().manual_seed(seed)
        model = motion.fit_motion_model(
            features, sel.object_initial, sel.object_final, sel.robot_start, bumper_mesh(se3.identity()),
            sel.action[0], SMALL.environment_contacts_training, 2, SMALL.contact_cutoff, SMALL.contact_drop_off, g,
            physics=torch.stack([sel.ground_friction, sel.mass], -1), robot_motion=robot_motions(sel),
            block_pushes=block,
        )
        return _motion_arrays(model), g.get_state()

    whole, state = fit(len(sel))
    assert len(motion.training_blocks(len(sel), len(features.p), block_pushes)) > 1
    blocked, blocked_state = fit(block_pushes)
    _assert_identical(whole, blocked)
    assert torch.equal(blocked_state, state)  # the generator drew the same numbers in the same order
    assert not torch.equal(fit(block_pushes, seed=4)[0]["environment.u_p"], whole["environment.u_p"])


def test_trained_model_is_the_same_with_small_blocks(cube_pushes, monkeypatch):
    """train_push_model end to end (bandwidth search included) with blocks of 2 or 3 pushes."""
    cube, records, features = cube_pushes
    whole = train_push_model(cube, records, SMALL, generator=0).arrays()
    monkeypatch.setattr(motion, "TRAINING_BLOCK_PAIRS", len(features.p))  # default blocks: at least 2 pushes
    assert len(motion.training_blocks(9, len(features.p))) == 4
    _assert_identical(whole, train_push_model(cube, records, SMALL, generator=0).arrays())


def test_freed_heap_pages_go_back_to_the_system_between_training_blocks():
    """What training calls between its blocks (parallel.return_freed_memory): 40 MB of small blocks freed below a
    live one stay resident (glibc keeps them in its heap) until the trim hands them back; within the slack
    nothing is trimmed."""
    import sys

    from pushtorch.parallel import resident_mb, return_freed_memory

    if not sys.platform.startswith("linux") or not return_freed_memory():
        pytest.skip("glibc's malloc_trim is Linux-only")
    blocks = [bytearray(b"x" * 100_000) for _ in range(400)]  # below glibc's mmap threshold: from the heap
    fence = bytearray(b"y" * 100_000)  # a live block above them keeps free() from trimming the heap's top
    del blocks
    freed = resident_mb()
    assert not return_freed_memory(slack_mb=1e6)  # it grew by far less than the slack: no trim
    assert return_freed_memory()
    assert resident_mb() < freed - 20.0
    del fence
