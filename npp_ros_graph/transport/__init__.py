"""What crosses between processes: topic names and QoS, message <-> core conversions, run seals, parameters.

May import: the npp_ros core; nothing else of npp_ros_graph.
"""
