"""scripts/ros_install.sh: where scripts/setup.sh takes ROS 2 Jazzy from (a full install, sourced or at
/opt/ros/jazzy, or the PyPI wheels), run against fake prefixes, and the lock installed over a full install.
The full-install path of setup.sh itself is not exercised here (no ROS install on these machines)."""
import os
import subprocess

from conftest import ROOT

SCRIPT = str(ROOT / "scripts" / "ros_install.sh")


def fake_prefix(path, rclpy=True, setup=True):
    (path / "share" / "rclpy").mkdir(parents=True)
    if rclpy:
        (path / "share" / "rclpy" / "package.xml").write_text("<package/>")
    if setup:
        (path / "setup.bash").write_text("# fake\n")
    return path


def detect(tmp_path, **env):
    base = {"PATH": os.environ["PATH"], "HOME": str(tmp_path), "COMPER_ROS_ROOT": str(tmp_path / "opt_ros")}
    res = subprocess.run([SCRIPT, "detect"], capture_output=True, text=True, env={**base, **env})
    return res.returncode, res.stdout.strip(), res.stderr


def test_no_install_means_the_pypi_wheels(tmp_path):
    assert detect(tmp_path) == (0, "pypi", "")


def test_an_install_at_opt_ros_jazzy_is_used(tmp_path):
    fake_prefix(tmp_path / "opt_ros" / "jazzy")
    assert detect(tmp_path)[:2] == (0, f"system {tmp_path / 'opt_ros' / 'jazzy'}")
    assert detect(tmp_path, COMPER_ROS="pypi")[:2] == (0, "pypi")


def test_a_sourced_jazzy_is_used_before_opt_and_a_venv_or_overlay_is_skipped(tmp_path):
    fake_prefix(tmp_path / "opt_ros" / "jazzy")
    venv = fake_prefix(tmp_path / "venv", setup=False)             # the PyPI wheels' prefix: no setup.bash
    overlay = tmp_path / "ws" / "install"
    overlay.mkdir(parents=True)
    (overlay / "setup.bash").write_text("")                          # a workspace: no rclpy
    underlay = fake_prefix(tmp_path / "custom" / "jazzy")
    path = ":".join(map(str, (overlay, venv, underlay)))
    assert detect(tmp_path, ROS_DISTRO="jazzy", AMENT_PREFIX_PATH=path)[:2] == (0, f"system {underlay}")
    # a sourced jazzy whose prefixes hold no rclpy falls back to /opt/ros/jazzy
    assert detect(tmp_path, ROS_DISTRO="jazzy", AMENT_PREFIX_PATH=str(overlay))[:2] == \
        (0, f"system {tmp_path / 'opt_ros' / 'jazzy'}")


def test_another_sourced_distro_or_a_missing_forced_install_is_an_error(tmp_path):
    rc, out, err = detect(tmp_path, ROS_DISTRO="humble", AMENT_PREFIX_PATH=str(tmp_path))
    assert rc == 1 and out == "" and "ROS 2 'humble' is sourced" in err and "needs Jazzy" in err
    rc, out, err = detect(tmp_path, COMPER_ROS="system")
    assert rc == 1 and "no ROS 2 Jazzy install was found" in err
    rc, _, err = detect(tmp_path, COMPER_ROS="apt")
    assert rc == 1 and "COMPER_ROS must be auto, pypi or system" in err
    fake_prefix(tmp_path / "opt_ros" / "jazzy", rclpy=False)         # an incomplete install is not one
    assert detect(tmp_path)[:2] == (0, "pypi")


def test_the_lock_over_a_full_install_keeps_the_python_stack_and_drops_what_the_install_provides():
    full = (ROOT / "requirements.lock").read_text().splitlines()
    res = subprocess.run([SCRIPT, "lock", str(ROOT / "requirements.lock")], capture_output=True, text=True,
                         check=True)
    kept = res.stdout.splitlines()
    names = {line.split("==")[0].split("[")[0].lower() for line in kept if "==" in line}
    assert not any(n.startswith("ros-") for n in names)
    assert not names & {"numpy", "empy", "lark-parser", "catkin-pkg", "setuptools"}
    assert {"torch", "gymnasium", "mujoco", "faiss-cpu", "rosbags", "colcon-common-extensions"} <= names
    dropped = [line for line in full if line not in kept]
    assert all(line.split("==")[0].lower().startswith("ros-") or line.split("==")[0].lower() in
               {"numpy", "empy", "lark-parser", "catkin-pkg", "setuptools"} for line in dropped), dropped
