"""A run whose plant is a robot: its checks are the robot's own episodes from its reset, and the expert's plans are
run on it by their feedback law, so what joins the data is what the robot did.

The robot is reached through a small link (link: reset, one command per control period, the measured state back);
episodes drives the policy on it and keeps every robot episode in the run file as it ends (a fault cuts an episode,
which is stored and marked, never counted as a check); expert plans on a model of the robot and runs the plan on it;
simulated is a MuJoCo robot behind the same link, with parameters the run is not told (tests, trials); setup builds
the run from a request and a link.

Part of npp_ros.run. May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt, npp_ros.tasks, npp_ros.run.
"""
