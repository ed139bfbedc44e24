"""Typed, bounded configs (issue 21): every app refuses a bad value by name, and a refused run leaves no folder.

The battery composes each app's real config with one bad override and asserts :class:`ConfigError` naming
the key; the shipped experiment configs and every documented command (tests/test_documented_commands.py)
must pass the same check. A few cases run the real command line: exit 2, one line, no run folder (also for
Hydra's own composition errors and for an error found after Hydra made the folder).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from pushtorch.apps.config_check import ConfigError, check_config
from pushtorch.errors import InvalidParameterError
from pushtorch.experiments.registry import experiment_names

CONF = Path(__file__).resolve().parents[1] / "conf"


def _compose(app: str, overrides: list[str]):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="pushtorch.conf", version_base="1.3"):
        return compose(app, overrides=overrides, return_hydra_config=True)


BAD = [
    # (app, overrides, a fragment the message must hold)
    ("config", ["seed=abc"], "seed must be an integer"),
    ("config", ["experiment=shape_transfer", "model.training_objects=[shapes:box:5:998]"], "held-out"),
    ("config", ["experiment=shape_transfer", "model.training_objects=[shapes:torus:5]"], "torus"),
    ("config", ["experiment=shape_transfer", "experiment.ensemble=0"], "experiment.ensemble"),
    ("config", ["experiment=shape_transfer", "experiment.coverage_band=[0.9,0.8]"], "coverage_band"),
    ("config", ["experiment=shape_transfer", "model.settings.transfer_scale=0"], "transfer_scale"),
    ("config", ["seed=1e20"], "seed must be an integer"),
    ("config", ["seed=-1"], "seed must be an integer"),
    ("config", ["model.settings.position_frames=2.5"], "model.settings.position_frames must be an integer"),
    ("config", ["model.settings.anneal_candidates=1e9"], "anneal_candidates"),
    ("config", ["model.settings.voxel_size=0"], "voxel_size"),
    ("config", ["+model.settings.typo=1"], "unknown model settings"),
    ("config", ["model.samples_per_action=abc"], "model.samples_per_action"),
    ("config", ["experiment.actions.duration=1e9"], "experiment.actions.duration"),
    ("config", ["experiment.actions.duration=1e5"], "experiment.actions.duration"),
    ("config", ["experiment.actions.count=0"], "experiment.actions.count"),
    ("config", ["experiment.actions.angle_range_deg=[10,-10]"], "angle_range_deg"),
    ("config", ["experiment.name=common"], "not an experiment"),
    ("config", ["experiment.name=../x"], "cannot be part of a file name"),
    ("config", ["experiment.progress=maybe"], "experiment.progress must be true or false"),
    ("config", ["experiment.workers=-2"], "experiment.workers"),
    ("config", ["experiment.parts.model_selection.truth_samples=0"], "truth_samples"),
    ("config", ["experiment.parts.model_selection.objects=[cube,a/../b]"], "cannot be part of a file name"),
    ("config", ["model.friction=nonsense"], "not in priors.friction"),
    ("config", ["priors.friction.general.low=abc"], "priors.friction.general.low must be a number"),
    ("config", ["priors.mass.high.kind=gamma"], "unknown prior kind"),
    ("config", ["sim.time_step=abc"], "sim.time_step"),
    ("config", ["sim.ground_half_extent=0"], "sim.ground_half_extent"),
    ("config", ["object=mesh"], "object.path is not set"),
    ("config", ["object=cube", "object.name=sphere"], "not a catalogue object"),
    ("config", ["object=cube", "object.scale=abc"], "object.scale"),
    ("simulate", ["samples_per_action=abc"], "samples_per_action must be an integer"),
    ("simulate", ["samples_per_action=2.5"], "samples_per_action must be an integer"),
    ("simulate", ["friction=fixed", "friction.value=abc"], "friction.value must be a number"),
    ("simulate", ["mass=fixed", "mass.value=-1"], "mass"),
    ("simulate", ["actions.speed=0"], "actions.speed"),
    ("simulate", ["shard_size=0"], "shard_size"),
    ("simulate", ["start_method=thread"], "start_method must be one of"),
    ("simulate", ["samples_per_action=100000", "actions.duration=60", "sim.record_rate=200"], "GiB"),
    ("train", [], "data is not set"),
    ("train", ["data=runs/x", "allow_partial=yes"], "allow_partial must be true or false"),
    ("train", ["data=runs/x", "name=a/b"], "cannot be part of a file name"),
    ("predict", [], "models is not set"),
    ("predict", ["models=[a.npz]", "x=60"], "off the simulated ground"),
    ("predict", ["models=[a.npz]", "y=nan"], "y must be a number"),
    ("predict", ["models=[a.npz]", "actions=[0,-1]"], "actions must be 'all'"),
    ("predict", ["models=[a.npz]", "truth_samples=-1"], "truth_samples"),
    ("predict", ["models=[a.npz]", "duration=1e5"], "duration"),
    ("predict", ["models=[a.npz]", "recording=1"], "recording must be true or false"),
]


@pytest.mark.parametrize(("app", "overrides", "fragment"), BAD, ids=[" ".join([a, *o]) for a, o, _ in BAD])
def test_a_bad_value_is_refused_by_name(app, overrides, fragment):
    with pytest.raises(ConfigError, match=None) as caught:
        check_config(_compose(app, overrides), app)
    assert fragment in str(caught.value)
    assert "\n" not in str(caught.value)
    assert isinstance(caught.value, InvalidParameterError)


@pytest.mark.parametrize("experiment", sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))
def test_every_shipped_experiment_passes(experiment):
    check_config(_compose("config", [f"experiment={experiment}"]), "config")
    assert experiment in experiment_names()


@pytest.mark.parametrize(("app", "overrides"), [
    ("simulate", []), ("simulate", ["object=hybrid", "friction=general", "mass=high", "workers=1"]),
    ("train", ["data=[runs/a,runs/b]", "model=quick"]), ("predict", ["models=a.npz", "x=1.5", "yaw_deg=30"]),
    ("config", ["model.settings.anneal_steps=100.0"]),  # an integral float is the count
])
def test_good_values_pass(app, overrides):
    check_config(_compose(app, overrides), app)


def test_every_problem_is_named_in_one_line():
    with pytest.raises(ConfigError) as caught:
        check_config(_compose("config", ["seed=abc", "sim.time_step=-1", "experiment.progress=2"]), "config")
    message = str(caught.value)
    assert "seed" in message and "sim.time_step" in message and "experiment.progress" in message


def _cli(tmp_path, *argv):
    env = {k: v for k, v in os.environ.items() if not k.startswith("HYDRA")}
    return subprocess.run([sys.executable, "-m", *argv], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120, env=env)


# one case per path a refusal takes (the callback, a sweep, Hydra's composition, after the folder is made);
# the rest are slow here (a subprocess each) and covered by tools/bad_input_battery.py as well
_SLOW = pytest.mark.slow


@pytest.mark.parametrize("argv", [
    pytest.param(("pushtorch", "seed=abc"), id="seed"),
    pytest.param(("pushtorch", "-m", "model=tiny", "seed=1,abc"), id="sweep"),
    pytest.param(("pushtorch.apps.simulate", "actions.duration=1e5"), id="duration", marks=_SLOW),
    pytest.param(("pushtorch.apps.predict", "models=[a.npz]", "x=1e9"), id="position", marks=_SLOW),
    pytest.param(("pushtorch.apps.train", "data=x", "hydra.run.dir=a_file/run"), id="folder-under-a-file", marks=_SLOW),
    pytest.param(("pushtorch", "experiment=nope"), id="unknown-option"),
    pytest.param(("pushtorch", "sed=1"), id="unknown-key", marks=_SLOW),
    pytest.param(("pushtorch", "-m", "model=tiny,huge"), id="unknown-option-in-a-sweep", marks=_SLOW),
    pytest.param(("pushtorch.apps.train", "data=nowhere"), id="error-after-the-folder-is-made"),
])
def test_the_command_line_exits_2_with_one_line_and_makes_no_folder(tmp_path, argv):
    (tmp_path / "a_file").write_text("")
    result = _cli(tmp_path, *argv)
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    app = argv[0].replace("pushtorch.apps.", "pushtorch-")  # an app's errors open with its console script's name
    assert len(lines) == 1 and lines[0].startswith(app + ":"), result.stderr
    assert "Traceback" not in result.stderr
    assert not any(tmp_path.glob("runs/*")), "a refused run leaves no run folder"
