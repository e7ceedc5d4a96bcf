#!/usr/bin/env bash
# Mutation testing of CoWorld's core (issue 52; docs/testing.md): mutmut mutates coworld/losses/coworld.py,
# coworld/agents/coworld.py and coworld/losses/dreamer.py and runs, for each mutant, the fast tests that reach the
# mutated function. Run it after scripts/install.sh; it takes about 10 minutes on two busy CPU cores.
#
#   bash scripts/mutation.sh            # run, in a fresh copy of the checkout
#   bash scripts/mutation.sh results    # list the mutants that survived
#   bash scripts/mutation.sh show NAME  # show one mutant's diff
#
# It works in a copy of the tree, .mutation/tree, so the checkout is never mutated. Where the venv has no mutmut, it is
# installed into .mutation/site (never into the venv) and appended to the path, so the venv's own pytest and plugins
# are the ones that run. Environment: PYTHON (default .venv/bin/python),
# MUTATION_JOBS (parallel mutants, default 1), MUTATION_RESUME=1 (go on with the last copy, skipping judged mutants),
# MUTATION_ALL=1 (train_coworld's loop too, see below).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
py=${PYTHON:-$root/.venv/bin/python}
work=$root/.mutation
tree=$work/tree
site=$work/site
MUTATE=(coworld/losses/coworld.py coworld/agents/coworld.py coworld/losses/dreamer.py)
TESTS=(
  tests/losses/test_coworld_losses.py
  tests/losses/test_dreamer_loss_contracts.py
  tests/models/test_dreamer_losses.py
  tests/agents/test_coworld_wiring.py
  tests/agents/test_coworld_schedule.py
)

if ! "$py" -c "import mutmut" 2>/dev/null && ! PYTHONPATH=$site "$py" -c "import mutmut" 2>/dev/null; then
  echo "mutation: installing mutmut into $site"
  "$py" -m pip install -q --disable-pip-version-check --target "$site" "mutmut==3.8.1" 2>&1 | grep -v "^WARNING: Location" || true
fi
mutmut=("$py" -c "import sys; sys.path.append('$site'); from mutmut.__main__ import cli; sys.argv[0] = 'mutmut'; cli()")

# a run starts from a fresh copy of the checkout (MUTATION_RESUME=1 keeps the last copy and its results); results
# and show read the last run's copy
if [ "${1:-run}" = run ] && [ "${MUTATION_RESUME:-0}" != 1 ]; then rm -rf "$tree"; fi
if [ ! -d "$tree" ]; then
  mkdir -p "$tree"
  cp -r coworld tests pyproject.toml "$tree"/
  find "$tree" -name __pycache__ -prune -exec rm -rf {} +
  # mutmut's config: the whole package is copied, the three files alone are mutated
  {
    echo "[mutmut]"
    echo "source_paths = coworld/"
    echo "only_mutate ="
    for file in "${MUTATE[@]}"; do echo "    $file"; done
    echo "pytest_add_cli_args_test_selection ="
    for test in "${TESTS[@]}"; do echo "    $test"; done
  } >"$tree/setup.cfg"
fi
cd "$tree"
# the mutated copy, not the checkout the venv's editable install points at, is what the tests import
export MUJOCO_GL=${MUJOCO_GL:-egl} OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
unset PYTHONPATH
# The mutants of the update steps and the loss functions; train_coworld's loop (about 385 mutants, each needing whole
# toy runs of 2-10 s) only with MUTATION_ALL=1: tests/agents/test_coworld_wiring.py's schedule tests pin it instead.
SELECTION=("coworld.losses.*" "coworld.agents.coworld.xǁ*")
[ "${MUTATION_ALL:-0}" = 1 ] && SELECTION=()
case "${1:-run}" in
  run) nice -n 19 "${mutmut[@]}" run --max-children "${MUTATION_JOBS:-1}" "${SELECTION[@]}" ;;
  *) "${mutmut[@]}" "$@" ;;
esac
