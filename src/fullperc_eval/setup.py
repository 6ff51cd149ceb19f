import os
from glob import glob

from setuptools import find_packages, setup

package_name = "fullperc_eval"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={"": ["*.c", "*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        (os.path.join("share", package_name, "config"),
         glob("config/*.yaml") + glob("config/*.rviz")),
        (os.path.join("share", package_name, "launch"), glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="fullperc developers",
    maintainer_email="dev@fullperc.org",
    description="Evaluation: OR digital twin, device emulators, rosbag2 record/replay, offline evaluation, supervisor.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'sim = fullperc_eval.sim.cli:main',
            'vega_emulator = fullperc_eval.emulators.vega_cli:main',
            'record = fullperc_eval.bag.record:main',
            'play = fullperc_eval.bag.play:main',
            'evaluate = fullperc_eval.evaluation.cli:main',
            'fit_noise_model = fullperc_eval.evaluation.sensor_stats:main',
            'time_align = fullperc_eval.evaluation.time_align_cli:main',
            'supervisor = fullperc_eval.graph.cli:main',
            'echo = fullperc_eval.bag.topic_tools:echo_main',
            'pub = fullperc_eval.bag.topic_tools:pub_main',
            'call = fullperc_eval.bag.topic_tools:call_main',
        ],
    },
)
