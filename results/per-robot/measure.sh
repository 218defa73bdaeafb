#!/usr/bin/env bash
# The per-robot measurements of results/per-robot/README.md, run from the repository's root (bash
# results/per-robot/measure.sh). The runs go to runs/per-robot/ (not in git) and are made once; every robot check is
# kept in its run folder as it is made, so a second pass makes no rollout and rewrites the same files in seconds.
set -uo pipefail
mkdir -p runs/per-robot results/per-robot
out=results/per-robot

learn() {  # run folder name, then npp-learn's options; a folder that holds a run is left as it is
  local name=$1
  shift
  [ -f "runs/per-robot/$name/run.sqlite" ] || nice -n 10 .venv/bin/npp-learn "$@" --seed 0 --run-dir "runs/per-robot/$name"
}

learn pendulum-u1-s0 --task pendulum_swingup --uncertainty 1 --certify success --rule mixture
learn pendulum-u0.5-s0 --task pendulum_swingup --uncertainty 0.5 --certify success --rule mixture
learn pendulum-u0.25-s0 --task pendulum_swingup --uncertainty 0.25 --certify success --rule mixture
learn pendulum-u0.5-p0.97-s0 --task pendulum_swingup --uncertainty 0.5 --certify success --rule mixture --p 0.97 \
  --max-episodes 2000 --evaluate 0
learn cartpole-u1-s0 --task cartpole_swingup --uncertainty 1 --certify success --epsilon 130 --lipschitz 4300
learn cartpole-u0.5-s0 --task cartpole_swingup --uncertainty 0.5 --certify success --epsilon 130 --lipschitz 4300

for run in pendulum-u1-s0 pendulum-u0.5-s0 pendulum-u0.25-s0 pendulum-u0.5-p0.97-s0 cartpole-u1-s0 cartpole-u0.5-s0; do
  [ -f "runs/per-robot/$run/run.sqlite" ] || continue
  .venv/bin/npp-robots map "runs/per-robot/$run" --figure "$out/$run-map.png" --json "$out/$run-map.json" \
    > "$out/$run-map.txt"
  for pr in 0.8 0.9; do  # the same m: the claim at 0.9 takes the robot checks the claim at 0.8 made
    most=100
    # p = 0.97's policy passed 63 of its first 66 robot checks at p_r 0.8: given the checks it needs to certify
    [ "$run" = pendulum-u0.5-p0.97-s0 ] && [ "$pr" = 0.8 ] && most=300
    nice -n 10 .venv/bin/npp-robots claim "runs/per-robot/$run" --q 0.9 --p-r "$pr" --m 50 --max-checks "$most" \
      --min-checks 60 --json "$out/$run-claim-pr$pr.json" > "$out/$run-claim-pr$pr.txt"
  done
done

# Before any run: the pendulum's expert alone on 40 draws of (s0, robot) of its full set (seconds per answer).
nice -n 10 .venv/bin/npp-robots expert --task pendulum_swingup --uncertainty 1 --robots 40 \
  --figure "$out/pendulum-u1-expert-map.png" --json "$out/pendulum-u1-expert-map.json" > "$out/pendulum-u1-expert-map.txt"
