"""The robots inside a set, one by one: where in the set a policy and its expert fail (success_map, its figure in
figure, and expert_map, the expert alone before a run) and a claim about the share of robots on which the policy
succeeds often enough (claim), which a certificate over (s0, theta) does not make.

Part of npp_ros.run. May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt, npp_ros.tasks, npp_ros.run.
"""
