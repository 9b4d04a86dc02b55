"""The README's main job (scripts/demo.py): real simulator node -> estimator node, estimates beside ground truth."""
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from estimator_models import build_streaming_model

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.ros


def test_demo_prints_estimates_beside_ground_truth(tmp_path, ros_domain_id):
    model = build_streaming_model(tmp_path)  # the bundled model's quality is training's business
    result = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "demo.py"), "--episodes", "2", "--model", str(model),
         "--logs", str(tmp_path / "logs"), "--timeout", "240"],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("unseen-")]
    assert len(rows) == 2, result.stdout
    for row in rows:
        name, truth, estimate = row.split(" | ")
        assert name.split()[0].split("-")[-2] == truth.split()[0]  # the episode's material, as ground truth
        assert re.search(r"^(jelly|plasticine|sand) +\(p=[01]\.\d\d\) .*\[25 frames, [\d.]+ ms\]$", estimate)
    assert "accuracy" in result.stdout


def test_ctrl_c_stops_the_demo_and_its_nodes_cleanly(tmp_path, ros_domain_id):
    model = build_streaming_model(tmp_path)
    demo = subprocess.Popen(
        [sys.executable, str(REPO / "scripts" / "demo.py"), "--episodes", "50", "--model", str(model),
         "--logs", str(tmp_path / "logs"), "--timeout", "240"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for line in demo.stdout:  # the simulator is starting: both nodes are up
            if line.startswith("estimator up"):
                break
        time.sleep(1.0)
        demo.send_signal(signal.SIGINT)
        _, err = demo.communicate(timeout=60)
    finally:
        demo.kill()
    assert demo.returncode == 130, err
    assert "Traceback" not in err and "demo: interrupted" in err, err
    leftovers = subprocess.run(["pgrep", "-f", str(model)], capture_output=True, text=True).stdout.split()
    assert leftovers == [], f"estimator node still running: {leftovers}"


@pytest.mark.parametrize("argv, expected", [
    (["--episodes", "0"], "argument --episodes: expected a whole number >= 1, got '0'"),  # started both nodes
    (["--episodes", "-1"], "argument --episodes: expected a whole number >= 1, got '-1'"),
    (["--timeout", "-5"], "argument --timeout: expected a number > 0, got '-5'"),  # "the estimator did not come up"
    (["--real-time-factor", "-1"], "argument --real-time-factor: expected a number >= 0, got '-1'"),  # the simulator failed
    (["--real-time-factor", "nan"], "argument --real-time-factor: expected a number >= 0, got 'nan'"),
    (["--logs", "{tmp}/file"], "--logs: {tmp}/file is a file; give a folder for the node logs"),  # FileExistsError
    (["--logs", "{tmp}/file/logs"], "--logs: cannot make the folder {tmp}/file/logs: Not a directory"),
])
def test_a_bad_argument_is_one_line_before_any_node_starts(tmp_path, ros_domain_id, argv, expected):
    (tmp_path / "file").write_text("not a folder")
    result = subprocess.run([sys.executable, str(REPO / "scripts" / "demo.py"), "--logs", str(tmp_path / "logs"),
                             *[a.format(tmp=tmp_path) for a in argv]], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.splitlines()[-1] == f"./run_demo.sh: error: {expected.format(tmp=tmp_path)}", result.stderr
    assert "Traceback" not in result.stderr and "estimator up" not in result.stdout


def test_run_demo_help_answers_without_re_running_setup():
    """`./run_demo.sh --help` on a set-up checkout: the demo's options, without setup's checks first."""
    result = subprocess.run([str(REPO / "run_demo.sh"), "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage: ./run_demo.sh") and "--episodes" in result.stdout
    assert "up to date" not in result.stdout + result.stderr  # setup.sh's re-run lines


def _demo_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("demo", REPO / "scripts" / "demo.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _Node:
    """Takes the Listener's subscriptions; the test calls their callbacks."""

    def __init__(self):
        self.callbacks = {}

    def create_subscription(self, msg_type, topic, callback, qos):
        self.callbacks[topic] = callback


def test_no_more_rows_than_episodes_asked_for(capsys):
    """With --real-time-factor 0, estimates arrive faster than the main loop looks: `--episodes 2` printed 3 rows,
    a summary over 3, then one more row after the summary while the nodes were being stopped."""
    from ad_msgs.msg import MaterialEstimate, SimInstance

    demo = _demo_module()
    node = _Node()
    listener = demo.Listener(node, 2)
    for k in range(4):
        instance = SimInstance(episode_id=f"unseen-box-sand-000{k}", shape="box", material="sand",
                               parameter_names=["friction_angle"], parameters=[0.5])
        instance.header.stamp.sec = 10 + k
        node.callbacks["/ad_sim/instance"](instance)
        estimate = MaterialEstimate(material="sand", class_names=["jelly", "plasticine", "sand"],
                                    class_probabilities=[0.0, 0.0, 1.0], parameter_names=["friction_angle"],
                                    parameters=[0.4], parameter_uncertainties=[0.1], frames_used=25)
        estimate.oldest_stamp.sec = 10 + k
        node.callbacks["/ad_estimator/estimate"](estimate)
    assert [i.episode_id for i, _ in listener.rows] == ["unseen-box-sand-0000", "unseen-box-sand-0001"]
    printed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert printed == [i.episode_id for i, _ in listener.rows]
    assert demo.summary(listener.rows).startswith("accuracy 2/2;")


def test_an_estimate_without_its_episodes_first_frame_is_still_paired(capsys):
    """The estimator's oldest frame need not be the episode's first (a frame lost on the way): pairing by equal
    stamps left such an estimate waiting for ever, and the demo reported fewer rows than episodes."""
    from ad_msgs.msg import MaterialEstimate, SimInstance

    demo = _demo_module()
    node = _Node()
    listener = demo.Listener(node)
    for k, lost in enumerate([0, 2]):  # the second episode's first two frames (25 ms apart) were lost
        instance = SimInstance(episode_id=f"unseen-box-sand-000{k}", shape="box", material="sand",
                               parameter_names=["friction_angle"], parameters=[0.5])
        instance.header.stamp.sec = 10 + 2 * k  # episodes 2 s apart
        node.callbacks["/ad_sim/instance"](instance)
        estimate = MaterialEstimate(material="sand", class_names=["jelly", "plasticine", "sand"],
                                    class_probabilities=[0.0, 0.0, 1.0], parameter_names=["friction_angle"],
                                    parameters=[0.4], parameter_uncertainties=[0.1], frames_used=25 - lost)
        estimate.oldest_stamp.sec, estimate.oldest_stamp.nanosec = 10 + 2 * k, lost * 25_000_000
        node.callbacks["/ad_estimator/estimate"](estimate)
    assert [i.episode_id for i, _ in listener.rows] == ["unseen-box-sand-0000", "unseen-box-sand-0001"]
    assert not listener.pending
    late = MaterialEstimate(material="sand")  # stamped after the last episode's frames: not paired with it
    late.oldest_stamp.sec, late.oldest_stamp.nanosec = 12, 700_000_000
    node.callbacks["/ad_estimator/estimate"](late)
    assert listener.pending == [late] and len(listener.rows) == 2
