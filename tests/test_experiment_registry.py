"""The experiments' registry (pushtorch.experiments.registry): one name per shipped config, every entry runnable,
every quickstart part a known kind, and the names readable without importing any experiment.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from pushtorch.errors import InvalidParameterError
from pushtorch.experiments.registry import EXPERIMENTS, PARTS, experiment_names, experiment_runner, part_runner

CONF = Path(__file__).resolve().parents[1] / "conf"


def _experiment(stem: str):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        return compose("config", overrides=[f"experiment={stem}"]).experiment


def test_every_shipped_config_names_an_experiment_and_every_experiment_has_a_config():
    stems = sorted(path.stem for path in (CONF / "experiment").glob("*.yaml"))
    assert [_experiment(stem).name for stem in stems] == stems  # experiment=<file> runs experiment.name=<file>
    assert set(stems) == set(EXPERIMENTS) == set(experiment_names())


@pytest.mark.parametrize("name", sorted(EXPERIMENTS))
def test_every_experiment_loads_its_run_function(name):
    assert callable(experiment_runner(name))


@pytest.mark.parametrize("kind", sorted(PARTS))
def test_every_part_loads_its_run_part_function(kind):
    assert part_runner(kind).__name__ == "run_part"


def test_every_quickstart_part_is_a_known_kind():
    parts = _experiment("quickstart").parts
    assert {part.get("kind", name) for name, part in parts.items()} <= set(PARTS)


def test_the_biasing_experiments_share_one_run_function():
    assert experiment_runner("friction_biasing") is experiment_runner("mass_biasing")


def test_an_unknown_name_is_refused_with_the_known_ones():
    with pytest.raises(InvalidParameterError, match="not an experiment; known: .*quickstart"):
        experiment_runner("common")
    with pytest.raises(InvalidParameterError, match="unknown experiment part 'friction_biasing'"):
        part_runner("friction_biasing")


def test_the_names_are_read_without_importing_an_experiment():
    probe = ("import sys; from pushtorch.experiments.registry import experiment_names; experiment_names(); "
             "print(sorted(m for m in sys.modules if m.startswith('pushtorch.experiments.')))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['pushtorch.experiments.registry']"
