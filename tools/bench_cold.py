"""Cold start of the library (issue 23, item 4): import, first and warm prediction in a fresh process.

A library user's first ``predict`` pays for everything a long run amortises: imports, lazily built kernel
layouts and, if the fast path is compiled, torch.compile's tracing and code generation. This benchmark
trains (once, cached under ``--cache``) a cube model at the quickstart's sizes (conf/model/quick.yaml:
60 pushes per action, 3 actions, the quickstart's protocol placements, 1,000 query kernels, 200 candidates
× 50 steps), then starts a fresh Python process per compile mode and times, in that process:

* ``import_s``: ``import pushtorch`` and the modules a prediction needs (``pushtorch.predict``: torch,
  open3d, pytorch_kinematics);
* ``first_predict_s``: the first ``pushtorch.predict`` of a saved model (loaded beforehand, not timed) on
  a prism's partial cloud (captured beforehand);
* ``warm_predict_s``: the median of the next five predictions (other yaws, other seeds).

The library's default (``PUSHTORCH_COMPILE`` unset: eager, since the process declares no long run, see
:func:`pushtorch.kde.declare_long_run`) is measured last; ``PUSHTORCH_COMPILE=1`` (the fused functions
compiled, as in a long run) is measured first, and the ratio of the two printed, since both ran on the CPU
in the same conditions. The last line is exactly
``import_s=<..> first_predict_s=<..> warm_predict_s=<..>`` of the default. Targets on the 2-core machine:
``first_predict_s <= 2.0``, ``warm_predict_s <= 0.5``.

    .venv/bin/python tools/bench_cold.py [--cache runs/bench_cold]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Runs in the fresh process: prints one JSON line of timings.
_CHILD = r"""
import json, statistics, sys, time
started = time.perf_counter()
import pushtorch
import pushtorch.prediction
import_s = time.perf_counter() - started
model = pushtorch.load_model(sys.argv[1])
prism = pushtorch.load_object("prism_thin")
clouds = [pushtorch.capture_partial_cloud(prism, prism.resting_pose(yaw=0.2 * i)) for i in range(6)]
started = time.perf_counter()
first = pushtorch.predict(model, clouds[0], model.actions[1])
first_s = time.perf_counter() - started
warm = []
for i in range(1, 6):
    started = time.perf_counter()
    pushtorch.predict(model, clouds[i], model.actions[i % len(model.actions)], generator=i)
    warm.append(time.perf_counter() - started)
print(json.dumps({"import_s": import_s, "first_predict_s": first_s, "warm_predict_s": statistics.median(warm),
                  "compiled": pushtorch.kde.fast_path_compiled()}))
"""


def quickstart_model(folder: Path) -> Path:
    """The cached quickstart-size cube model (conf/model/quick.yaml, the spread protocol), trained on first use
    (simulation and training, ~1-2 min on 2 cores)."""
    from bench_predict import paper_size_model
    from omegaconf import OmegaConf

    from pushtorch.models.settings import ModelSettings
    from pushtorch.sim.plan import Placement

    conf = ROOT / "conf"
    model_conf = OmegaConf.merge(OmegaConf.load(conf / "model" / "default.yaml"),
                                 OmegaConf.load(conf / "model" / "quick.yaml"))
    placement = Placement(**OmegaConf.to_container(OmegaConf.load(conf / "protocol" / "spread.yaml")))
    settings = ModelSettings.from_mapping(OmegaConf.to_container(model_conf.settings))
    pushes = int(model_conf.samples_per_action)
    paper_size_model("cube", pushes, folder, settings, placement, tag="_quick")
    return folder / f"cube_{pushes}_quick.npz"


def measure(model_path: Path, compile_mode: str | None) -> dict:
    """One fresh process's timings with ``PUSHTORCH_COMPILE`` set to ``compile_mode`` (None: unset)."""
    env = dict(os.environ)
    env.pop("PUSHTORCH_COMPILE", None)
    if compile_mode is not None:
        env["PUSHTORCH_COMPILE"] = compile_mode
    result = subprocess.run([sys.executable, "-c", _CHILD, str(model_path)], capture_output=True, text=True,
                            env=env, cwd=ROOT, check=False)
    if result.returncode != 0:
        raise SystemExit(f"the timed process failed:\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", default="runs/bench_cold", help="model cache folder")
    args = parser.parse_args()
    folder = Path(args.cache)
    folder.mkdir(parents=True, exist_ok=True)
    sys.path.insert(0, str(ROOT / "tools"))
    from bench_predict import cpu_name

    model_path = quickstart_model(folder)

    print(f"cpu {cpu_name()!r} ({os.cpu_count()} cores) load_average={os.getloadavg()[0]:.2f}")
    compiled = measure(model_path, "1")
    default = measure(model_path, None)
    for label, t in (("compiled (PUSHTORCH_COMPILE=1)", compiled), ("library default", default)):
        print(f"{label}: import {t['import_s']:.2f} s, first predict {t['first_predict_s']:.2f} s, "
              f"warm predict {t['warm_predict_s']:.3f} s (fast path compiled: {t['compiled']})")
    print(f"ratios compiled/default: first {compiled['first_predict_s'] / default['first_predict_s']:.1f}, "
          f"warm {compiled['warm_predict_s'] / default['warm_predict_s']:.2f}")
    print(f"import_s={default['import_s']:.2f} first_predict_s={default['first_predict_s']:.2f} "
          f"warm_predict_s={default['warm_predict_s']:.3f}")


if __name__ == "__main__":
    main()
