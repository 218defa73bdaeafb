"""What crosses between the graph's processes by name: topic and service names, QoS, refusal prefixes.

Names are relative, so that the usual namespacing and remapping apply; both ends of a topic use the QoS named here.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# Topic and service names, relative so that the usual namespacing and remapping apply.
STATE = "npp/state"
ACTION = "npp/action"
GAP = "npp/gap"
EPISODE = "npp/episode"
CERTIFICATE = "npp/certificate"
EXPERT_SERVICE = "npp/expert/trajectory"
PLANT = "npp/sim/plant"
RESET_SERVICE = "npp/sim/reset"
ROLLOUT_DONE = "npp/sim/rollout"
DATASET_TOPIC = "npp/dataset/trajectory"
DATASET_SERVICE = "npp/dataset/get"
POLICY_STATUS = "npp/policy/trajectories"
POLICY_DROPPED = "npp/policy/dropped_states"
# ros2_control's conventions, spoken by npp-deploy and npp-robot: joint_state_broadcaster's states and a
# forward_command_controller's commands (absolute: they are the robot's topics, not a run's).
JOINT_STATES = "/joint_states"
FORWARD_COMMANDS = "/forward_effort_controller/commands"

# Service refusals that say "ask again": a caller retries these within its deadline; any other refusal
# (a bad request, a foreign plant) is final for that request.
BUSY = "busy:"
NOT_READY = "not ready:"

# Lockstep control: every state and action matters, so reliable with a short queue.
CONTROL_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# Reports a monitor may read late: reliable, deeper queue.
REPORT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# The supervisor's per-episode reports (/npp/gap, /npp/episode) are kept for late subscribers that ask for
# them (npp-record): a recorder started before the run whose discovery of the supervisor comes after the
# first episodes still records every one, and npp-run, which starts its supervisor, gets all of its run's. Volatile
# subscribers (npp-monitor) get new ones only.
REPORT_HISTORY_QOS = QoSProfile(
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
)
# Requests queue while one is served; rclpy's default service queue (KEEP_LAST 10) silently drops
# the oldest when more than 10 clients' requests are pending, so services keep a deep one.
SERVICE_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# Latched: late joiners get the last value (both ends must be transient local and reliable). A publisher
# keeps its last sample (LATCHED_QOS); a reader keeps the last sample of every publisher, up to 100
# (LATCHED_READER_QOS). A one-deep reader keeps only the sample that came last: with a stranger's sample on
# the same topic (a second sim's plant description), the run's own could be overwritten before it was read,
# and no publisher ever sends it again, so the node would wait for it forever.
LATCHED_QOS = QoSProfile(
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
)
LATCHED_READER_QOS = QoSProfile(
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
)
