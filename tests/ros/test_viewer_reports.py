"""A viewer shows the live run's reports as the run's, and no other's: a certificate replayed from another
run's bag under the same NPP_RUN_KEY is not shown as this run's, and a viewer without the key says of every
report that it is not verified.

A first run (npp-run --record, epsilon 300: some 80 episodes) certifies; a second run under the same exported
key (epsilon 0.001: it does not certify) runs while npp-replay plays the first run's certificate onto its
domain. Watched by npp-run's own progress, npp-monitor and npp-dashboard with the key, and by npp-monitor
without it.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from domain_coordinator import domain_id

from npp_ros.run.store import RunStore
from npp_ros_graph.transport.message_seal import KEY_ENV, RunSeal

pytestmark = pytest.mark.slow

HORIZON = 50
TIMEOUT_S = 600.0
PYTHON = sys.executable


@contextmanager
def started(command: list[str], out: Path, env: dict[str, str]) -> Iterator[subprocess.Popen[bytes]]:
    """A process in a group of its own with its output in ``out``; its group is ended at exit, whatever happened."""
    with out.open("wb") as fh:
        proc = subprocess.Popen(command, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


def wait_until(predicate: Callable[[], bool], what: str) -> None:
    """pytest.fail, not TimeoutError, on timeout: domain_id() takes an OSError for a taken domain and retries."""
    deadline = time.monotonic() + TIMEOUT_S
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {TIMEOUT_S:.0f} s waiting for {what}")
        time.sleep(0.2)


def dashboard_state(log: Path) -> dict[str, Any]:
    url = re.search(r"http://127\.0\.0\.1:\d+/", log.read_text())
    assert url is not None, log.read_text()
    with urllib.request.urlopen(url.group(0) + "state.json", timeout=30) as response:
        return dict(json.loads(response.read()))


@pytest.mark.long
def test_a_replayed_certificate_is_not_shown_as_the_live_runs(tmp_path: Path, ros_domain: int) -> None:
    keyless = {k: v for k, v in os.environ.items() if k != KEY_ENV}
    with domain_id() as domain:
        keyless["ROS_DOMAIN_ID"] = str(domain)
        keyed = {**keyless, KEY_ENV: RunSeal.new_key()}
        run = [PYTHON, "-m", "npp_ros_graph.tools.run", "--domain-id", str(domain), "--horizon", str(HORIZON)]
        first = subprocess.run([*run, "--run-dir", str(tmp_path / "first"), "--epsilon", "300", "--record"],
                               capture_output=True, text=True, timeout=TIMEOUT_S, env=keyed)  # fmt: skip
        assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
        bag = next((tmp_path / "first").glob("bag*"))
        with RunStore.open(tmp_path / "first" / "run.sqlite") as store:
            replayed_run = store.run_id[:12]

        out = {name: tmp_path / f"{name}.out" for name in ("second", "monitor", "keyless", "dashboard")}
        monitor = [PYTHON, "-m", "npp_ros_graph.tools.monitor"]
        with (
            started([PYTHON, "-m", "npp_ros_graph.tools.dashboard", "--port", "0"], out["dashboard"], keyed),
            started(monitor, out["monitor"], keyed),
            started(monitor, out["keyless"], keyless),
            started([*run, "--run-dir", str(tmp_path / "second"), "--epsilon", "0.001", "--max-episodes", "100000"],
                    out["second"], keyed) as second,
        ):  # fmt: skip
            text = {name: lambda name=name: out[name].read_text() for name in out}
            wait_until(lambda: "[gap]" in text["monitor"](), "the second run's reports in the keyed monitor")
            replay = [PYTHON, "-m", "npp_ros_graph.tools.replay", str(bag), "--topics", "npp/certificate", "--rate",
                      "0", "--linger", "inf"]  # fmt: skip
            with started(replay, tmp_path / "replay.out", keyless):  # latched while it lingers: every viewer gets it
                # The replayed certificate reached the domain's viewers, and each with the key has decided on it.
                wait_until(lambda: "[certificate]" in text["keyless"](), "the replayed certificate, keyless")
                left_out = "left out: reports of run"
                decided = {
                    "monitor": lambda: left_out in text["monitor"]() or "[certificate]" in text["monitor"](),
                    "second": lambda: left_out in text["second"]() or second.poll() is not None,
                    "dashboard": lambda: (
                        left_out in text["dashboard"]() or dashboard_state(out["dashboard"])["certificate"] is not None
                    ),
                }
                for name, done in decided.items():
                    wait_until(done, f"{name} to take the replayed certificate")
            assert second.poll() is None, text["second"]()[-2000:]  # not stopped as if certified
            state = dashboard_state(out["dashboard"])

        # With the key: this run's reports, not the replayed certificate, whose run is named as left out.
        shown = text["monitor"]()
        assert "[certificate]" not in shown and "eps 0.001" in shown and "eps 300 " not in shown, shown[-2000:]
        for name in ("monitor", "second", "dashboard"):
            assert f"left out: reports of run {replayed_run}, sealed with this run's key" in text[name]()
        assert "[certificate]" not in text["second"]()
        assert state["verified"] is True and state["certificate"] is None
        assert state["episodes"] and all(e["epsilon"] == 0.001 for e in state["episodes"])
        # Without it: every report, said to be not verified, with the run it names.
        with RunStore.open(tmp_path / "second" / "run.sqlite") as store:
            live_run = store.run_id[:12]
        before, certificate = text["keyless"]().split("[certificate]", 1)
        assert f"not verified: no run key (NPP_RUN_KEY); it names run {replayed_run}" in certificate
        unverified = f"[reports] not verified: no run key (NPP_RUN_KEY): the reports below name run {live_run};"
        assert before.index(unverified) < before.index("[gap]"), before[-2000:]
        assert f"the reports below name run {replayed_run}" in before.splitlines()[-1]
