"""The paper's experiments: configs at the paper's protocol, result pooling, and a tiny quickstart end to end
(results.json schema, report, figures, recording, resumption) with the train and predict apps on its data."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hypothesis import given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from pushtorch import viz
from pushtorch.apps.predict import predict_from_config
from pushtorch.apps.train import train_from_config
from pushtorch.errors import InvalidParameterError, PushtorchError
from pushtorch.evaluation.metrics import Accuracy
from pushtorch.experiments import quickstart
from pushtorch.experiments.common import PredictionSet, sample_test_poses, summarise
from pushtorch.experiments.report import PAPER_LINEAR_CM, acceptance_checks, pool, primary
from pushtorch.models.model import load_model
from pushtorch.models.settings import ModelSettings
from pushtorch.objects import load_object

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
RECORD_KEYS = {"task", "object", "method", "model", "condition", "n", "hacc_mean", "hacc_std", "linear_cm",
               "angular_deg"}


def _compose(overrides: list[str], name: str = "config", hydra_config: bool = False):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        return compose(name, overrides=overrides, return_hydra_config=hydra_config)


def test_the_engine_gap_experiments_pin_their_engines_and_predict_every_method():
    """Three settings, each pinned in its config whatever the default world: two cross-engine, one the inverse
    crime; the six catalogue objects, 10 conditions x 3 actions, the residual model and the density peer."""
    pinned = {"engine_gap": ("mujoco", "pybullet"), "engine_gap_pybullet": ("pybullet", "mujoco"),
              "engine_gap_same": ("pybullet", "pybullet")}
    for name, engines in pinned.items():
        cfg = _compose([f"experiment={name}"])
        assert (cfg.world.engine, cfg.physics.engine) == engines
        part = cfg.experiment.parts.engine_gap
        assert len(part.objects) == 6 and part.test_conditions * cfg.experiment.actions.count >= 30
        assert part.residual and part.ensemble == part.residual_ensemble
        assert all(cfg.experiment.parts[p].skip for p in cfg.experiment.parts if p != "engine_gap")
    assert (_compose([]).world.engine, _compose([]).physics.engine) == ("mujoco", "pybullet")  # the default


def test_the_main_job_runs_the_fast_path_eagerly_and_every_other_experiment_compiles_it():
    from pushtorch.apps.experiment import compiles

    assert not compiles(_compose([]))  # the quickstart: compiling costs more than its predictions win back
    assert compiles(_compose(["experiment.compile=true"]))
    for name in ("friction_biasing", "online_adaptation", "engine_gap", "engine_gap_same", "quickstart_transfer"):
        assert compiles(_compose([f"experiment={name}"])), name


def test_paper_experiments_default_to_the_full_protocol():
    selection = _compose(["experiment=model_selection"])
    assert (selection.experiment.test_conditions, selection.experiment.truth_samples) == (50, 4)
    assert list(selection.experiment.objects) == ["cube", "cylinder"]
    assert OmegaConf.to_container(selection.priors.friction.selection) == {"kind": "uniform", "low": 0.15,
                                                                          "high": 0.35}
    assert selection.model.samples_per_action == 500
    pose = _compose(["experiment=pose_estimation"])
    assert pose.experiment.runs == 100
    assert list(pose.experiment.objects) == ["cube", "cylinder", "modified_cube"]
    s = pose.model.settings
    assert (s.query_kernels, s.anneal_candidates, s.anneal_steps) == (3000, 500, 100)
    training_pushes = 0
    for bias, other in (("friction", "mass"), ("mass", "friction")):
        cfg = _compose([f"experiment={bias}_biasing"])
        exp = cfg.experiment
        assert list(cfg.model[bias]) == ["general", "low", "medium", "high"]
        assert list(exp.conditions[bias]) == ["low", "medium", "high"]
        assert (exp.test_conditions, exp.truth_samples, len(exp.objects)) == (100, 3, 6)
        # the density peers: physics_ensemble and the residual model, at one cost of rollouts
        assert exp.residual is True and exp.ensemble == exp.residual_ensemble == 4
        assert cfg.priors[bias].low.mean == 0.1 and cfg.priors[other].paper_default.std > 0
        training_objects = set(exp.training_object_of.values())
        training_pushes += len(training_objects) * 4 * exp.actions.count * cfg.model.samples_per_action
    assert training_pushes == 24_000  # the "24,000 training pushes over both"


def test_model_config_lists_every_model_setting_at_its_default():
    cfg = _compose(["experiment=friction_biasing"])
    assert OmegaConf.to_container(cfg.model.settings) == asdict(ModelSettings())
    quick = _compose(["experiment=quickstart"]).model.settings
    quick_settings = ModelSettings.from_mapping(OmegaConf.to_container(quick))
    assert quick_settings.query_kernels < ModelSettings().query_kernels


def test_training_placement_comes_from_the_protocol_and_keeps_its_own_caches(tmp_path):
    from pushtorch.experiments.common import context_from_config, training_records
    from pushtorch.sim.plan import Placement

    default = context_from_config(_compose(["experiment=quickstart"]), tmp_path)
    assert default.placement == Placement(lateral_jitter=0.1, yaw_jitter_deg=5.0)  # conf/protocol/spread.yaml
    paper = context_from_config(_compose(["experiment=quickstart", "protocol=paper"]), tmp_path)
    assert paper.placement == Placement()  # the paper repeats one placement
    spread_cfg = _compose(["experiment=quickstart", "protocol=paper", "model.placement.lateral_jitter=0.05",
                           "model.samples_per_action=2", "experiment.progress=false"])
    spread = context_from_config(spread_cfg, tmp_path)
    assert spread.placement == Placement(lateral_jitter=0.05)
    assert spread.with_model(OmegaConf.to_container(spread_cfg.model, resolve=True)).placement == spread.placement
    cube = load_object("cube")
    records = training_records(spread, cube, "paper_default", "paper_default")
    offsets = records.robot_start.p[:, 1]  # the robot approaches along +x: jitter moves it along y
    assert len(set(offsets.tolist())) == len(records) and offsets.abs().max() <= 0.05
    assert [p.name for p in (tmp_path / "data").iterdir()] == [
        "cube_paper_default_paper_default_lateral_jitter0.05_mujoco"  # the default world's pushes are named so
    ]
    with pytest.raises(InvalidParameterError, match="model.placement"):
        context_from_config(_compose(["experiment=quickstart", "+model.placement.lateral=0.05"]), tmp_path)


def test_quickstart_runs_every_paper_experiment_smaller_and_points_to_the_rest():
    cfg = _compose(["experiment=quickstart"])
    parts = cfg.experiment.parts
    assert {p.kind for p in parts.values() if not p.get("skip")} == {"model_selection", "pose_estimation", "biasing",
                                                                    "online_adaptation"}
    assert parts.shape_transfer.skip and "pushtorch experiment=quickstart_transfer" in cfg.experiment.more
    assert {p.bias for p in parts.values() if p.kind == "biasing"} == {"friction", "mass"}
    assert parts.pose_estimation.runs < 100 and parts.model_selection.test_conditions < 50
    assert cfg.model.samples_per_action < 500
    online = parts.online_adaptation
    assert online.test_conditions * cfg.experiment.actions.count >= 30  # scored pushes per object and condition
    # an extreme condition of each parameter at least
    assert all({"low", "high"} & set(online.conditions[bias]) for bias in ("friction", "mass"))
    transfer_cfg = _compose(["experiment=quickstart_transfer"])
    assert [name for name, part in transfer_cfg.experiment.parts.items() if not part.skip] == ["shape_transfer"]
    transfer = transfer_cfg.experiment.parts.shape_transfer
    assert transfer.test_conditions * cfg.experiment.actions.count >= 30  # scored pushes per object
    assert set(transfer.transfer_objects) <= set(transfer.objects)
    assert not set(transfer.model.training_objects) & set(transfer.objects)


def test_object_override_and_sweep_compose():
    cfg = _compose(["experiment=pose_estimation", "object=mesh", "object.path=/tmp/part.stl",
                    "object.scale=0.001"])
    assert (cfg.object.name, cfg.object.path, cfg.object.scale) == ("mesh", "/tmp/part.stl", 0.001)
    swept = _compose(["experiment=friction_biasing", "model.friction=low"], hydra_config=True)
    assert swept.model.friction == "low"
    subdir = OmegaConf.to_container(swept.hydra.sweep, resolve=False)["subdir"]
    assert "pushtorch.job_dir" in subdir and "hydra.overrides.task" in subdir  # named by what it sweeps
    joblib = _compose(["experiment=quickstart", "hydra/launcher=joblib"], hydra_config=True).hydra.launcher
    assert "JoblibLauncher" in joblib._target_


def _accuracy(values: list[float]) -> Accuracy:
    t = torch.tensor(values, dtype=torch.float64)
    return Accuracy(hacc=t, linear=t, angular=torch.zeros_like(t), linear_cm=2 * t, angular_deg=3 * t)


@given(st.lists(st.lists(st.floats(0.0, 5.0), min_size=1, max_size=12), min_size=1, max_size=6))
def test_pooled_groups_equal_the_statistics_of_all_their_samples(groups):
    records = [summarise("prediction", "cube", "pushtorch", _accuracy(g)) for g in groups]
    pooled = pool(records)
    every = torch.tensor([v for g in groups for v in g], dtype=torch.float64)
    assert pooled["n"] == every.numel()
    assert math.isclose(pooled["hacc_mean"], float(every.mean()), rel_tol=1e-9, abs_tol=1e-9)
    assert math.isclose(pooled["hacc_std"], float(every.std(unbiased=False)), rel_tol=1e-6, abs_tol=1e-6)
    assert math.isclose(pooled["linear_cm"], 2 * float(every.mean()), rel_tol=1e-9, abs_tol=1e-9)


def test_acceptance_checks_fail_when_a_baseline_wins():
    group = ("friction:low", "friction:low")
    good = summarise("prediction", "cube", "pushtorch", _accuracy([0.1, 0.2]), *group)
    still = summarise("prediction", "cube", "no_motion", _accuracy([2.0, 2.1]), *group)
    assert [c["passed"] for c in acceptance_checks([good, still])] == [True]
    worse = summarise("prediction", "cube", "no_motion", _accuracy([0.01, 0.02]), *group)
    assert [c["passed"] for c in acceptance_checks([good, worse])] == [False]


def _selection(method: str, values: list[float]) -> dict:
    return summarise("selection", "cube", method, _accuracy(values), "cube", "selection")


@settings(max_examples=60, deadline=None)
@given(st.floats(0.01, 1.0), st.floats(0.0, 0.3), st.integers(2, 30), st.floats(-6.0, 6.0))
def test_a_match_claim_holds_within_three_standard_errors_or_five_percent(level, spread, n, shift_in_se):
    """``adaptive matches congruent`` holds exactly when |difference| <= max(3 SE, 5 % of congruent's H_acc)."""
    base = [level + spread * ((-1) ** i) for i in range(n)]
    congruent = _selection("congruent", base)
    se0 = math.sqrt(2 * congruent["hacc_std"] ** 2 / n)
    shifted = _selection("adaptive", [v + shift_in_se * max(se0, 1e-3) for v in base])
    check = next(c for c in acceptance_checks([congruent, shifted]) if c["check"] == "adaptive matches congruent")
    diff = shifted["hacc_mean"] - congruent["hacc_mean"]
    se = math.sqrt(shifted["hacc_std"] ** 2 / n + congruent["hacc_std"] ** 2 / n)
    margin = max(3 * se, 0.05 * congruent["hacc_mean"])
    if abs(abs(diff) - margin) > 1e-6:  # away from the boundary, where float rounding decides
        assert check["passed"] == (abs(diff) <= margin), check


def test_research_questions_are_findings_never_checks():
    from pushtorch.experiments.transfer_report import transfer_findings, transfer_section

    group = ("friction:low", "friction:low")
    records = [dict(summarise("transfer", "hybrid", m, _accuracy(v), "shapes" if m != "pushtorch" else "two",
                              group[0], metric="displacement", nll=torch.tensor([1.0, 2.0])), task="transfer")
               for m, v in (("pushtorch_shapes", [0.9, 1.0]), ("pushtorch", [0.1, 0.12]))]
    info = {"transfer_objects": ["hybrid"], "held_out": []}
    findings = transfer_findings(records, info)
    assert [(f["question"], f["held"]) for f in findings][0] == ("pushtorch_shapes within 2 SE of pushtorch or "
                                                                 "better", False)
    assert acceptance_checks(records) == []  # a "not yet" never turns a run red
    assert "### Research questions" in transfer_section(records, info, set())


def test_the_summary_names_the_strongest_non_oracle_peer():
    from pushtorch.experiments.summary import summary_table

    group = ("friction:low", "friction:low")
    records = [summarise("prediction", "cube", m, _accuracy(v), *group, metric="displacement")
               for m, v in (("pushtorch", [0.1, 0.1]), ("no_motion", [2.0, 2.0]), ("mean_motion", [0.3, 0.3]),
                            ("oracle_physics", [0.01, 0.01]))]
    table = summary_table(records, acceptance_checks(records))
    header, row = table.splitlines()[:2]
    assert header.split()[:3] == ["object", "pushtorch", "H_acc"]
    assert row.split()[0] == "cube" and "mean_motion" in row and "oracle" not in table and row.endswith("1/1")


def test_the_summary_counts_invalid_conditions_per_method():
    from pushtorch.experiments.summary import summary_table

    group = ("friction:low", "friction:low")
    records = [summarise("prediction", "cube", m, _accuracy(v), *group, metric="displacement")
               for m, v in (("pushtorch", [0.1, 0.1]), ("no_motion", [2.0, 2.0]))]
    thrown = [{"object": "cube", "method": "incongruent", "model": None, "thrown": 0, "pushes": 6,
               "invalid_starts": 4, "starts": 9},
              {"object": "cylinder", "method": "incongruent", "model": None, "thrown": 0, "pushes": 6,
               "invalid_starts": 1, "starts": 9},
              {"object": "cube", "method": "congruent", "model": None, "thrown": 0, "pushes": 6,
               "invalid_starts": 0, "starts": 9}]
    last = summary_table(records, acceptance_checks(records), thrown).splitlines()[-1]
    assert last.startswith("invalid conditions") and "incongruent 5/18" in last and ", congruent 0/9" not in last
    assert "invalid" not in summary_table(records, acceptance_checks(records), thrown[2:])


def test_an_experiment_logs_the_warnings_it_expects_below_warning_and_a_library_call_still_warns(caplog):
    import logging

    from pushtorch.experiments.suite import EXPECTED_WARNINGS, expected_warnings_quiet

    caplog.set_level(logging.DEBUG)
    for name in EXPECTED_WARNINGS:
        with expected_warnings_quiet():
            logging.getLogger(name).warning("an invalid condition, counted in the summary")
        logging.getLogger(name).warning("a library user's call")
    levels = [(r.name, r.levelno) for r in caplog.records]
    assert levels == [x for name in EXPECTED_WARNINGS for x in ((name, logging.DEBUG), (name, logging.WARNING))]
    # at INFO (a run's default) a handler without a level of its own, as Hydra's console, prints nothing of it
    caplog.set_level(logging.INFO)
    seen: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = seen.append
    logging.getLogger().addHandler(handler)
    try:
        with expected_warnings_quiet():
            logging.getLogger(EXPECTED_WARNINGS[0]).warning("an invalid condition")
            logging.getLogger("pushtorch.experiments").warning("anything else still warns")
    finally:
        logging.getLogger().removeHandler(handler)
    assert [r.getMessage() for r in seen] == ["anything else still warns"]


def test_sampled_test_poses_are_seeded_upright_and_in_range():
    cube = load_object("cube")
    a = sample_test_poses(cube, 20, (-45.0, 45.0), seed=3)
    b = sample_test_poses(cube, 20, (-45.0, 45.0), seed=3)
    assert torch.equal(a.p, b.p) and torch.equal(a.q, b.q)
    yaw = 2 * torch.atan2(a.q[:, 3], a.q[:, 0])
    assert (yaw.abs() <= math.radians(45.0) + 1e-6).all() and yaw.std() > 0.1
    assert torch.allclose(a.p[:, 2], torch.full((20,), cube.rest_height))
    assert not torch.equal(sample_test_poses(cube, 20, (-45.0, 45.0), seed=4).q, a.q)
    with pytest.raises(InvalidParameterError):
        sample_test_poses(cube, 0, (-45.0, 45.0), seed=0)


TINY = [
    "experiment=quickstart",
    "experiment.progress=false",
    "experiment.workers=2",
    "experiment.actions.count=2",
    "model.samples_per_action=3",
    "model.settings.query_kernels=200",
    "model.settings.anneal_candidates=40",
    "model.settings.anneal_steps=8",
    "model.settings.environment_kernels=200",
    "model.settings.manipulator_kernels=40",
    "model.settings.environment_samples=20",
    "model.settings.voxel_size=0.008",
    "model.settings.feature_radius=0.02",
    "experiment.parts.model_selection.test_conditions=1",
    "experiment.parts.model_selection.truth_samples=1",
    "experiment.parts.pose_estimation.objects=[cube,cylinder]",
    "experiment.parts.pose_estimation.runs=2",
    "experiment.parts.friction_biasing.objects=[cube,prism_thin]",
    "experiment.parts.friction_biasing.model.friction=[low,high]",
    "experiment.parts.mass_biasing.objects=[cube]",
    "experiment.parts.mass_biasing.model.mass=[low]",
    "experiment.parts.mass_biasing.conditions.mass=[low,high]",
    "experiment.parts.online_adaptation.objects=[cube]",
    "experiment.parts.online_adaptation.conditions.friction=[low,medium]",
    "experiment.parts.online_adaptation.conditions.mass=[high]",
    "experiment.parts.online_adaptation.test_conditions=2",
    "experiment.parts.online_adaptation.observed=[0,2]",
    "experiment.parts.online_adaptation.peer_grid=3",
    "experiment.parts.shape_transfer.skip=false",
    "experiment.parts.shape_transfer.objects=[prism_thin]",
    "experiment.parts.shape_transfer.transfer_objects=[prism_thin]",
    "experiment.parts.shape_transfer.held_out=1",
    "experiment.parts.shape_transfer.model.training_objects=[shapes:mixed:2]",
    "experiment.parts.shape_transfer.test_conditions=1",
    "experiment.parts.shape_transfer.conditions.friction=[low]",
    "experiment.parts.shape_transfer.ensemble=2",
    "experiment.parts.shape_transfer.widening_pushes=1",
    "experiment.parts.shape_transfer.library=true",
]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("quickstart")
    cfg = _compose(TINY)
    summary = quickstart.run(cfg, out)
    return cfg, out, summary


def test_tiny_quickstart_writes_tidy_results(tiny_run):
    cfg, out, summary = tiny_run
    results = json.loads((out / "results.json").read_text())
    assert set(results) == {"experiment", "world", "physics", "config", "overrides", "wall_s", "records",
                            "model_bandwidths", "separability", "tasks"}
    # two cores: the models, the pose estimates, the groups of predictions and the online conditions ran in local
    # worker processes
    kinds = {key.split(" | ")[0] for key in results["tasks"] if key.endswith("(local workers)")}
    assert {"models trained", "objects' poses estimated", "groups predicted, pushed and scored",
            "groups of conditions scored"} <= kinds
    # the default world: the truth in MuJoCo, the physics peers in pybullet (no peer has the truth's physics)
    assert results["world"] == {"engine": "mujoco"} and results["physics"] == {"engine": "pybullet"}
    # every trained model chose its bandwidths from its training pushes, and the run says which
    assert results["model_bandwidths"] and all(set(b["chosen"]) == set(b["start"])
                                               for b in results["model_bandwidths"].values())
    assert results["experiment"] == "quickstart" and results["wall_s"] > 0
    assert results["config"]["experiment"]["parts"]["pose_estimation"]["runs"] == 2
    every = [r for r in results["records"] if r["task"] != "online"]
    for r in every:
        expected = (RECORD_KEYS | ({"selection_rate"} if r["task"] == "selection" else set())
                    | ({"metric", "nll_mean", "nll_median", "coverage_50", "coverage_90"} if r["task"] != "pose"
                       else set()))
        assert set(r) == expected
        assert r["n"] >= 1 and r["hacc_mean"] >= 0 and r["hacc_std"] >= 0 and r["linear_cm"] >= 0
        # the likelihood is a displacement-sense score: a finite number there, empty on frame records
        if r.get("metric") == "displacement":
            assert math.isfinite(r["nll_mean"]) and math.isfinite(r["nll_median"])
        elif r.get("metric") == "frame":
            assert r["nll_mean"] is None
    # every prediction and selection group is scored twice: displacement (primary) and frame
    scored = [r for r in every if r["task"] != "pose"]
    assert {r["metric"] for r in scored} == {"displacement", "frame"}
    assert len([r for r in scored if r["metric"] == "frame"]) == len(scored) // 2
    records = primary(every)
    by_task = {t: [r for r in records if r["task"] == t] for t in ("selection", "pose", "prediction")}
    assert {(r["object"], r["method"]) for r in by_task["selection"]} == {
        (o, m) for o in ("cube", "cylinder") for m in ("congruent", "incongruent", "adaptive")}
    rates = {(r["object"], r["method"]): r["selection_rate"] for r in by_task["selection"]}
    assert rates[("cube", "congruent")] == 1.0 and rates[("cube", "incongruent")] == 0.0
    assert 0.0 <= rates[("cylinder", "adaptive")] <= 1.0
    # H_r picks the cube's model for the cube; with common random numbers its predictions are then the
    # congruent method's, pushed under the same sampled physics: the same numbers
    assert rates[("cube", "adaptive")] == 1.0
    same = [r for r in by_task["selection"] if r["object"] == "cube" and r["method"] != "incongruent"]
    assert same[0]["hacc_mean"] == same[1]["hacc_mean"] and same[0]["n"] == same[1]["n"]
    assert all(r["n"] == 1 * 2 * 1 for r in by_task["selection"])  # conditions x actions x samples
    assert {r["method"]: r["n"] for r in by_task["pose"]} == {"position_model": 2, "centroid": 1}
    friction = [r for r in by_task["prediction"] if r["model"].startswith("friction:")]
    assert {(r["object"], r["model"], r["condition"], r["method"]) for r in friction} == {
        (o, f"friction:{m}", f"friction:{c}", method) for o in ("cube", "prism_thin") for m in ("low", "high")
        for c in ("low", "medium", "high")
        for method in ("pushtorch", "no_motion", "mean_motion", "nearest_push", "physics_from_cloud",
                       "oracle_physics")}
    assert all(r["n"] == 1 * 2 * 2 for r in friction)
    mass = [r for r in by_task["prediction"] if r["model"].startswith("mass:")]
    assert {r["condition"] for r in mass} == {"mass:low", "mass:high"}
    # a push moves the object ~40 cm: standing still is far off, our prediction is not
    still = pool([r for r in friction if r["method"] == "no_motion"])
    ours = pool([r for r in friction if r["method"] == "pushtorch"])
    assert still["linear_cm"] > 20 and ours["linear_cm"] < still["linear_cm"]
    assert ours["nll_mean"] < still["nll_mean"]  # a point that stands still is far less likely than our density
    # coverage: a share in [0, 1] for every method with a density, none for a point prediction or a frame record
    for r in [r for r in every if r.get("metric") == "displacement"]:
        dense = r["task"] == "selection" or r["method"] in (  # a selection method is pushtorch with some model
            "pushtorch", "mean_motion", "pushtorch_shapes", "pushtorch_library", "physics_ensemble",
            "pushtorch_residual")
        for key in ("coverage_50", "coverage_90"):
            assert (0.0 <= r[key] <= 1.0) if dense else r[key] is None, (r["method"], key, r[key])
        if dense:
            assert r["coverage_50"] <= r["coverage_90"]
    transfer = [r for r in records if r["task"] == "transfer"]
    assert {(r["object"], r["method"], r["model"]) for r in transfer} == {
        (o, m, model) for o in ("prism_thin", "polygon_1000") for m, model in (
            ("pushtorch_shapes", "shapes"), ("pushtorch_residual", "shapes"), ("pushtorch_library", "library"),
            ("pushtorch", "cube+cylinder"),
            ("mean_motion", "shapes"), ("nearest_push", "shapes"), ("physics_from_cloud", "shapes"),
            ("physics_ensemble", "shapes"), ("oracle_physics", "shapes"), ("mean_motion", "cube+cylinder"),
            ("nearest_push", "cube+cylinder"))}
    assert all(r["n"] == 1 * 2 * 1 for r in transfer)  # conditions x actions x samples
    # the pooled model trained on generated shapes below the held-out seeds, never on a test object
    trained = {p.name.split("_general")[0] for p in (out / "data").iterdir()}
    assert {"polygon_1", "superellipse_2"} <= trained and "polygon_1000" not in trained
    # the pooled model's residual model, its widening chosen across the training shapes, kept beside it
    assert any(p.name.startswith("shapes_") and p.name.endswith("_mujoco_residual_vs_pybullet.npz")
               for p in (out / "models").iterdir())
    shapes_meta = results["model_bandwidths"]
    assert any(name.startswith("shapes_") for name in shapes_meta)
    online = [r for r in results["records"] if r["task"] == "online"]
    assert summary["results"] == str(out / "results.json") and summary["records"] == len(every) + len(online)
    # online adaptation: every predictor per condition and k, the posterior beside the conditioned ones
    methods = {"online", "online_general", "general", "congruent", "incongruent", "physics_from_cloud",
               "physics_from_cloud_online"}
    assert {(r["condition"], r["method"], r["observed"]) for r in online} == {
        (c, m, k) for c in ("friction:low", "friction:medium", "mass:high") for m in methods for k in (0, 2)} | {
        (c, "debiased", 0) for c in ("friction:low", "friction:medium", "mass:high")}
    for r in online:
        assert set(r) >= RECORD_KEYS | {"observed", "metric", "nll_mean", "nll_median"} and r["n"] == 2 * 2
        assert math.isfinite(r["hacc_mean"]) and math.isfinite(r["nll_mean"])
        if r["method"] in ("online", "online_general"):
            assert 0 < r["mu_mean"] < 1 and r["mu_std"] >= 0 and math.isfinite(r["log_mass_mean"])
            assert r["mass_true"] == (5.0 if r["condition"] == "mass:high" else 0.5)
        if r["method"] == "online" and r["observed"] > 0:  # the evidence itself, per library model and case
            for key in ("log_evidence", "log_weights"):
                assert set(r[key]) == {"general", "low", "medium", "high"}
                assert all(len(v) == 2 and all(math.isfinite(x) for x in v) for v in r[key].values())
            for case in range(2):  # the library's posterior over its models is normalised
                assert math.isclose(sum(math.exp(r["log_weights"][m][case]) for m in r["log_weights"]), 1.0,
                                    rel_tol=1e-6)
    by = {(r["condition"], r["method"], r["observed"]): r for r in online}
    # without observations, the conditioned predictors are the general model's own predictions
    assert by[("friction:low", "online_general", 0)]["hacc_mean"] == by[("friction:low", "general", 0)]["hacc_mean"]
    # adjacent conditions of one parameter only: friction low and medium
    [separable] = results["separability"]
    assert (separable["object"], separable["parameter"], separable["pair"]) == ("cube", "friction", "low|medium")
    assert separable["separability"] >= 0 and separable["mean_gap_cm"] >= 0


def test_tiny_quickstart_writes_report_figures_and_recording(tiny_run):
    _, out, summary = tiny_run
    report = (out / "report.md").read_text()
    for heading in ("Contact model selection", "Pose estimation", "Friction biasing", "Mass biasing",
                    "Acceptance checks", "model prior = test condition", "Transfer from many shapes"):
        assert heading in report
    assert "1.41" in report and "7.06" in report and str(PAPER_LINEAR_CM["cube"]) in report
    figures = sorted((out / "figures").glob("*.png"))
    assert {"model_selection.png", "pose_estimation.png", "friction_biasing.png", "mass_biasing.png",
            "objects.png", "training_friction_biasing_cube.png", "online_adaptation.png", "coverage.png"} <= {
        p.name for p in figures}
    for figure in figures:
        assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"figures/{figure.name}" in report
    paths = viz.read_entity_paths(out / "recording.rrd")
    assert "/world/experiments/pose_estimation/cube/estimates" in paths
    assert any(p.startswith("/world/model/training/cube_selection_selection") for p in paths)
    predictions = {p for p in paths if p.startswith("/world/model/prediction/")}
    assert any(p.endswith("/final_true") for p in predictions)
    assert "/world/model/prediction/model_selection/cylinder/adaptive/c0a1/final_true" in predictions
    # shape transfer: the pooled model's examples, and its residual model's with their rollouts, cell by cell
    shapes = "/world/model/prediction/shape_transfer/prism_thin/pushtorch_shapes"
    assert {f"{shapes}/c0a{j}/final_true" for j in range(2)} <= predictions
    assert {f"{shapes}/pushtorch_residual/c0a{j}/rollouts/finals" for j in range(2)} <= predictions
    # online adaptation: the posterior on the timeline of observed pushes, with each observed push
    online = {p for p in paths if p.startswith("/world/experiments/online_adaptation/cube/")}
    assert any(p.endswith("/posterior/samples") for p in online)
    assert any(p.endswith("/observed/cloud") for p in online) and any(p.endswith("/observed/final") for p in online)
    assert "Online adaptation" in report and "Separability" in report
    assert summary["recording"] == str(out / "recording.rrd")


def test_tiny_quickstart_recording_opens_ready_to_review(tiny_run):
    """Issue 22's acceptance: the quickstart's recording holds a blueprint, ground-truth pushes on
    sim_time and scalar series (read back with Rerun's own reader)."""
    from rerun.chunk import RrdReader

    from pushtorch.viz.blueprint import read_blueprint

    _, out, _ = tiny_run
    blueprint = read_blueprint(out / "recording.rrd")
    assert blueprint["timeline"] == "sim_time"
    kinds = {view["class"] for view in blueprint["views"]}
    assert {"3D", "TextDocument", "TimeSeries"} <= kinds
    on_sim_time, series, points = set(), set(), {}
    for chunk in RrdReader(str(out / "recording.rrd")).store().stream().to_chunks():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if "sim_time" in names:
            on_sim_time.add(str(chunk.entity_path))
        if "Scalars:scalars" in names:
            series.add(str(chunk.entity_path))
        if str(chunk.entity_path).endswith("/rollouts/point") and "Points3D:positions" in names:
            points[str(chunk.entity_path)] = batch.column("Points3D:positions").to_pylist()[0]
    # the residual model's logged example is the prediction its set holds (made once, kept for the recording): its
    # point, whichever the model reports
    residual_set = PredictionSet.load(next((out / "predictions").glob("shape_transfer_prism_thin_shapes*.npz")))
    for j in range(2):
        point = points["/world/model/prediction/shape_transfer/prism_thin/pushtorch_shapes/pushtorch_residual"
                       f"/c0a{j}/rollouts/point"]
        assert torch.allclose(torch.tensor(point).reshape(3), residual_set.residual_final.take((0, j)).p, atol=1e-6)
    assert any(p.endswith("/truth_push/object") for p in on_sim_time)
    assert any(p.endswith("/truth_push/robot") for p in on_sim_time)
    assert any(p.startswith("/metrics/") and "/hacc/" in p for p in series)
    assert any(p.endswith("/motion/best_log_prob") for p in series)


@pytest.mark.slow  # about 30 s in the suite (the whole tiny run again); a killed run's resume stays in the default
# suite (test_records, test_bad_inputs)
def test_rerun_in_the_same_directory_reuses_models_and_predictions(tiny_run):
    cfg, out, _ = tiny_run
    models = sorted((out / "models").glob("*.npz"))
    stamps = {p: p.stat().st_mtime_ns for p in models + sorted((out / "predictions").glob("*.npz"))}
    before = json.loads((out / "results.json").read_text())["records"]
    quickstart.run(cfg, out)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert json.loads((out / "results.json").read_text())["records"] == before


@pytest.mark.slow  # 20 s: a second test set's run
def test_the_placement_spread_test_set_runs_beside_the_default_one_in_one_folder(tiny_run, tmp_path):
    import shutil

    cfg, out, _ = tiny_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    default_predictions = {p.name: p.stat().st_mtime_ns for p in (run / "predictions").glob("friction_*.npz")}
    spread_cfg = _compose([*TINY, "test_placement=spread", "~experiment.parts.model_selection",
                           "~experiment.parts.pose_estimation", "~experiment.parts.mass_biasing"])
    quickstart.run(spread_cfg, run)
    truth = sorted(p.name for p in (run / "truth").iterdir() if p.name.startswith("friction_biasing_cube"))
    spread = [name for name in truth if "_test_spread_lateral_jitter0.1_yaw_jitter_deg5" in name]
    assert spread and len(spread) * 2 == len(truth)  # each group's ground truth twice: model starts, spread starts
    assert {p.name: p.stat().st_mtime_ns for p in (run / "predictions").glob("friction_*.npz")
            if p.name in default_predictions} == default_predictions  # the default set untouched
    records = [r for r in json.loads((run / "results.json").read_text())["records"]
               if r["task"] == "prediction" and r["method"] == "pushtorch"]
    assert records and all(math.isfinite(r["hacc_mean"]) for r in records)
    assert "placement_spread" in (run / "report.md").read_text()


@pytest.mark.slow  # 10-12 s: a second world's run beside the tiny one
def test_the_pybullet_world_runs_beside_the_mujoco_one_in_one_folder(tiny_run, tmp_path):
    """world=pybullet: training pushes and truth in pybullet (cached apart from the default MuJoCo world's, which
    are named _mujoco), the peers in MuJoCo; results.json and the report name both engines; the MuJoCo caches are
    left as they were."""
    import shutil

    cfg, out, _ = tiny_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    before = {p.name: p.stat().st_mtime_ns for p in (run / "models").iterdir()}
    assert before and all(name.endswith(("_mujoco.npz", "_mujoco_residual_vs_pybullet.npz")) for name in before)
    pybullet_cfg = _compose([*TINY, "world=pybullet", "~experiment.parts.model_selection",
                             "~experiment.parts.pose_estimation", "~experiment.parts.mass_biasing",
                             "~experiment.parts.online_adaptation", "~experiment.parts.shape_transfer"])
    quickstart.run(pybullet_cfg, run)
    results = json.loads((run / "results.json").read_text())
    assert results["world"] == {"engine": "pybullet"} and results["physics"] == {"engine": "mujoco"}
    assert {p.name: p.stat().st_mtime_ns for p in (run / "models").iterdir() if p.name in before} == before
    pybullet_models = sorted(p.name for p in (run / "models").iterdir() if p.name not in before)
    assert pybullet_models and not any("_mujoco" in name.split("_residual_vs_")[0] for name in pybullet_models)
    manifests = [json.loads((p / "manifest.json").read_text()) for p in (run / "data").iterdir()
                 if not p.name.endswith("_mujoco")]
    assert manifests and all(m["settings"].get("engine", "pybullet") == "pybullet" for m in manifests)
    assert "**World: pybullet. Physics peers: mujoco.**" in (run / "report.md").read_text()


# slow: about 30 s each in the suite (a serial run of the part); the default suite keeps the same claim for Ray and
# local task workers (test_executors: the same shards and records either way)
@pytest.mark.slow
@pytest.mark.parametrize("part", ["pose_estimation", "friction_biasing", "online_adaptation"])
def test_the_parts_steps_in_worker_processes_give_the_records_of_a_serial_run(tiny_run, tmp_path, part):
    """The default run fills a part's caches in forked task workers, and its loop reads each group as its task
    ends; experiment.workers=1 does every step in this process, in the loop's order. The records are the same."""
    _, out, _ = tiny_run
    others = {"model_selection", "pose_estimation", "friction_biasing", "mass_biasing", "online_adaptation",
              "shape_transfer"} - {part}
    serial_cfg = _compose([*TINY, "experiment.workers=1", *(f"~experiment.parts.{p}" for p in sorted(others))])
    quickstart.run(serial_cfg, tmp_path / "serial")

    def records(run):
        every = json.loads((run / "results.json").read_text())["records"]
        if part in ("online_adaptation", "pose_estimation"):
            task = "online" if part == "online_adaptation" else "pose"
            return sorted(json.dumps(r, sort_keys=True) for r in every if r["task"] == task)
        return sorted(json.dumps(r, sort_keys=True) for r in every
                      if r["task"] == "prediction" and (r["model"] or "").startswith("friction"))

    spread, serial = records(out), records(tmp_path / "serial")
    assert spread and len(spread) == len(serial)
    differ = sum(a != b for a, b in zip(spread, serial, strict=True))
    assert spread == serial, f"{differ} of {len(spread)} records differ ({part})"


def test_the_logged_examples_come_from_the_workers_that_predicted_them(tiny_run):
    """With task workers, a recording's examples are predicted (with their history) by the task that predicts
    their set, kept beside it and logged from there: the submitting process reads and removes them, and
    predicts nothing itself."""
    _, out, _ = tiny_run
    folder = out / "examples"
    assert folder.is_dir() and not any(folder.iterdir())
    paths = viz.read_entity_paths(out / "recording.rrd")
    assert any("/friction_biasing/" in p and "/c0a0/" in p for p in paths)


def test_a_cluster_task_receives_a_trained_model_as_its_files_path_and_a_context_without_its_recording(tiny_run):
    import pickle

    from pushtorch.experiments.common import context_from_config
    from pushtorch.experiments.tasks import models_by_path, saved_as, saved_models

    cfg, out, _ = tiny_run
    path = sorted((out / "models").glob("cube_general_*.npz"))[0]
    model = saved_as(load_model(path), load_model, str(path))
    assert saved_models()[id(model)][0] is model
    ctx = context_from_config(cfg, out)
    ctx.recording = lambda: None  # as an open recording: not picklable, and not for a task
    ctx.task_counts["models trained | here"] = 1
    with models_by_path():
        payload = pickle.dumps((model, ctx))
    assert len(payload) < 20_000 and str(path).encode() in payload  # the path, not the kernels' tensors
    back, task_ctx = pickle.loads(payload)
    assert back is not model and back.arrays().keys() == model.arrays().keys()
    assert all(torch.equal(back.arrays()[k], v) for k, v in model.arrays().items())
    assert task_ctx.recording is None and task_ctx.executor.kind == "local" and task_ctx.workers == 1
    assert task_ctx.task_counts == {} and task_ctx.run_dir == ctx.run_dir and task_ctx.settings == ctx.settings
    with pytest.raises((TypeError, pickle.PicklingError, AttributeError)):  # outside, a context pickles as it is
        pickle.dumps(ctx)
    key = id(model)
    del model, back
    assert key not in saved_models()  # an entry leaves with its model


@pytest.mark.slow  # 30-55 s: a Ray instance and its workers; Ray's shards and tasks stay in make test (test_executors)
def test_the_friction_biasing_part_on_ray_writes_the_same_records(tiny_run, tmp_path):
    """executor=ray: the training pushes as Ray shards; the models, the predictions with their peers, the truth and
    the scores as Ray tasks (a real local instance). The records are those of the local run."""
    ray = pytest.importorskip("ray")
    _, out, _ = tiny_run
    cfg = _compose([*TINY, "executor=ray", "executor.num_cpus=2", "~experiment.parts.model_selection",
                    "~experiment.parts.pose_estimation", "~experiment.parts.mass_biasing",
                    "~experiment.parts.online_adaptation"])
    try:
        quickstart.run(cfg, tmp_path / "ray")
    finally:
        ray.shutdown()

    def friction(path):
        return [r for r in json.loads((path / "results.json").read_text())["records"]
                if str(r.get("model", "")).startswith("friction:")]

    assert friction(tmp_path / "ray") and friction(tmp_path / "ray") == friction(out)
    # the models, and the predictions with their peers, truth and scores, ran as Ray tasks (a node of its own)
    tasks = json.loads((tmp_path / "ray" / "results.json").read_text())["tasks"]
    assert {key.split(" | ")[0] for key in tasks if "/ray-node-" in key} == {
        "models trained", "groups predicted, pushed and scored"}, tasks


@pytest.mark.slow  # a process per array task (submitit's local backend): about a minute on two cores
def test_the_friction_biasing_part_as_slurm_arrays_writes_the_same_records(tiny_run, tmp_path):
    """executor=slurm (submitit's local backend, the same arrays a Slurm cluster runs): the training pushes, the
    models and the groups as array tasks into the run folder; the records are those of the local run."""
    pytest.importorskip("submitit")
    _, out, _ = tiny_run
    cfg = _compose([*TINY, "executor=slurm", "executor.cluster=local", "~experiment.parts.model_selection",
                    "~experiment.parts.pose_estimation", "~experiment.parts.mass_biasing",
                    "~experiment.parts.online_adaptation"])
    quickstart.run(cfg, tmp_path / "slurm")

    def friction(path):
        return [r for r in json.loads((path / "results.json").read_text())["records"]
                if str(r.get("model", "")).startswith("friction:")]

    assert friction(tmp_path / "slurm") and friction(tmp_path / "slurm") == friction(out)
    tasks = json.loads((tmp_path / "slurm" / "results.json").read_text())["tasks"]
    assert {key.split(" | ")[0] for key in tasks} >= {"models trained", "groups predicted, pushed and scored"}, tasks


def _session_processes(session: int) -> list[tuple[int, bytes]]:
    """(pid, cmdline) of every process of a session (/proc/<pid>/stat's sixth field)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
                if int(stat.rsplit(")", 1)[1].split()[3]) == session:
                    found.append((int(entry.name), (entry / "cmdline").read_bytes()))
            except (OSError, ValueError, IndexError):
                pass
    return found


def _kill_session(session: int) -> None:
    import os
    import signal

    for pid, _ in _session_processes(session):
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


@pytest.mark.slow  # about 25 s itself, but it needs the tiny run (70 s) on its worker: over a minute in the suite
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the nodes' processes in /proc")
def test_a_ray_cluster_that_loses_a_node_finishes_with_every_record_once(tiny_run, tmp_path, monkeypatch):
    """A head and a worker node on loopback (one CPU each, each a session of its own) run the friction-biasing
    part; the worker node is killed, raylet and workers at once, while it runs a task. The run finishes on the
    head, and its records are the local run's, each once."""
    import os
    import socket
    import tempfile
    import threading
    import time

    ray = pytest.importorskip("ray")
    _, out, _ = tiny_run
    with socket.socket() as probe:  # a free port for the head
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    # `ray start` notes its cluster in /tmp/ray/ray_current_cluster, where a later ray.init() without an address
    # would look for it: the note is put back as it was
    current = Path(tempfile.gettempdir()) / "ray" / "ray_current_cluster"
    noted = current.read_text() if current.is_file() else None
    env = dict(os.environ, RAY_AUTH_MODE="disabled")
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    ray_cli = [sys.executable, "-m", "ray.scripts.scripts", "start", "--block", "--node-ip-address", "127.0.0.1",
               "--num-cpus", "1", "--disable-usage-stats"]
    head = subprocess.Popen([*ray_cli, "--head", "--port", str(port), "--include-dashboard=false"], env=env,
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = None
    try:
        deadline = time.monotonic() + 60
        while True:  # the head's GCS answers
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "the Ray head did not start"
                time.sleep(0.5)
        worker = subprocess.Popen([*ray_cli, "--address", f"127.0.0.1:{port}"], env=env, start_new_session=True,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        ray.init(address=f"127.0.0.1:{port}", include_dashboard=False, log_to_driver=False)
        while sum(n["Alive"] for n in ray.nodes()) < 2:
            assert time.monotonic() < deadline + 60, "the worker node did not join"
            time.sleep(0.5)
        cfg = _compose([*TINY, "executor=ray", f"executor.address=127.0.0.1:{port}",
                        "~experiment.parts.model_selection", "~experiment.parts.pose_estimation",
                        "~experiment.parts.mass_biasing", "~experiment.parts.online_adaptation"])
        result = {}

        def run():
            try:
                result["summary"] = quickstart.run(cfg, tmp_path / "two_nodes")
            except BaseException as exc:  # noqa: BLE001 - reported below
                result["error"] = exc

        thread = threading.Thread(target=run)
        thread.start()
        killed, deadline = None, time.monotonic() + 300
        while killed is None and thread.is_alive() and time.monotonic() < deadline:
            if any(cmd.startswith((b"ray::_remote_task", b"ray::run_shard_task"))
                   for _, cmd in _session_processes(worker.pid)):
                killed = [cmd.split(b"\0")[0] for _, cmd in _session_processes(worker.pid)]
                _kill_session(worker.pid)
            time.sleep(0.05)
        thread.join(timeout=900)
        assert killed is not None, "no task was caught running on the worker node"
        assert "error" not in result, result.get("error")
        assert "summary" in result, "the run did not finish"
        gone = time.monotonic() + 120  # Ray marks a node dead after its missed health checks
        while sum(n["Alive"] for n in ray.nodes()) != 1 and time.monotonic() < gone:
            time.sleep(1.0)
        assert sum(n["Alive"] for n in ray.nodes()) == 1  # the worker node is gone
    finally:
        ray.shutdown()
        for node in (worker, head):
            if node is not None:
                _kill_session(node.pid)
                node.wait(timeout=30)
        if noted is None:
            current.unlink(missing_ok=True)
        else:
            current.write_text(noted)

    def friction(path):
        return sorted(json.dumps(r, sort_keys=True) for r in json.loads((path / "results.json").read_text())["records"]
                      if str(r.get("model", "")).startswith("friction:"))

    assert friction(tmp_path / "two_nodes") and friction(tmp_path / "two_nodes") == friction(out)


@pytest.mark.slow  # the console scripts themselves stay in the default suite (test_layout)
def test_train_and_predict_apps_on_the_runs_data(tiny_run, tmp_path):
    _, out, _ = tiny_run
    base = {"object": {"name": "cube", "path": None, "scale": 1.0},
            "model": {"settings": {"query_kernels": 200, "anneal_candidates": 40, "anneal_steps": 8,
                                   "environment_kernels": 200, "manipulator_kernels": 40}}}
    data = out / "data" / "cube_low_paper_default_lateral_jitter0.1_yaw_jitter_deg5_mujoco"  # spread, MuJoCo world
    trained = train_from_config({**base, "data": str(data), "name": "tiny", "recording": False},
                                tmp_path / "t")
    model = load_model(trained["model"])
    assert model.name == "tiny" and trained["pushes"] == 2 * 3 and len(model.motions) == 2
    with pytest.raises(InvalidParameterError):  # the data are the cube's
        train_from_config({**base, "object": {"name": "cylinder"}, "data": str(data)}, tmp_path / "bad")
    cfg = {"models": [trained["model"]], "object": {"name": "prism_thin"}, "yaw_deg": 10.0, "actions": [1],
           "truth_samples": 2, "friction": {"kind": "normal", "mean": 0.1, "std": 0.005},
           "mass": {"kind": "fixed", "value": 0.5}, "recording": True}
    summary = predict_from_config(cfg, tmp_path / "p")
    payload = json.loads((tmp_path / "p" / "predictions.json").read_text())
    assert summary["predictions"] == 1 and payload["predictions"][0]["action_index"] == 1
    assert len(payload["predictions"][0]["truth_final"]) == 2 and summary["hacc_mean"] >= 0
    paths = viz.read_entity_paths(tmp_path / "p" / "recording.rrd")
    assert "/world/model/prediction/action_1/final_true" in paths
    with pytest.raises(PushtorchError):
        predict_from_config({**cfg, "actions": [7]}, tmp_path / "p2")


def test_cli_help_lists_the_experiments():
    result = subprocess.run([sys.executable, "-m", "pushtorch", "--help"], capture_output=True, text=True,
                            timeout=120, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-2000:]
    for name in ("quickstart", "model_selection", "pose_estimation", "friction_biasing", "mass_biasing"):
        assert name in result.stdout
    assert "model: default, quick" in result.stdout


@pytest.mark.slow
def test_full_paper_protocol(tmp_path):
    """tools/reproduce_paper.py at the paper's sizes: hours on 2 cores (docs/experiments.md has the times).

    Set PUSHTORCH_PAPER_RUN=<folder> to keep (and resume) the run; by default it goes to a temporary folder.
    """
    import os

    out = Path(os.environ.get("PUSHTORCH_PAPER_RUN", tmp_path / "paper"))
    result = subprocess.run([sys.executable, str(ROOT / "tools" / "reproduce_paper.py"), "--out", str(out)],
                            cwd=ROOT)
    assert result.returncode == 0
    expected_n = {"selection": 50 * 3 * 4, "pose": 100, "prediction": 100 * 3 * 3}
    checks = []
    for name, count in (("model_selection", 6), ("pose_estimation", 6), ("friction_biasing", 6 * 4 * 3 * 8),
                        ("mass_biasing", 6 * 4 * 3 * 8)):  # objects x models x conditions x methods
        records = primary(json.loads((out / name / "results.json").read_text())["records"])
        assert len(records) == count
        for r in records:
            if not (r["task"] == "pose" and r["method"] == "centroid"):
                assert r["n"] == expected_n[r["task"]]
        checks += acceptance_checks(records)
    assert checks and all(c["passed"] for c in checks), [c for c in checks if not c["passed"]]
