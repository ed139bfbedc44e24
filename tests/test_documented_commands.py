"""Every documented command in README.md, docs/ and the configs' comments runs as written: the console scripts
(``pushtorch``, ``pushtorch-simulate``, ``pushtorch-train``, ``pushtorch-predict``, ``pushtorch-collect``),
``python -m pushtorch`` and ``python -m pushtorch.apps.<app>``.

Each command goes through the argument parser its app really uses (Hydra's, or ``pushtorch-collect``'s), so
an ``unrecognized arguments`` like the one that broke the README's sweep (overrides on both sides of ``-m``)
fails here; then every job of it (a sweep expanded into its combinations) is composed from the installed
configs (``pushtorch.conf``), Hydra's own config included, so an unknown group option or key fails here too.
Commands with a ``<placeholder>`` in inline prose (``experiment=<name>``) are templates, not commands, and are
skipped; in code blocks every command must compose.
"""

from __future__ import annotations

import itertools
import math
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra._internal.utils import get_args_parser
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

import pushtorch.apps.cli  # noqa: F401  (registers the pushtorch.job_dir resolver the output config uses)
from pushtorch.apps import collect
from pushtorch.apps.config_check import ConfigError, check_config

ROOT = Path(__file__).resolve().parents[1]
#: Console script → the config its Hydra app composes.
HYDRA_APPS = {"pushtorch": "config", "pushtorch-simulate": "simulate", "pushtorch-train": "train",
              "pushtorch-predict": "predict"}
#: ``python -m`` module → the console script it is.
MODULES = {"pushtorch": "pushtorch", "pushtorch.apps.experiment": "pushtorch",
           **{f"pushtorch.apps.{app}": f"pushtorch-{app}" for app in ("simulate", "train", "predict", "collect")}}
_COMMAND = re.compile(r"(?:\S*/)?(?:python3? -m (pushtorch[\w.]*)|(pushtorch(?:-[a-z]+)?))(?=\s|$)(.*)")


def _sources() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "conf").rglob("*.yaml"))]


def _joined_lines(text: str) -> list[str]:
    """Lines with backslash continuations joined (and a YAML comment's ``#`` and indent dropped)."""
    lines, pending = [], ""
    for raw in text.splitlines():
        line = re.sub(r"^\s*#\s?", "", raw) if pending and raw.lstrip().startswith("#") else raw
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        lines.append(pending + line)
        pending = ""
    return lines


def documented_commands() -> list[tuple[str, str, list[str]]]:
    """``(where, module, argv)`` of every documented command: a code-block or YAML-comment line that starts
    with one, and inline code spans unless they hold a ``<placeholder>`` or ``[overrides]``."""
    found = []
    for path in _sources():
        in_block = False
        for number, line in enumerate(_joined_lines(path.read_text()), 1):
            if line.lstrip().startswith("```"):
                in_block = not in_block
                continue
            if path.suffix == ".yaml":
                if not line.lstrip().startswith("#"):
                    continue
                line = line.lstrip().lstrip("#")
            if "`" in line and not in_block:
                candidates = [span for span in re.findall(r"`([^`]+)`", line)
                              if "<" not in span and "[overrides]" not in span]
            elif in_block or path.suffix == ".yaml":
                candidates = [line]
            else:
                candidates = []
            for candidate in candidates:
                match = _COMMAND.match(candidate.strip())
                if match:
                    script = MODULES.get(match.group(1), f"python -m {match.group(1)}") if match.group(1) \
                        else match.group(2)
                    argv = shlex.split(match.group(3), comments=True)
                    if match.group(2) == "pushtorch" and argv and not (argv[0].startswith("-") or "=" in argv[0]):
                        continue  # prose that names the package ("`pushtorch beats no-motion`"), not a command
                    found.append((f"{path.relative_to(ROOT)}:{number}", script, argv))
    return found


COMMANDS = documented_commands()


def test_the_docs_document_every_app():
    modules = {module for _, module, _ in COMMANDS}
    assert set(HYDRA_APPS) | {"pushtorch-collect"} <= modules, modules
    assert any("-m" in argv or "--multirun" in argv for _, _, argv in COMMANDS)  # the sweeps are checked too


def _jobs(argv_overrides: list[str], multirun: bool) -> list[list[str]]:
    """The overrides of each job: a sweep (``a=x,y``) expanded into every combination."""
    if not multirun:
        return [argv_overrides]
    parsed = OverridesParser.create().parse_overrides(argv_overrides)
    choices = []
    for text, override in zip(argv_overrides, parsed, strict=True):
        if override.is_sweep_override():
            key = text.partition("=")[0]
            choices.append([f"{key}={value}" for value in override.sweep_string_iterator()])
        else:
            choices.append([text])
    return [list(combination) for combination in itertools.product(*choices)]


