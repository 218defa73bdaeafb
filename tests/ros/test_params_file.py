"""A run's settings from a ROS 2 parameters file: npp-run's --params-file, the nodes' --ros-args --params-file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from npp_ros_graph.graph.description import NODES
from npp_ros_graph.graph.npp_run_options import parse_args
from npp_ros_graph.tools.run import run_request


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_npp_run_takes_its_settings_from_the_file_and_the_command_line_wins(tmp_path: Path) -> None:
    params = write(tmp_path / "run.yaml", "npp_run:\n  ros__parameters:\n    task: lqr_2_1\n    seed: 3\n"
                   "    max_episodes: 7\n    epsilon: 12.5\n    no_rollouts: true\n    run_dir: here\n")  # fmt: skip
    args = parse_args("", ["--params-file", str(params), "--seed", "5"])
    assert (args.task, args.seed, args.max_episodes, args.epsilon) == ("lqr_2_1", 5, 7, 12.5)
    assert args.no_rollouts is True and args.run_dir == Path("here")
    request = run_request(args)  # the request's own checks take the file's values as the command line's
    assert (request.task, request.seed, request.max_episodes, request.epsilon) == ("lqr_2_1", 5, 7, 12.5)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        (
            "npp_run:\n  ros__parameters:\n    max_episode: 7\n",
            "unknown npp-run setting 'max_episode'; did you mean 'max_episodes'?",
        ),
        ("npp_sim:\n  ros__parameters:\n    seed: 1\n", "has no 'npp_run: ros__parameters:' section (found: npp_sim)"),
        ("npp_run:\n  ros__parameters:\n    no_rollouts: 3\n", "no_rollouts takes true or false, got 3"),
        ("npp_run: [unclosed\n", "cannot read the parameters file"),
        ("npp_run:\n  ros__parameters:\n    max_episodes: -4\n", "--max-episodes: must be an integer >= 1, got '-4'"),
    ],
)
def test_a_bad_parameters_file_is_refused_in_one_line_before_anything_starts(
    tmp_path: Path, text: str, reason: str, capsys: pytest.CaptureFixture[str]
) -> None:
    params = write(tmp_path / "run.yaml", text)
    with pytest.raises(SystemExit) as stopped:
        parse_args("", ["--params-file", str(params)])
    assert stopped.value.code == 2
    assert reason in capsys.readouterr().err


def test_a_node_reads_its_parameters_file_and_refuses_an_unknown_name_in_it(tmp_path: Path) -> None:
    """rclpy's own --params-file: the node's known names from it, an unknown one refused as on the command line."""
    params = write(tmp_path / "sim.yaml", "/**:\n  ros__parameters:\n    horizn: 50\n")
    cmd = [sys.executable, "-m", NODES["sim"].module, "--ros-args", "-r", "__ns:=/params_file", "--params-file"]
    done = subprocess.run([*cmd, str(params)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "unknown parameter 'horizn'; did you mean 'horizon'?" in done.stderr, done.stderr
