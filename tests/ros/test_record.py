"""Record and replay: npp-record's bags hold the run as it went over the wire, survive a SIGKILL of the
recorder, and read back with rosbags and with the mcap package; npp-monitor --bag and npp-replay show them."""

from __future__ import annotations

import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from npp_interfaces.msg import Certificate, GapReport
from rclpy.serialization import serialize_message
from ruamel.yaml import YAML

from npp_ros.run.records import EpisodeRow
from npp_ros.run.store import RunStore
from npp_ros_graph.tools.bag import BagError, BagWriter, is_complete, open_reader, qos_entry, read_messages, repair
from npp_ros_graph.transport.topics import CERTIFICATE, GAP, LATCHED_QOS, REPORT_HISTORY_QOS

# A short run that certifies: horizon 50, epsilon 300 (lqr_2_1, analytic L): about 80 episodes.
# p 0.8 and delta 0.2: a certificate in 54 episodes instead of 83 (what is recorded is tested, not the claim)
RUN_ARGS = ["--horizon", "50", "--epsilon", "300", "--max-episodes", "300", "--p", "0.8", "--delta", "0.2"]
GAP_TYPE = "npp_interfaces/msg/GapReport"


def metadata(bag: Path) -> dict[str, Any]:
    return YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def metadata_counts(bag: Path) -> dict[str, int]:
    info = metadata(bag)
    return {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}


