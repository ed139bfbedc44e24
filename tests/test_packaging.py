"""An installed pushtorch carries its configs, and users can add their own (README, "Your own configs").

The full check (a wheel installed into a fresh environment at the declared lower bounds, run from outside the
checkout) is `make check-install`, which CI runs; these are its fast parts.
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

ROOT = Path(__file__).resolve().parents[1]


def test_every_config_group_folder_is_a_listed_package():
    packages = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {"pushtorch.conf." + ".".join(p.relative_to(ROOT / "conf").parts)
               for p in (ROOT / "conf").rglob("*") if p.is_dir() and p.name != "__pycache__"}
    assert folders <= packages, f"add to pyproject's packages: {sorted(folders - packages)}"


def test_the_wheel_carries_every_config_and_asset(tmp_path: Path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                    str(tmp_path), str(ROOT)], check=True, capture_output=True, timeout=300)
    (wheel,) = tmp_path.glob("pushtorch-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    configs = {"pushtorch/conf/" + p.relative_to(ROOT / "conf").as_posix() for p in (ROOT / "conf").rglob("*.yaml")}
    assert configs <= names, sorted(configs - names)
    assert {"pushtorch/py.typed", "pushtorch/assets/pioneer_bumper.urdf", "pushtorch/conf/__init__.py"} <= names


def test_a_users_config_folder_adds_options_beside_the_installed_ones(tmp_path: Path):
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "mine.yaml").write_text("defaults:\n  - quick\n  - _self_\nsamples_per_action: 7\n")
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="pushtorch.conf", version_base="1.3"):
        cfg = compose("config", overrides=[f"hydra.searchpath=[file://{tmp_path}]", "experiment=friction_biasing",
                                           "model=mine"])
    assert cfg.model.samples_per_action == 7 and cfg.model.settings.anneal_steps == 50  # quick's, then mine
