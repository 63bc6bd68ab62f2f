from glob import glob

from setuptools import find_packages, setup

package_name = "inseggan_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["tests"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml", "README.md"]),
        ("share/" + package_name + "/models", [f for f in glob("models/**/*", recursive=True)
                                                if not f.endswith("/")]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="inseggan_ros developers",
    maintainer_email="dev@inseggan-ros.invalid",
    description="Unsupervised instance segmentation of identical objects in a bin (InSeGAN)",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "inseggan = inseggan_ros.cli:main",
            "bin_replay = inseggan_ros.nodes.bin_replay:main",
        ],
    },
)
