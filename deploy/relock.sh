#!/usr/bin/env bash
# Re-resolve deploy/constraints.txt to the newest versions pyproject.toml's ranges allow, then run the
# README's test command against them. The lock is rewritten only when the suite passes.
#   bash deploy/relock.sh            # re-resolve, test, write the lock
#   bash deploy/relock.sh -m 'not slow'   # extra pytest arguments (a quicker check; CI runs everything)
set -euo pipefail
cd "$(dirname "$0")/.."
venv="$(mktemp -d)/venv"
echo "== fresh venv $venv, newest allowed versions (no constraints)"
python3 -m venv "$venv"
"$venv/bin/python" -m pip install -q -e '.[test,mf4]'
echo "== the suite against them"
"$venv/bin/python" -m pytest "$@"
{
  echo "# The locked versions CI passed with (pip constraints: install with 'pip install -c deploy/constraints.txt ...')."
  echo "# Made by deploy/relock.sh from pyproject.toml's ranges on Python 3.11; do not edit by hand."
  "$venv/bin/python" -m pip freeze --exclude-editable | grep -v '^-e'
} >deploy/constraints.txt
echo "== deploy/constraints.txt rewritten; review with: git diff deploy/constraints.txt"
