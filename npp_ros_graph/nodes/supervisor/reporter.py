"""What the supervisor tells the rest of the world per episode: the gap report and episode result, the
certificate, new trajectories for the policy, and the run folder's CSV logs."""

from __future__ import annotations

import csv
from collections.abc import Callable
from pathlib import Path

from npp_interfaces.msg import Certificate as CertificateMsg
from npp_interfaces.msg import EpisodeResult, GapReport
from rclpy.clock import Clock
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.publisher import Publisher

from npp_ros.certificate.certifier import Certificate, CertificationStatus
from npp_ros.policy.dataset import Trajectory
from npp_ros.run.loop import Observer, RunConfig
from npp_ros.run.progress import unreachable_text
from npp_ros.run.records import EpisodeRow, append_episode_log
from npp_ros.tasks.registry import task_label
from npp_ros_graph.transport.convert import certificate_to_msg, episode_result, gap_report
from npp_ros_graph.transport.message_seal import RunSeal

GAP_COLUMNS = ["episode", "gap", "v_lb", "v_ub", "epsilon", "oracle_called", "dataset_size", "oracle_calls", "quiet"]


class GraphReporter(Observer):
    """Publishes gap reports, episode results and the certificate; appends the CSV logs.

    It gets what it uses: the three report publishers, the run's seal (key, plant and identity) and the
    context that names that plant and run in each report (runtime/reports.py: a viewer checks a report
    like the run's own data), a way to send a trajectory to the policy, the node's clock and logger, the
    run's config and its folder.
    """

    def __init__(
        self,
        *,
        gaps: Publisher,
        episodes: Publisher,
        certificates: Publisher,
        send_trajectory: Callable[[int, Trajectory], None],
        seal: RunSeal,
        context: str,
        clock: Clock,
        logger: RcutilsLogger,
        config: RunConfig,
        run_dir: Path,
        max_episodes: int | None = None,
    ) -> None:
        self.gaps, self.episodes, self.certificates = gaps, episodes, certificates
        self.send_trajectory, self.seal, self.context = send_trajectory, seal, context
        self.clock, self.logger, self.config = clock, logger, config
        self.epsilon = config.spec.epsilon  # the gap log's column, from the spec the reports are built from
        self.gap_log = run_dir / "gaps.csv"
        self.episode_log = run_dir / "episodes.csv"
        self.max_episodes = max_episodes  # says once when no certificate can come within it
        self.unreachable = ""

    def on_episode(self, row: EpisodeRow, status: CertificationStatus) -> None:
        stamp = self.clock.now().to_msg()
        gap: GapReport = gap_report(row, self.config, stamp)
        self.gaps.publish(self.seal.seal_header(gap, self.context))
        result: EpisodeResult = episode_result(row, self.config.horizon, stamp)
        self.episodes.publish(self.seal.seal_header(result, self.context))
        _append(
            self.gap_log,
            GAP_COLUMNS,
            [row.episode, row.gap, row.v_lb, row.v_ub, self.epsilon, int(row.oracle_called), row.dataset_size,
             row.oracle_calls, row.quiet_episodes],
        )  # fmt: skip
        append_episode_log(self.episode_log, row)  # the columns npp-learn writes too
        if self.max_episodes is not None and not self.unreachable:
            self.unreachable = unreachable_text(status, row.episode + 1, self.max_episodes) or ""
            if self.unreachable:
                self.logger.warning(self.unreachable)

    def on_trajectory(self, index: int, trajectory: Trajectory) -> None:
        self.send_trajectory(index, trajectory)

    def on_certificate(self, certificate: Certificate) -> None:
        msg: CertificateMsg = certificate_to_msg(certificate, self.clock.now().to_msg())
        self.certificates.publish(self.seal.seal_header(msg, self.context))
        self.logger.info("\n" + certificate.summary(task_label(self.config.task)))


def _append(path: Path, header: list[str], row: list[object]) -> None:
    new = not path.exists()
    with path.open("a", newline="") as fh:
        writer = csv.writer(fh)
        if new:
            writer.writerow(header)
        writer.writerow(row)
