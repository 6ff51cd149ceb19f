import os
from glob import glob

from setuptools import find_packages, setup

package_name = "fullperc_fusion"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={"": ["*.c", "*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        (os.path.join("share", package_name, "config"), glob("config/*.yaml")),
        (os.path.join("share", package_name, "launch"), glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="fullperc developers",
    maintainer_email="dev@fullperc.org",
    description="Estimation: frame chain, KF/BKF/CKF/CBKF, synchronizer, view-margin model; fusion and margin nodes.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'fusion_node = fullperc_fusion.fusion_node:main',
            'margin_node = fullperc_fusion.margin_node:main',
            'calibrate = fullperc_fusion.calibrate:main',
        ],
    },
)
