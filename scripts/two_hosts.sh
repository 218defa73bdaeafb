#!/usr/bin/env bash
# The two-host deployment, tried on one machine (as root): the expert runs on the "expert host", the sim,
# policy and supervisor on the "robot host", each a network namespace; a veth pair is the only link between
# them and neither has a route beyond it. Each host exports what a real one would: ROS_DOMAIN_ID,
# ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, ROS_STATIC_PEERS=<the other host's address> and the run's
# NPP_RUN_KEY (the same on both; a fresh one unless NPP_RUN_KEY is set).
# npp-monitor watches from the expert host; the script ends when the certificate arrives there (Ctrl-C
# ends it earlier) and then stops the nodes and deletes both namespaces. Logs go to RUN_DIR/logs.
#
#   sudo scripts/two_hosts.sh [RUN_DIR] [-p name:=value ...]   # extra parameters go to the supervisor
#
# Defaults: lqr_2_1, horizon 50 (HORIZON=...), epsilon 300 and the task's own check (rollout, sequential
# rule): a proven certificate within about a hundred episodes. A later -p wins, e.g. `-p epsilon:=50.0`.
# tests/ros/test_two_hosts.py runs the same deployment (with the paper's surrogate check) and checks it.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

PY=${PY:-.venv/bin/python}
RUN_DIR=${1:-runs/two-hosts}
shift $(($# > 0 ? 1 : 0))
HORIZON=${HORIZON:-50}
DOMAIN=${ROS_DOMAIN_ID:-0}
KEY=${NPP_RUN_KEY:-$(openssl rand -hex 32)}
TAG=npp$$ # interface names are at most 15 characters
EXPERT_NS=$TAG-expert ROBOT_NS=$TAG-robot
EXPERT_IP=10.231.0.1 ROBOT_IP=10.231.0.2

[[ $(id -u) == 0 ]] || { echo "two_hosts.sh: needs root (ip netns, ip link)" >&2; exit 2; }
[[ -x $PY ]] || { echo "two_hosts.sh: $PY is missing; run make setup first" >&2; exit 2; }
mkdir -p "$RUN_DIR/logs"

pids=()
cleanup() {
    # SIGTERM: background jobs of a script ignore SIGINT; rclpy shuts a node down cleanly on either
    for pid in "${pids[@]}"; do kill -TERM "$pid" 2>/dev/null || true; done
    for _ in $(seq 100); do # up to 10 s, then SIGKILL
        local alive=0
        for pid in "${pids[@]}"; do if kill -0 "$pid" 2>/dev/null; then alive=1; fi; done
        ((alive)) || break
        sleep 0.1
    done
    for pid in "${pids[@]}"; do kill -KILL "$pid" 2>/dev/null || true; done
    ip netns del "$EXPERT_NS" 2>/dev/null || true
    ip netns del "$ROBOT_NS" 2>/dev/null || true
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

ip netns add "$EXPERT_NS"
ip netns add "$ROBOT_NS"
ip link add "${TAG}e" netns "$EXPERT_NS" type veth peer name "${TAG}r" netns "$ROBOT_NS"
ip -n "$EXPERT_NS" addr add "$EXPERT_IP/30" dev "${TAG}e"
ip -n "$ROBOT_NS" addr add "$ROBOT_IP/30" dev "${TAG}r"
for ns_link in "$EXPERT_NS ${TAG}e" "$ROBOT_NS ${TAG}r"; do
    read -r ns link <<<"$ns_link"
    ip -n "$ns" link set lo up
    ip -n "$ns" link set "$link" up
done

# on NAMESPACE PEER_IP LOG COMMAND...: one process on one host, with that host's exports
on() {
    local ns=$1 peer=$2 log=$3
    shift 3
    ip netns exec "$ns" env ROS_DOMAIN_ID="$DOMAIN" ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST \
        ROS_STATIC_PEERS="$peer" NPP_RUN_KEY="$KEY" "$PY" "$@" >"$RUN_DIR/logs/$log.log" 2>&1 &
    pids+=($!)
}

on "$EXPERT_NS" "$ROBOT_IP" expert nodes/npp_expert.py
on "$ROBOT_NS" "$EXPERT_IP" sim nodes/npp_sim.py --ros-args -p task:=lqr_2_1 -p seed:=0 -p "horizon:=$HORIZON"
on "$ROBOT_NS" "$EXPERT_IP" policy nodes/npp_policy.py
on "$ROBOT_NS" "$EXPERT_IP" supervisor nodes/npp_supervisor.py --ros-args -p "run_dir:=$RUN_DIR" \
    -p epsilon:=300.0 -p lipschitz:=analytic "$@"
echo "two_hosts.sh: expert on $EXPERT_NS ($EXPERT_IP); sim, policy, supervisor on $ROBOT_NS ($ROBOT_IP);" \
    "ROS_DOMAIN_ID $DOMAIN; logs in $RUN_DIR/logs" >&2
ip netns exec "$EXPERT_NS" env ROS_DOMAIN_ID="$DOMAIN" ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST \
    ROS_STATIC_PEERS="$ROBOT_IP" NPP_RUN_KEY="$KEY" "$PY" nodes/npp_monitor.py --exit-on-certificate
echo "two_hosts.sh: bytes on the expert's end of the link:" >&2
ip -n "$EXPERT_NS" -s link show dev "${TAG}e" >&2
