import os
from glob import glob

from setuptools import find_packages, setup

package_name = "fullperc_drivers"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={"": ["*.c", "*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        (os.path.join("share", package_name, "config"), glob("config/*.yaml")),
        # synthetic NDI tool definitions for the Vega emulator only (config/emulator_roms/README.md)
        (os.path.join("share", package_name, "config", "emulator_roms"),
         glob("config/emulator_roms/*.rom") + glob("config/emulator_roms/*.md")),
        (os.path.join("share", package_name, "launch"), glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="fullperc developers",
    maintainer_email="dev@fullperc.org",
    description="Device drivers: NDI Combined API (Vega TCP, Spectra/Vicra serial), NOKOV mocap, Diana 7 arm.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'ndi_driver = fullperc_drivers.ndi_driver:main',
            'omc_driver = fullperc_drivers.omc_driver:main',
            'diana_state = fullperc_drivers.diana_state:main',
        ],
    },
)
