"""A run that can no longer certify within --max-episodes says so, and may stop there.

``CertificationStatus.episodes_to_certify`` is a lower bound on the episodes a certificate still needs:
fed real check sequences, no rule ever certifies sooner than it said; under the streak rule the bound is
met exactly when every further check passes.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from npp_ros.certificate.certifier import CertificationSpec
from npp_ros.certificate.mixture import certifier_for
from npp_ros.policy.lipschitz import LipschitzConstant

LEARN = [sys.executable, "-m", "npp_ros.cli.learn"]


def spec(rule: str) -> CertificationSpec:
    return CertificationSpec("i", 1.0, 0.9, 0.1, LipschitzConstant(1.0, "user"), rule=rule)  # type: ignore[arg-type]


@pytest.mark.parametrize("rule", ["sequential", "paper", "mixture"])
@pytest.mark.parametrize("q", [0.9, 0.97])
def test_no_rule_certifies_sooner_than_its_bound(rule: str, q: float) -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        certifier = certifier_for(spec(rule))
        bounds = [certifier.status().episodes_to_certify]
        for episode in range(1, 600):
            passed = episode > 1 and rng.random() < q  # the first episode has no policy
            status = certifier.observe(0.0 if passed else math.inf, failed=not passed)
            if status.certified:
                assert all(b is not None and episode - i >= b for i, b in enumerate(bounds)), (episode, bounds)
                assert status.episodes_to_certify == 0 and status.reachable_within(0)
                break
            bounds.append(status.episodes_to_certify)


def test_the_streak_bound_is_met_when_every_further_check_passes() -> None:
    certifier = certifier_for(spec("sequential"))
    assert certifier.status().episodes_to_certify == 31  # the first episode fails, then test 1's 30 passes
    for _ in range(3):
        certifier.observe(math.inf, failed=True)
    status = certifier.observe(0.0, failed=False)
    assert (status.test, status.required, status.episodes_to_certify) == (3, 48, 47)
    assert status.reachable_within(47) and not status.reachable_within(46)
    for left in range(46, 0, -1):
        assert certifier.observe(0.0, failed=False).episodes_to_certify == left
    assert certifier.observe(0.0, failed=False).certified


def test_condition_ii_does_not_tell() -> None:
    ii = CertificationSpec("ii", 1.0, 0.9, 0.1, LipschitzConstant(1.0, "user"), diameter=1.0, certify="surrogate")
    status = certifier_for(ii).observe(0.5, failed=False)
    assert status.episodes_to_certify is None and status.reachable_within(0) is None


def test_npp_learn_says_once_and_may_stop_there(tmp_path: Path) -> None:
    base = [*LEARN, "--horizon", "50", "--evaluate", "0"]
    said = "the certificate can no longer be reached within"
    run = subprocess.run(
        [*base, "--max-episodes", "4", "--run-dir", str(tmp_path / "a")], capture_output=True, text=True
    )
    assert run.returncode == 1, run.stderr
    assert run.stderr.count(said) == 1  # once, after the first episode (test 1 needs 30 passes)
    assert "after episode 1 it needs at least 30 more episodes (test 1 streak 0/30), and 3 are left" in run.stderr
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert (summary["episodes"], summary["ended"]) == (4, "max-episodes")
    stop = [*base, "--max-episodes", "40", "--stop-when-unreachable", "--run-dir", str(tmp_path / "b")]
    run = subprocess.run(stop, capture_output=True, text=True)
    assert run.returncode == 1, run.stderr
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["ended"] == "unreachable" and summary["episodes"] < 40
    assert summary["episodes"] + summary["episodes_to_certify"] > 40
    assert "ended           stopped early (--stop-when-unreachable): " + said in run.stdout
