"""ROS 2 adapters over the npp_ros core: transport, runtime, graph, nodes, tools and the ROS loop bench.

Each subpackage says what it may import; tests/test_layering.py holds the whole table and checks it.
"""
