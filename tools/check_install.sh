#!/usr/bin/env bash
# What a user of a normal install gets (CI runs this after the tests, `make check-install`): the wheel,
# installed into a fresh environment with every dependency pinned to its declared lower bound, runs its
# commands from a folder outside the checkout (configs come from the package, not from ./conf).
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
python=${PYTHON:-python3}
torch_spec=${TORCH_SPEC:-torch==2.13.0}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

echo "check-install: building the wheel"
"$python" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q --upgrade pip
"$work/venv/bin/python" -m pip wheel -q --no-deps -w "$work/dist" "$repo"
"$repo/.venv/bin/python" "$repo/tools/lower_bounds.py" slurm > "$work/lower-bounds.txt"
echo "check-install: installing it at the lower bounds: $(tr '\n' ' ' < "$work/lower-bounds.txt")"
"$work/venv/bin/python" -m pip install -q "$torch_spec"
"$work/venv/bin/python" -m pip install -q -c "$work/lower-bounds.txt" "$(ls "$work"/dist/pushtorch-*.whl)[slurm]"

cd "$work"   # outside the checkout: nothing of the repository is on the path
"$work/venv/bin/pushtorch" --help > "$work/help.txt"   # (piped into grep -q, --help would lose its stdout)
grep -q "experiment: .*quickstart" "$work/help.txt"
"$work/venv/bin/python" -m pushtorch.apps.simulate --help > /dev/null
"$work/venv/bin/python" -m pushtorch.apps.train --help > /dev/null
"$work/venv/bin/python" -m pushtorch.apps.predict --help > /dev/null
echo "check-install: a tiny quickstart from $work"
start=$(date +%s)
"$work/venv/bin/python" -m pushtorch experiment=quickstart model=tiny experiment.progress=false \
    hydra.run.dir="$work/run" > "$work/quickstart.log" 2>&1 || { tail -40 "$work/quickstart.log"; exit 1; }
grep "checks:" "$work/quickstart.log"
test -s "$work/run/results.json" && test -s "$work/run/recording.rrd" && test -s "$work/run/report.md"
"$work/venv/bin/python" -m pushtorch.apps.collect "$work/run" > /dev/null && test -s "$work/run/collected.csv"
echo "check-install: passed ($(( $(date +%s) - start )) s for the quickstart)"
