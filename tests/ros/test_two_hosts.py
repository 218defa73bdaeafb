"""The graph across two hosts: the expert on one, the sim, policy and supervisor on the other.

Two network namespaces joined by a veth pair stand for the two machines. Each has its own interfaces
(lo and its end of the link), addresses and routes (the link's /30, no default route), and the expert's
host has its own /dev/shm, so Fast DDS cannot take a shared-memory shortcut between the hosts: whatever
the expert and the rest of the graph exchange crosses the link as UDP, as between two machines. Each host
runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and ROS_STATIC_PEERS=<the other host's address>, and
both export the run's NPP_RUN_KEY.

Needs root, `ip netns`, unshare and nsenter; skipped with the reason otherwise.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import pytest
from reference import ROLLOUT_FREE, decisions, uninterrupted_run

from npp_ros.run.store import RunStore
from npp_ros_graph.tools.run import child_setup
from npp_ros_graph.transport.message_seal import KEY_ENV, RunSeal

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
PYTHON = os.path.realpath(sys.executable)
SUBNET = "10.231.0"  # exists only inside the two namespaces: parallel sessions cannot clash on it
HORIZON = 50
EPSILON = 50.0
MAX_EPISODES = 400
START_TIMEOUT_S = 120.0
CERTIFICATE_TIMEOUT_S = 1800.0  # about a minute on an idle machine; generous for a shared one
STOP_TIMEOUT_S = 10.0
LOG_TAIL_LINES = 40
# The expert host's processes get a /dev/shm of their own: two machines share no memory.
OWN_SHM = ["unshare", "--mount", "sh", "-c", 'mount -t tmpfs tmpfs /dev/shm && exec "$@"', "sh"]


@dataclass(frozen=True)
class Host:
    """One side of the link: a network namespace, its end of the veth pair and its address."""

    netns: str
    link: str
    address: str

    def ip(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["ip", "-n", self.netns, *args], capture_output=True, text=True, check=check)

    def ip_json(self, *args: str) -> Any:
        return json.loads(self.ip("-j", *args).stdout or "[]")

    def link_bytes(self) -> tuple[int, int]:
        """(received, sent) bytes on this host's end of the link."""
        stats = self.ip_json("-s", "link", "show", "dev", self.link)[0]["stats64"]
        return int(stats["rx"]["bytes"]), int(stats["tx"]["bytes"])

    def netns_inode(self) -> int:
        return os.stat(f"/run/netns/{self.netns}").st_ino


@dataclass
class TwoHosts:
    """The expert's host, the robot's host, and the node processes started on them."""

    expert: Host
    robot: Host
    log_dir: Path
    procs: dict[str, tuple[subprocess.Popen[bytes], Path, IO[bytes]]] = field(default_factory=dict)

    def start(self, label: str, prefix: list[str], argv: list[str], env: dict[str, str]) -> subprocess.Popen[bytes]:
        """Run `python argv` behind `prefix`; returns once the process is Python (the namespaces are entered)."""
        log = self.log_dir / f"{label}.log"
        fh = open(log, "wb")  # closed in stop_all
        proc = subprocess.Popen(
            [*prefix, sys.executable, *argv],
            stdout=fh,
            stderr=subprocess.STDOUT,
            cwd=REPO,
            env=env,
            preexec_fn=child_setup(os.getpid()),  # SIGINT restored; SIGTERM if this test process dies
        )
        self.procs[label] = (proc, log, fh)
        # ip netns exec, unshare, sh and nsenter each exec the next: the pid becomes the node's own.
        deadline = time.monotonic() + START_TIMEOUT_S
        while _exe(proc.pid) != PYTHON:
            self.assert_alive()
            assert time.monotonic() < deadline, f"{label} never became a Python process"
            time.sleep(0.05)
        return proc

    def log(self, label: str) -> str:
        return self.procs[label][1].read_text(errors="replace")

    def assert_alive(self, *but: str) -> None:
        for label, (proc, _, _) in self.procs.items():
            if proc.poll() is not None and label not in but:
                pytest.fail(f"{label} exited with {proc.returncode}:\n{self._tail(label)}")

    def stop_all(self, show_logs: bool) -> None:
        for proc, _, _ in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)  # all at once: they shut down in parallel
        for label, (proc, log, fh) in self.procs.items():
            try:
                proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(STOP_TIMEOUT_S)
            fh.close()
            if show_logs:
                print(f"\n----- {label} (exit {proc.returncode}), log {log}\n{self._tail(label)}")

    def _tail(self, label: str) -> str:
        return "\n".join(self.log(label).splitlines()[-LOG_TAIL_LINES:])


