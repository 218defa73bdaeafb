"""Which robot of a set this one is, from its own motion, and whether the certified policy holds at it.

A recording of the robot's states and commands (recording), the set's parameters fitted to it by least squares on
one-step predictions through MuJoCo (fit: the combinations the motion can tell apart, with intervals, the delay, and
where the robot lies against the set), a short bounded excitation to add to its commands (excitation), and the check
of the certified policy at the identified robot before it moves (check), from an identification file npp-identify
wrote (identified). npp-identify and npp-deploy call these.

May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt, npp_ros.tasks, npp_ros.run.
"""
