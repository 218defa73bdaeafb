"""What a certificate may claim: the counterexample to Theorem 3.4, and the stopping rule under repeated looks.

The counterexample in short: the 1-D integrator f(s, a) = s + a with
r(s, a) = -|s| - 0.1|a| and gamma = 0.99 has V*(s) = -1.1|s|; L = 2.1 bounds the slope of Q*, and
one expert trajectory from s0 = 1 is a consistent dataset. At s = 0.1 the greedy policy copies the
data point at 0 (action 0) and stays at 0.1 forever: V^pi(0.1) = -10 while V_lb(0.1) = -0.21.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from npp_ros.certificate import mixture
from npp_ros.certificate.certifier import STOPPING_RULES as RULES
from npp_ros.certificate.certifier import CertificationSpec, false_certificate_rate
from npp_ros.certificate.values import ValueBasis, theorem_34_condition
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, FloatArray, Trajectory
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.loop import NPPLoop, RunConfig

GAMMA = 0.99
L = 2.1
EPSILON = 0.5
HORIZON = 4000  # gamma^H * 10 < 1e-16: the discounted H-step return is the value to rounding


def expert_trajectory(s0: float) -> Trajectory:
    """Move to 0 in one step, then stay: Q = V*(s) along the way; the return is V*(s0)."""
    states = np.array([[s0], [0.0], [0.0]])
    actions = np.array([[-s0], [0.0], [0.0]])
    values = np.array([-1.1 * abs(s0), 0.0, 0.0])
    return Trajectory(states, actions, values, expert_return=-1.1 * abs(s0))


class IntegratorExpert:
    def trajectory(self, initial_state: FloatArray) -> Trajectory:
        return expert_trajectory(float(initial_state[0]))


def discounted_return(policy: NonparametricPolicy, s0: float) -> float:
    s, total, weight = s0, 0.0, 1.0
    for _ in range(HORIZON):
        a = float(policy.act(np.array([s]))[0])
        total += weight * (-abs(s) - 0.1 * abs(a))
        s, weight = s + a, weight * GAMMA
    return total


class IntegratorRollouts:
    def run_episode(self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy) -> float:
        return discounted_return(policy, float(initial_state[0]))


def basis() -> ValueBasis:
    holds, text = theorem_34_condition(L, GAMMA, transition_lipschitz=1.0, reward_lipschitz=1.0, where="all of R")
    tail_bound = GAMMA**HORIZON * 1.1 * 10  # what the truncated horizon can hide, far below rounding
    return ValueBasis("the discounted value V*", lambda s0: tail_bound, "tail(s0) <= gamma^H max|V|", holds, text)


def loop(certify: str) -> NPPLoop:
    spec = CertificationSpec("i", EPSILON, 0.9, 0.1, LipschitzConstant(L, "user"), certify=certify)
    config = RunConfig(task="integrator", seed=0, state_dim=1, action_dim=1, spec=spec, gamma=GAMMA)
    states = lambda episode: np.array([1.0 if episode == 0 else 0.1])  # noqa: E731
    return NPPLoop(config, IntegratorExpert(), states, driver=IntegratorRollouts(), basis=basis())


def test_counterexample_breaks_theorem_34_with_a_valid_lipschitz_constant() -> None:
    data = Dataset(1, 1)
    data.append(expert_trajectory(1.0))
    policy = NonparametricPolicy(data, L)
    s = np.array([0.1])
    assert policy.v_lb(s) == pytest.approx(-0.21) and policy.v_ub(s) == pytest.approx(0.21)
    assert float(policy.act(s)[0]) == 0.0
    assert discounted_return(policy, 0.1) == pytest.approx(-10.0, abs=1e-9)
    assert policy.v_lb(s) > discounted_return(policy, 0.1)  # V_lb(0.1) > V^pi(0.1): Theorem 3.4 fails
    assert policy.gap(s) <= EPSILON and -1.1 * 0.1 - discounted_return(policy, 0.1) > 9.8  # Proposition 3.7 too


def test_surrogate_mode_certifies_there_and_says_the_proof_does_not_hold() -> None:
    run = loop("surrogate")
    result = run.run(max_episodes=200)
    cert = result.certificate
    assert cert is not None and result.oracle_calls == 1  # every check at 0.1 passes: 0.42 <= 0.5
    assert not cert.proven
    assert any("gamma L_f" in a and "misses it" in a and "not a proven bound" in a for a in cert.assumptions)
    assert discounted_return(run.policy, 0.1) == pytest.approx(-10.0)  # and the claim is false


def test_rollout_mode_never_passes_the_counterexample_state() -> None:
    run = loop("rollout")
    run.run_episode()  # s0 = 1: the expert's trajectory
    assert float(run.policy.act(np.array([0.1]))[0]) == 0.0  # the policy of the counterexample
    row = run.run_episode()  # s0 = 0.1
    assert row.checked_gap == pytest.approx(0.21 + 10.0, abs=1e-9) and row.oracle_called
    result = run.run(max_episodes=200)
    cert = result.certificate
    assert cert is not None and cert.proven and cert.policy_trajectories == 2
    # Every check the certified policy passed is a true gap within epsilon.
    assert -1.1 * 0.1 - discounted_return(run.policy, 0.1) <= EPSILON
    passes = [r for r in result.rows if r.checked_gap <= EPSILON]
    assert passes and all(r.policy_return == pytest.approx(-0.11) for r in passes)


@pytest.mark.parametrize("q", [0.85])
def test_sequential_rule_keeps_false_certificates_below_delta(q: float) -> None:
    repetitions, delta = 2000, 0.1
    # One-sided margin: 3 standard errors of a frequency at delta (sampling error over 2,000 runs).
    margin = 3 * math.sqrt(delta * (1 - delta) / repetitions)
    lipschitz = LipschitzConstant(L, "user")
    rule = {name: CertificationSpec("i", EPSILON, 0.9, delta, lipschitz, rule=name) for name in RULES}
    sequential = false_certificate_rate(rule["sequential"], q, repetitions, seed=7)
    paper = false_certificate_rate(rule["paper"], q, repetitions, seed=7)
    assert sequential + margin < delta, f"sequential rule: {sequential:.3%} false certificates"
    assert paper - margin > delta, f"paper's rule: {paper:.3%} false certificates"


@pytest.mark.parametrize("q", [0.85, 0.9])
def test_mixture_rule_keeps_false_certificates_below_delta(q: float) -> None:
    """Every policy passes a check with probability q <= p = 0.9, so every certificate is false; the
    simulation feeds the rule's own certifier pass/fail outcomes (no plant), 1,000 episodes a run."""
    repetitions, delta = 2000, 0.1
    margin = 3 * math.sqrt(delta * (1 - delta) / repetitions)  # 3 standard errors of a frequency at delta
    spec = CertificationSpec("i", EPSILON, 0.9, delta, LipschitzConstant(L, "user"), rule="mixture")
    rate = mixture.false_certificate_rate(spec, q, repetitions, seed=7)
    assert rate + margin < delta, f"mixture rule at q = {q}: {rate:.3%} false certificates"
