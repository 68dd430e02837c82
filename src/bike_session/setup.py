from setuptools import find_packages, setup

package_name = "bike_session"

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
    description="Session manager, recorder, launcher and CLI of the bike testbed",
    license="Apache-2.0",
    entry_points={"console_scripts": ["session_node = bike_plant.entry:session_node", "recorder_node = bike_plant.entry:recorder_node",
                                      "ftms_node = bike_plant.entry:ftms_node"]},
)
