from glob import glob

from setuptools import find_packages, setup

package_name = "comper_sim"

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
    description="Simulation bridge: gymnasium MuJoCo/classic-control and ALE (Machado et al. 2018 protocol) behind lock-step ROS 2 services.",
    license="Apache-2.0",
    entry_points={"console_scripts": [
        "sim_node = comper_sim.sim_node:main",
    ]},
)
