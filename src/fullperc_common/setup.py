from setuptools import find_packages, setup

package_name = "fullperc_common"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="fullperc developers",
    maintainer_email="dev@fullperc.org",
    description="Shared rigid transforms, ROS message conversion, diagnostics and parameter checks.",
    license="Apache-2.0",
    entry_points={"console_scripts": []},
)
