"""npp-dashboard as a person sees it: a headless Chromium opens the page while the graph runs, waits for
the certificate and takes a screenshot; then the same run is opened from its folder and from its bag."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from browser import Browser, chromium
from graph import graph_parameters, start_graph

from npp_ros.run.store import RunStore

pytestmark = pytest.mark.skipif(
    chromium() is None and os.environ.get("CI") != "true",
    reason="chromium is not installed (scripts/setup.sh installs it where apt is available)",
)
SCREENSHOT_COPY = os.environ.get("NPP_DASHBOARD_SCREENSHOT")  # e.g. results/dashboard.png when run by hand


class Dashboard:
    """npp-dashboard as a process; `url` once it serves."""

    def __init__(self, log: Path, *args: str) -> None:
        self.log_path = log
        self.log = log.open("wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "npp_ros_graph.tools.dashboard", "--port", "0", *args],
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + 120
        self.url = ""
        while not self.url:
            text = log.read_text(errors="replace")
            self.url = next((w for w in text.split() if w.startswith("http://127.0.0.1:")), "")
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"npp-dashboard did not start:\n{text}")
            time.sleep(0.1)

    def get(self, path: str, host: str | None = None) -> tuple[int, bytes]:
        request = urllib.request.Request(self.url + path.lstrip("/"))
        if host:
            request.add_header("Host", host)
        try:
            with urllib.request.urlopen(request, timeout=30) as response:
                return response.status, response.read()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read()

    def state(self) -> dict[str, Any]:
        status, body = self.get("/state.json")
        assert status == 200
        return dict(json.loads(body))

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


@pytest.fixture
def dashboards(tmp_path: Path) -> Iterator[list[Dashboard]]:
    started: list[Dashboard] = []
    try:
        yield started
    finally:
        for dashboard in started:
            dashboard.stop()


@pytest.fixture
def browser() -> Iterator[Browser]:
    b = Browser()
    try:
        yield b
    finally:
        b.close()


@pytest.mark.long
def test_the_page_follows_a_run_to_its_certificate(launch: Any, dashboards: list[Dashboard], browser: Browser,
                                                   tmp_path: Path) -> None:  # fmt: skip
    live = Dashboard(tmp_path / "dashboard.log")
    dashboards.append(live)
    # Served on this machine only, and only to pages that name it.
    assert live.url.startswith("http://127.0.0.1:")
    assert live.get("/", host="attacker.example:80")[0] == 403
    assert live.get("/../../etc/passwd")[0] == 404
    browser.open(live.url)
    browser.wait_for("document.getElementById('status').textContent === 'live'", 120, "the page to connect")

    run_dir, bag = tmp_path / "run", tmp_path / "bag"
    record_log = (tmp_path / "record.log").open("wb")
    recorder = subprocess.Popen(
        [sys.executable, "-m", "npp_ros_graph.tools.record", "-o", str(bag)],
        stdout=record_log,
        stderr=subprocess.STDOUT,
    )
    try:
        start_graph(
            launch, graph_parameters("lqr_2_1", 0, 50, run_dir, supervisor={"epsilon": 300.0, "max_episodes": 300})
        )
        browser.wait_for("document.body.dataset.certified === 'true'", 900, "the certificate on the page")
        browser.wait_for(
            "[...document.querySelectorAll('#nodes li.alive')].length >= 5", 60, "the four nodes and the recorder"
        )
        # each graph node's newest /diagnostics status under its name
        browser.wait_for("document.querySelectorAll('#nodes li.health').length >= 4", 60, "the nodes' health")
        time.sleep(1.0)  # let the last frame paint
        shot = browser.screenshot(tmp_path / "dashboard.png")
        if SCREENSHOT_COPY:
            shutil.copy(shot, SCREENSHOT_COPY)
        text = browser.text()
        episodes_shown = int(browser.evaluate("document.body.dataset.episodes"))
        dots = int(browser.evaluate("document.querySelectorAll('#plot circle').length"))
    finally:
        recorder.send_signal(signal.SIGINT)
        recorder.wait(timeout=60)
        record_log.close()

    with RunStore.open(run_dir / "run.sqlite") as store:
        rows, certificate = store.episodes(), store.certificate()
    assert certificate is not None
    assert episodes_shown == dots == len(rows) == certificate["episodes"]
    assert certificate["statement"] in text
    assert "certified" in text and "Assumptions" in text and "delta spent" in text
    for node in ("npp_sim", "npp_expert", "npp_policy", "npp_supervisor", "npp_record"):
        assert node in text
    assert shot.stat().st_size > 20_000  # a real picture, not a blank page

    # The same run from its folder and from its bag: the same episodes and certificate.
    from_run = Dashboard(tmp_path / "dashboard-run.log", "--run", str(run_dir))
    from_bag = Dashboard(tmp_path / "dashboard-bag.log", "--bag", str(bag))
    dashboards += [from_run, from_bag]
    for dashboard in (from_run, from_bag):
        state = dashboard.state()
        assert [e["episode"] for e in state["episodes"]] == [r.episode for r in rows]
        assert [e["oracle_calls"] for e in state["episodes"]] == [r.oracle_calls for r in rows]
        assert state["certificate"]["statement"] == certificate["statement"]
        assert state["plant"] == {"task": "lqr_2_1", "seed": 0, "horizon": 50}
    browser.open(from_bag.url)
    browser.wait_for("document.body.dataset.certified === 'true'", 120, "the bag's certificate on the page")
    assert f"bag {bag.resolve()}" in browser.text()
    browser.screenshot(tmp_path / "dashboard-bag.png")


def test_npp_run_refuses_a_dashboard_port_in_use_before_starting_any_node(tmp_path: Path, ros_domain: int) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        run = subprocess.run(
            [sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(tmp_path / "run"),
             "--dashboard", str(port)],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
    assert run.returncode != 0
    assert f"port {port} on 127.0.0.1 is in use" in run.stderr
    assert not (tmp_path / "run" / "logs" / "sim.log").exists()


def test_a_folder_that_is_not_a_run_is_refused(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.dashboard", "--port", "0", "--run", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and "cannot open the run" in out.stderr
