"""The README's main job (`make demo` → `python -m pushtorch`) end to end, read back from its .rrd."""

import subprocess
import sys
from pathlib import Path

from pushtorch import viz


def test_main_job_writes_a_recording_with_the_logged_entities(tmp_path: Path):
    run_dir = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "-m", "pushtorch", f"hydra.run.dir={run_dir}", "experiment=perception_demo",
         "experiment.objects=[cube,cylinder]"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert result.returncode == 0, result.stderr[-2000:]
    recording = run_dir / "recording.rrd"
    assert recording.is_file() and recording.stat().st_size > 10_000
    paths = viz.read_entity_paths(recording)
    for name in ("cube", "cylinder"):
        assert f"/world/objects/{name}/mesh" in paths
        assert f"/world/clouds/{name}/full_cloud" in paths
        assert f"/world/clouds/{name}/partial_cloud" in paths
        assert f"/world/clouds/{name}/features" in paths
    assert "/world/objects/hybrid/mesh" not in paths  # only what was asked for
    assert (run_dir / "resolved_config.yaml").is_file()


def test_unknown_experiment_is_a_clear_error(tmp_path: Path):
    result = subprocess.run(
        [sys.executable, "-m", "pushtorch", f"hydra.run.dir={tmp_path}", "experiment=nonexistent"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert result.returncode != 0
    assert "nonexistent" in result.stderr
