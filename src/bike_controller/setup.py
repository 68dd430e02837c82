from setuptools import find_packages, setup

package_name = "bike_controller"

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
    maintainer="Bike testbed maintainers",
    maintainer_email="maintainers@example.org",
    description="Torque controller of the bike testbed: control laws (no ROS) and the batched inner-loop node",
    license="Apache-2.0",
    entry_points={"console_scripts": ["controller_node = bike_plant.entry:controller_node",
                                      "bike-drive-emulator = bike_plant.entry:drive_emulator"]},
)
