"""NPP with certificates, free of ROS: policy, certificate, trajopt, tasks, run, experiment, bench, cli.

Each subpackage says what it may import; tests/test_layering.py holds the whole table and checks it.
"""
