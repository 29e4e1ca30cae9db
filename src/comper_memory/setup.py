from glob import glob

from setuptools import find_packages, setup

package_name = "comper_memory"

setup(
    name=package_name,
    version="0.2.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="COMPER suite developers",
    maintainer_email="dev@example.com",
    description="Compact experience replay memory (TM, similarity sets, RTM) as a ROS 2 service, with a client for other learners.",
    license="Apache-2.0",
    entry_points={"console_scripts": [
        "memory_node = comper_memory.memory_node:main",
    ]},
)
