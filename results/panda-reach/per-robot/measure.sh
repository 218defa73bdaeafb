#!/usr/bin/env bash
# The Panda's per-robot measurements (results/panda-reach/per-robot/README.md), run from the repository's root:
# bash results/panda-reach/per-robot/measure.sh. The run goes to runs/panda/payload-s0 (not in git) and is made
# once; every robot check is kept in the run folder as it is made, so a second pass makes no rollout.
set -uo pipefail
run=runs/panda/payload-s0
out=results/panda-reach/per-robot
mkdir -p "$out"
[ -f "$run/run.sqlite" ] || .venv/bin/npp-learn --task examples/panda_reach/task.toml --seed 0 --certify success \
  --rule mixture --uncertainty 1 --evaluate 0 --run-dir "$run"
.venv/bin/npp-robots map "$run" --figure "$out/payload-s0-map.png" --json "$out/payload-s0-map.json" \
  > "$out/payload-s0-map.txt"
claim() {  # p_r, m, most robot checks; the files named by p_r (and m where it is not 50)
  local name="payload-s0-claim-pr$1"
  [ "$2" = 50 ] || name="$name-m$2"
  .venv/bin/npp-robots claim "$run" --q 0.9 --p-r "$1" --m "$2" --max-checks "$3" --min-checks 60 \
    --json "$out/$name.json" > "$out/$name.txt"  # exits 1 when the claim is not made
}
claim 0.8 50 100
claim 0.9 50 100
claim 0.8 100 200
# The JSON records name the task by its identity as the run stored it (its path and hash): the path shortened to
# the repository's own.
sed -i "s#$(pwd)/##g" "$out"/*.txt "$out"/*.json