def same(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


def gap_matches_row(msg: Any, row: EpisodeRow) -> bool:
    """A recorded GapReport says what the run file says about its episode, number for number."""
    return (
        msg.episode == row.episode
        and tuple(float(x) for x in msg.initial_state) == row.initial_state
        and all(same(a, b) for a, b in ((msg.v_lb, row.v_lb), (msg.v_ub, row.v_ub), (msg.gap, row.gap)))
        and same(msg.checked_gap, row.checked_gap)
        and msg.oracle_called == row.oracle_called
        and (msg.dataset_size, msg.oracle_calls, msg.quiet_episodes, msg.quiet_required, msg.test)
        == (row.dataset_size, row.oracle_calls, row.quiet_episodes, row.required, row.test)
        and msg.test_delta == row.test_delta
    )


def mcap_count(bag: Path) -> tuple[int, set[str]]:
    """Messages and schema encodings as the mcap package's own reader sees them."""
    (path,) = bag.glob("*.mcap")
    with path.open("rb") as fh:
        reader = make_reader(fh)
        count, encodings = 0, set()
        for schema, channel, _message in reader.iter_messages():
            count += 1
            assert schema is not None and schema.data, f"channel {channel.topic} carries no message definition"
            encodings.add(schema.encoding)
    return count, encodings


# ----------------------------------------------------------------------------- the bag file alone
WRITER = """
import os, sys, time
from pathlib import Path
from npp_ros_graph.tools.bag import BagWriter, qos_entry, typestore
store = typestore()
Gap = store.types["npp_interfaces/msg/GapReport"]
Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
import numpy as np
bag = BagWriter(Path(sys.argv[1]))
qos = [qos_entry(reliable=True, transient_local=False, depth=100)]
topic = bag.add_topic("/npp/gap", "npp_interfaces/msg/GapReport", qos)
def gap(k):
    return Gap(Header(Time(0, 0), ""), k, np.array([0.5, -1.0]), -2.0, 3.0, 5.0, 50.0, k % 2 == 0, 10 * k, k, 0, 30,
               "i", "rollout", 1.0 / (k + 1), 1, 0.05)
for k in range({flushed}):
    bag.write(topic, store.serialize_cdr(gap(k), "npp_interfaces/msg/GapReport"), 1_000_000 + k)
    if k % 7 == 6:
        bag.flush()
bag.flush()
for k in range({flushed}, {flushed} + 5):
    bag.write(topic, store.serialize_cdr(gap(k), "npp_interfaces/msg/GapReport"), 1_000_000 + k)
os.kill(os.getpid(), 9)
"""


def last_chunk_middle(data: bytes) -> int:
    """An offset inside the file's last chunk record: where a write torn by a kill could end."""
    pos, middle = 8, 0
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        if opcode == 0x06:
            middle = pos + 9 + length // 2
        pos += 9 + length
    assert middle, "no chunk in the file"
    return middle


def test_a_killed_writer_leaves_every_flushed_message_readable(tmp_path: Path) -> None:
    bag = tmp_path / "killed"
    proc = subprocess.run([sys.executable, "-c", WRITER.replace("{flushed}", "40"), str(bag)], timeout=120)
    assert proc.returncode == -signal.SIGKILL
    assert is_complete(next(bag.glob("*.mcap")))
    episodes = [m.msg.episode for m in read_messages(bag)]
    assert episodes == list(range(40))  # every flushed message, none of the 5 written after the last flush
    assert metadata_counts(bag) == {"/npp/gap": 40}
    assert mcap_count(bag) == (40, {"ros2msg"})

    # A kill inside a flush's own write tears the file's end: reading refuses and says how to repair.
    torn = tmp_path / "torn"
    shutil.copytree(bag, torn)
    (path,) = torn.glob("*.mcap")
    data = path.read_bytes()
    path.write_bytes(data[: last_chunk_middle(data)])
    with pytest.raises(BagError, match="npp-record --repair"):
        open_reader(torn)
    out = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.record", "--repair", str(torn)], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    kept = [m.msg.episode for m in read_messages(torn)]
    assert kept == list(range(35))  # the chunks of the flushes before the torn one (7 messages each)
    assert metadata_counts(torn) == {"/npp/gap": len(kept)}


def test_a_closed_bag_has_its_summary_and_refuses_to_be_overwritten(tmp_path: Path) -> None:
    bag = BagWriter(tmp_path / "closed")
    latched = bag.add_topic("/npp/certificate", "npp_interfaces/msg/Certificate", [qos_entry(
        reliable=True, transient_local=True, depth=1)])  # fmt: skip
    bag.write(latched, serialize_message(Certificate(statement="P(gap <= 300) >= 0.9", assumptions=["a", "b"])), 7)
    bag.close()
    (path,) = (tmp_path / "closed").glob("*.mcap")
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics is not None and summary.statistics.message_count == 1
    (msg,) = read_messages(tmp_path / "closed")
    assert msg.msg.statement == "P(gap <= 300) >= 0.9" and list(msg.msg.assumptions) == ["a", "b"]
    assert msg.qos[0].durability.name == "TRANSIENT_LOCAL"
    with pytest.raises(BagError, match="not empty"):
        BagWriter(tmp_path / "closed")
    assert "nothing to repair" in repair(tmp_path / "closed")


# ----------------------------------------------------------------------------- a recorded graph run
@pytest.fixture(scope="module")
def recorded_run(ros_domain: int, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """npp-run --record --dashboard: the four nodes, the recorder and the dashboard, to a certificate."""
    run_dir = tmp_path_factory.mktemp("recorded") / "run"
    command = [sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(run_dir), "--record"]
    run = subprocess.run([*command, "--dashboard", "0", *RUN_ARGS], capture_output=True, text=True, timeout=1200)
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in sorted((run_dir / "logs").glob("*.log")))
    assert run.returncode == 0, f"{run.stderr[-3000:]}\n{logs}"
    assert "[certificate]" in run.stdout and "recording into" in run.stderr
    assert "dashboard at http://127.0.0.1:" in run.stderr  # npp-run --dashboard 0: any free port, named
    return run_dir


@pytest.mark.long
def test_the_bag_holds_every_gap_report_as_the_run_file_stores_it(recorded_run: Path) -> None:
    bag = recorded_run / "bag"
    counts: Counter[str] = Counter()
    gaps, certificates = [], []
    for message in read_messages(bag):
        counts[message.topic] += 1
        if message.topic == "/npp/gap":
            gaps.append(message.msg)
        elif message.topic == "/npp/certificate":
            certificates.append(message.msg)
    with RunStore.open(recorded_run / "run.sqlite") as store:
        rows = store.episodes()
        certificate = store.certificate()
    assert certificate is not None and len(rows) == certificate["episodes"]
    assert len(gaps) == len(rows)
    mismatched = [row.episode for msg, row in zip(gaps, rows, strict=True) if not gap_matches_row(msg, row)]
    assert not mismatched, f"episodes whose GapReport differs from the run file: {mismatched[:10]}"
    assert len(certificates) == 1 and certificates[0].statement == certificate["statement"]
    assert certificates[0].episodes == len(rows)
    # Every topic of the graph was recorded, the control loop included, with the QoS its publisher offers.
    for topic in ("/npp/state", "/npp/action", "/npp/episode", "/npp/sim/plant", "/npp/dataset/trajectory"):
        assert counts[topic] > 0, f"nothing recorded on {topic}: {counts}"
    assert counts["/npp/episode"] == len(rows)
    info = metadata(bag)
    qos = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"][0]["durability"]
           for t in info["topics_with_message_count"]}  # fmt: skip
    assert qos["/npp/certificate"] == qos["/npp/sim/plant"] == qos["/npp/gap"] == "transient_local"
    assert info["storage_identifier"] == "mcap" and info["message_count"] == sum(counts.values())
    assert {topic: n for topic, n in metadata_counts(bag).items() if n} == dict(counts)
    assert mcap_count(bag) == (sum(counts.values()), {"ros2msg"})  # any MCAP reader: the mcap package's own


