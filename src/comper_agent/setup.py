from glob import glob

from setuptools import find_packages, setup

package_name = "comper_agent"

setup(
    name=package_name,
    version="0.2.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="COMPER suite developers",
    maintainer_email="dev@example.com",
    description="COMPER and COMCACT agents, the Q-target (QT) trainer, recording and offline evaluation.",
    license="Apache-2.0",
    entry_points={"console_scripts": [
        "qt_trainer_node = comper_agent.nodes.qt_trainer_node:main",
        "comcact_node = comper_agent.nodes.comcact_node:main",
        "comper_node = comper_agent.nodes.comper_node:main",
        "actor_node = comper_agent.nodes.actor_node:main",
        "recorder_node = comper_agent.recording.recorder_node:main",
        "evaluate = comper_agent.offline.evaluate:main",
        "bag_to_memory = comper_agent.recording.bag_tools:bag_to_memory_main",
        "export_dataset = comper_agent.recording.bag_tools:export_dataset_main",
        "bag_repair = comper_agent.recording.bag_tools:bag_repair_main",
        "bringup = comper_agent.tools.supervisor:main",
    ]},
)
