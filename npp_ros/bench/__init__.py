"""The benchmark of the exact index and the experts: measurements and the report (bench.md, bench.json).

May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt, npp_ros.tasks, npp_ros.run.
"""
