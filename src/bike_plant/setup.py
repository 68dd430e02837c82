from setuptools import find_packages, setup

package_name = "bike_plant"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    package_data={"bike_plant.can": ["*.dbc"]},
    zip_safe=False,
    maintainer="Bike testbed maintainers",
    maintainer_email="maintainers@example.org",
    description="Machine and power stage of the bike testbed: physics kernels (no ROS) and the plant node",
    license="Apache-2.0",
    entry_points={"console_scripts": ["plant_node = bike_plant.entry:plant_node"]},
)