@pytest.mark.parametrize("module", sorted(MODULES))
def test_every_app_runs_from_any_folder(module, tmp_path):
    """``python -m <app> --help`` outside the checkout: the app exists and finds its installed configs."""
    if module.endswith("collect"):
        return  # not a Hydra app: its parser is checked below
    result = subprocess.run([sys.executable, "-m", module, "--help"], cwd=tmp_path, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "Configuration groups" in result.stdout and "object:" in result.stdout


@pytest.fixture
def slurm_on_path(tmp_path, monkeypatch):
    """A stand-in ``sbatch`` on the PATH: the documented cluster commands are checked as configurations here,
    while whether this machine has Slurm is the run's own check (tests/test_executors.py)."""
    script = tmp_path / "sbatch"
    script.write_text("#!/bin/sh\nexit 0\n")
    script.chmod(0o755)
    monkeypatch.setenv("PATH", f"{tmp_path}{os.pathsep}{os.environ.get('PATH', '')}")


@pytest.mark.parametrize(("where", "module", "argv"), COMMANDS, ids=[c[0] for c in COMMANDS])
def test_documented_command_runs_as_written(where, module, argv, slurm_on_path):
    if module == "pushtorch-collect":
        if argv:  # a bare mention of the app names no folders
            collect.parser().parse_args(argv)  # exits (SystemExit) on arguments it does not take
        return
    assert module in HYDRA_APPS, f"{where}: `{module}` is not one of pushtorch's apps"
    args = get_args_parser().parse_args(argv)  # the parser @hydra.main uses: unknown arguments exit here
    for overrides in _jobs(args.overrides, args.multirun):
        GlobalHydra.instance().clear()
        with initialize_config_module(config_module="pushtorch.conf", version_base="1.3"):
            cfg = compose(HYDRA_APPS[module], overrides=overrides, return_hydra_config=True)
        assert OmegaConf.select(cfg, "hydra.job.name").startswith("pushtorch"), where
        try:  # types, bounds and names as the app's callback checks them
            check_config(cfg, HYDRA_APPS[module])
        except ConfigError as exc:
            # a bare mention of an app (`pushtorch-train`) leaves its mandatory keys to the reader
            assert not argv and "is not set" in str(exc), f"{where}: {exc}"


@pytest.mark.slow  # 20-30 s; the shipped table trains from the command line in tests/test_tables.py
def test_the_push_table_example_trains_and_predicts_as_written(tmp_path):
    """docs/usage.md's push-table example, run as written from a folder that sees the shipped table: the command
    trains from tests/data/lab_table, the Python block predicts a push and conditions on three rows."""
    section = (ROOT / "docs" / "usage.md").read_text().split("## Your own pushes: a push table", 1)[1]
    blocks = re.findall(r"```(bash|python)\n(.*?)```", section.split("\n## ", 1)[0], re.S)
    assert [kind for kind, _ in blocks] == ["bash", "python"]
    (tmp_path / "tests").symlink_to(ROOT / "tests")
    command = blocks[0][1].strip().replace(".venv/bin/", f"{Path(sys.executable).parent}/")
    subprocess.run(shlex.split(command), cwd=tmp_path, check=True, capture_output=True, timeout=600)
    assert (tmp_path / "runs" / "lab_table" / "model.npz").is_file()
    result = subprocess.run([sys.executable, "-c", blocks[1][1]], cwd=tmp_path, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    first, second = result.stdout.strip().splitlines()[-2:]
    assert first.startswith("tensor([") and 0.0 < float(second) < 2.0  # a pose, and a friction coefficient


@pytest.mark.slow  # 25 s: the default suite ran 10:58 on the Intel host with it (make test-slow runs it)
def test_the_planning_example_scores_256_candidates_as_written(small_model, tmp_path):
    """docs/usage.md's planning example, run as written against a small cube model saved where it looks
    (runs/cube.npz): 256 candidates scored, the best three printed with finite scores."""
    section = (ROOT / "docs" / "usage.md").read_text().split("### Many candidate pushes of one object", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    (tmp_path / "runs").mkdir()
    small_model("cube").save(tmp_path / "runs" / "cube.npz")
    result = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-2000:]
    lines = [line for line in result.stdout.splitlines() if line.startswith("candidate ")]
    scores = [float(line.rsplit("log p ", 1)[1]) for line in lines]
    assert len(lines) == 3 and all(math.isfinite(v) for v in scores) and scores == sorted(scores, reverse=True)