def _exe(pid: int) -> str:
    try:
        return os.readlink(f"/proc/{pid}/exe")
    except OSError:
        return ""


def _cannot_make_namespaces() -> str | None:
    if os.geteuid() != 0:
        return "needs root: it creates network namespaces and a veth pair (ip netns, ip link)"
    for tool in ("ip", "unshare", "nsenter", "mount"):
        if shutil.which(tool) is None:
            return f"needs the {tool!r} command (iproute2, util-linux)"
    return None


def _run(*cmd: str) -> None:
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {done.stderr.strip()}")


def _failed(item: pytest.Item) -> bool:
    return any(getattr(getattr(item, f"rep_{when}", None), "failed", False) for when in ("setup", "call"))


@pytest.fixture
def two_hosts(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[TwoHosts]:
    """Two namespaces joined by one veth pair; at teardown every process is stopped, then both are deleted."""
    reason = _cannot_make_namespaces()
    if reason is not None:
        pytest.skip(reason)
    tag = f"npp{os.getpid()}"  # unique on this machine while this session runs; interface names <= 15 chars
    hosts = TwoHosts(Host(f"{tag}-expert", f"{tag}e", f"{SUBNET}.1"), Host(f"{tag}-robot", f"{tag}r", f"{SUBNET}.2"),
                     tmp_path)  # fmt: skip
    try:
        try:
            _run("ip", "netns", "add", hosts.expert.netns)
        except RuntimeError as exc:
            pytest.skip(f"cannot create a network namespace here: {exc}")
        _run("ip", "netns", "add", hosts.robot.netns)
        _run("ip", "link", "add", hosts.expert.link, "netns", hosts.expert.netns, "type", "veth",
             "peer", "name", hosts.robot.link, "netns", hosts.robot.netns)  # fmt: skip
        for host in (hosts.expert, hosts.robot):
            host.ip("addr", "add", f"{host.address}/30", "dev", host.link)
            host.ip("link", "set", "lo", "up")
            host.ip("link", "set", host.link, "up")
        yield hosts
    finally:
        hosts.stop_all(show_logs=_failed(request.node))
        for host in (hosts.expert, hosts.robot):
            subprocess.run(["ip", "netns", "del", host.netns], capture_output=True)  # takes its veth end along
        subprocess.run(["ip", "link", "del", hosts.expert.link], capture_output=True)  # had it stayed outside


def assert_only_the_link(host: Host, peer: Host) -> None:
    """The namespace reaches nothing but its peer: lo and one veth end, the link's /30, no default route."""
    links = {link["ifname"]: link for link in host.ip_json("link", "show")}
    assert set(links) == {"lo", host.link}, f"{host.netns} has interfaces {sorted(links)}"
    assert "link_netnsid" in links[host.link], "the veth's other end must be in the other namespace"
    main = [(route["dst"], route.get("dev")) for route in host.ip_json("-4", "route", "show")]
    assert main == [(f"{SUBNET}.0/30", host.link)], f"{host.netns} routes: {main}"
    for family in ("-4", "-6"):
        every = host.ip_json(family, "route", "show", "table", "all")
        assert not [r for r in every if r["dst"] == "default"], f"{host.netns} has a default route: {every}"
    outside = host.ip("route", "get", "192.0.2.1", check=False)  # TEST-NET-1: any address beyond the link
    assert outside.returncode != 0 and "unreachable" in outside.stderr, outside
    assert host.ip("route", "get", peer.address).returncode == 0


def environ_of(pid: int) -> dict[str, str]:
    raw = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(item.decode(errors="replace").split("=", 1) for item in raw if b"=" in item)


def ros_args(**params: str) -> list[str]:
    return ["--ros-args", *[arg for name, value in params.items() for arg in ("-p", f"{name}:={value}")]]


@pytest.mark.long
def test_expert_on_another_host_serves_the_run_to_its_certificate(
    two_hosts: TwoHosts, ros_domain: int, tmp_path: Path
) -> None:
    hosts = two_hosts
    assert_only_the_link(hosts.expert, hosts.robot)
    assert_only_the_link(hosts.robot, hosts.expert)

    run_key = RunSeal.new_key()

    def exports(peer: Host) -> dict[str, str]:
        """What a user exports on each host: the domain, this machine plus the other host, the run's key."""
        return {
            **os.environ,
            "ROS_DOMAIN_ID": str(ros_domain),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "ROS_STATIC_PEERS": peer.address,
            KEY_ENV: run_key,
        }

    on_expert_host = ["ip", "netns", "exec", hosts.expert.netns, *OWN_SHM]
    on_robot_host = ["ip", "netns", "exec", hosts.robot.netns]
    run_dir = tmp_path / "run"
    started = time.monotonic()
    expert = hosts.start("expert", on_expert_host, ["nodes/npp_expert.py"], exports(hosts.robot))
    # The operator watches from the expert's host: a second process there, in the expert's namespaces.
    join_expert = ["nsenter", f"--target={expert.pid}", "--net", "--mount", f"--wd={REPO}"]
    watch = ["nodes/npp_monitor.py", "--exit-on-certificate"]
    monitor = hosts.start("monitor", join_expert, watch, exports(hosts.robot))
    sim_args = ros_args(task="lqr_2_1", seed="0", horizon=str(HORIZON))
    sim = hosts.start("sim", on_robot_host, ["nodes/npp_sim.py", *sim_args], exports(hosts.expert))
    policy = hosts.start("policy", on_robot_host, ["nodes/npp_policy.py"], exports(hosts.expert))
    supervisor_args = ros_args(
        run_dir=str(run_dir), epsilon=repr(EPSILON), lipschitz="analytic", max_episodes=str(MAX_EPISODES),
        **ROLLOUT_FREE,
    )  # fmt: skip
    supervisor = hosts.start("supervisor", on_robot_host, ["nodes/npp_supervisor.py", *supervisor_args],
                             exports(hosts.expert))  # fmt: skip

    # Every process runs on the host the deployment puts it on, with what that host exports.
    expert_net, robot_net = hosts.expert.netns_inode(), hosts.robot.netns_inode()
    assert len({expert_net, robot_net, os.stat("/proc/self/ns/net").st_ino}) == 3
    placed = [(expert, expert_net, hosts.robot), (monitor, expert_net, hosts.robot)]
    placed += [(proc, robot_net, hosts.expert) for proc in (sim, policy, supervisor)]
    for proc, netns, peer in placed:
        assert os.stat(f"/proc/{proc.pid}/ns/net").st_ino == netns
        env = environ_of(proc.pid)
        got = (env["ROS_DOMAIN_ID"], env["ROS_AUTOMATIC_DISCOVERY_RANGE"], env["ROS_STATIC_PEERS"], env[KEY_ENV])
        assert got == (str(ros_domain), "LOCALHOST", peer.address, run_key)
    assert os.stat(f"/proc/{monitor.pid}/ns/mnt").st_ino == os.stat(f"/proc/{expert.pid}/ns/mnt").st_ino

    deadline = time.monotonic() + CERTIFICATE_TIMEOUT_S
    while monitor.poll() is None:  # it exits once the run's sealed certificate has reached the expert's host
        hosts.assert_alive()
        assert time.monotonic() < deadline, f"no certificate on the expert's host within {CERTIFICATE_TIMEOUT_S:.0f} s"
        time.sleep(1.0)
    elapsed = time.monotonic() - started
    hosts.assert_alive("monitor")
    received, sent = hosts.expert.link_bytes()
    watched = hosts.log("monitor")
    assert monitor.returncode == 0, watched[-3000:]
    assert "[certificate] condition (i), epsilon 50" in watched and "ORACLE" in watched, watched[-3000:]
    modelling = f"modelling lqr_2_1 seed 0 (state_dim 4, action_dim 1, default horizon {HORIZON}"
    assert modelling in hosts.log("expert")  # the sim's plant description crossed the link

    with RunStore.open(run_dir / "run.sqlite") as store:
        certificate = store.certificate()
        rows = store.episodes()
        data = store.load_dataset()
    assert certificate is not None and certificate["oracle_calls"] > 0
    assert certificate["oracle_calls"] == data.num_trajectories == sum(r.oracle_called for r in rows)
    # Every trajectory came from the expert over the link: its end sent at least their bytes.
    payload = data.states.nbytes + data.actions.nbytes + data.values.nbytes
    assert sent >= payload and received > 0, (sent, received, payload)
    # Two hosts change nothing Algorithm 1 decides: the same run as in one process.
    _, local = uninterrupted_run(epsilon=EPSILON, horizon=HORIZON, max_episodes=MAX_EPISODES, **ROLLOUT_FREE)
    assert decisions(rows) == decisions(local.rows)
    assert local.certificate is not None and certificate["episodes"] == local.certificate.episodes
    print(
        f"\ntwo hosts: certificate after {certificate['episodes']} episodes and {certificate['oracle_calls']} oracle "
        f"calls, {elapsed:.0f} s from the expert's start to the certificate on its host; the expert's end of the "
        f"link sent {sent:,} bytes (the trajectories: {payload:,}) and received {received:,}"
    )