def test_monitor_prints_the_bag_as_it_printed_the_live_run(recorded_run: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.monitor", "--bag", str(recorded_run / "bag")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    with RunStore.open(recorded_run / "run.sqlite") as store:
        rows = store.episodes()
    gap_lines = [line for line in out.stdout.splitlines() if line.startswith("[gap]")]
    assert [int(line.split()[2]) for line in gap_lines] == [row.episode + 1 for row in rows]  # counted from 1
    assert sum(line.startswith("[episode]") for line in out.stdout.splitlines()) == len(rows)
    assert "[certificate] condition (i), epsilon 300" in out.stdout
    closing = [line.strip() for line in out.stdout.rstrip().splitlines()][-8:]
    assert any(line.startswith("With probability") for line in closing)  # the statement, then what it assumes
    assert closing[-1].startswith("assumes:")

    refused = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.monitor", "--bag", str(recorded_run)],
        capture_output=True,
        text=True,
    )
    assert refused.returncode == 2 and "is not a bag folder" in refused.stderr


def test_replay_shows_the_recorded_run_to_a_live_monitor(recorded_run: Path) -> None:
    bag = recorded_run / "bag"
    recorded = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.monitor", "--bag", str(bag)],
        capture_output=True,
        text=True,
        timeout=300,
    ).stdout.splitlines()
    monitor = subprocess.Popen(
        [sys.executable, "-m", "npp_ros_graph.tools.monitor"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        replay = subprocess.run(
            [sys.executable, "-m", "npp_ros_graph.tools.replay", str(bag), "--rate", "20",
             "--wait-for", "npp/gap", "--wait-for", "npp/episode", "--wait-for", "npp/certificate"],
            capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert replay.returncode == 0, replay.stderr
        assert "published" in replay.stderr
        time.sleep(3.0)  # the monitor prints what is still in flight
    finally:
        monitor.send_signal(signal.SIGINT)
        live, err = monitor.communicate(timeout=60)
    live_lines = live.splitlines()
    for kind in ("[gap]", "[episode]"):  # each topic in order (the two topics may interleave differently)
        assert [x for x in live_lines if x.startswith(kind)] == [x for x in recorded if x.startswith(kind)], err
    assert any(line.startswith("[certificate]") for line in live_lines)


# ----------------------------------------------------------------------------- SIGKILL of the recorder
def wait_until(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.1)


def test_a_sigkilled_recorder_leaves_every_flushed_message(ros_client: Any, tmp_path: Path) -> None:
    """A publisher in the test: a latched certificate from before the recorder started, then a stream of
    GapReports; the recorder is SIGKILLed mid-stream and its bag holds everything of its last flush."""
    client = ros_client("kill_test", namespace="/killed")
    latched = client.node.create_publisher(Certificate, CERTIFICATE, LATCHED_QOS)
    gaps = client.node.create_publisher(GapReport, GAP, REPORT_HISTORY_QOS)  # as the supervisor publishes them
    latched.publish(Certificate(statement="latched before the recorder started"))
    bag = tmp_path / "bag"
    log = (tmp_path / "record.log").open("wb")
    recorder = subprocess.Popen(
        [sys.executable, "-m", "npp_ros_graph.tools.record", "-o", str(bag), "--flush-every", "0.2",
         "--ros-args", "-r", "__ns:=/killed"],
        stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ),
    )  # fmt: skip
    try:
        client.wait_for(lambda: gaps.get_subscription_count() > 0, 120, "the recorder's subscription")
        published = 0
        counts: dict[str, int] = {}

        def publish_until(n: int) -> None:
            nonlocal published
            while published < n:
                gaps.publish(GapReport(episode=published, gap=float(published), checked_gap=0.5 * published))
                published += 1
                time.sleep(0.005)

        publish_until(50)
        # Wait until a flush holds all 50, then publish more and kill right away: the last ones are in flight.
        wait_until(lambda: metadata_counts(bag).get("/killed/npp/gap", 0) >= 50, 120, "a flush of 50 messages")
        publish_until(80)
        counts = metadata_counts(bag)
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(timeout=60)
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.wait()
        log.close()
    assert recorder.returncode == -signal.SIGKILL
    final = metadata_counts(bag)  # what the last completed flush counted before the kill
    assert final["/killed/npp/gap"] >= counts["/killed/npp/gap"] >= 50
    messages = list(read_messages(bag))
    recorded_gaps = [m.msg.episode for m in messages if m.topic == "/killed/npp/gap"]
    # A flush commits the file, then metadata.yaml: a kill between the two leaves the file one flush ahead
    # of the counts, never behind. Every counted message is readable, in order, none missing, none torn.
    assert recorded_gaps == list(range(len(recorded_gaps)))
    assert len(recorded_gaps) >= final["/killed/npp/gap"]
    assert [m.msg.statement for m in messages if m.topic == "/killed/npp/certificate"] == [
        "latched before the recorder started"
    ]
    readable = Counter(m.topic for m in messages)
    assert all(readable[topic] >= count for topic, count in final.items()), (readable, final)
    assert mcap_count(bag)[0] == len(messages)
