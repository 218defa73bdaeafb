"""ROS 2 adapters over the npp_ros core: one process per node, thin by design."""
