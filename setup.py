import os
from glob import glob

from setuptools import find_packages, setup

package_name = "inseggan_ros"


def share_tree(folder):
    """data_files entries that install `folder` under share/inseggan_ros, keeping its layout."""
    entries = {}
    for path in sorted(glob(os.path.join(folder, "**", "*"), recursive=True)):
        if os.path.isfile(path):
            folder_in_share = os.path.join("share", package_name, os.path.dirname(path))
            entries.setdefault(folder_in_share, []).append(path)
    return list(entries.items())


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["tests", "tools"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml", "README.md"]),
    ] + share_tree("models") + share_tree("bags") + share_tree("config") + share_tree("launch"),
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},
    zip_safe=True,
    maintainer="inseggan_ros developers",
    maintainer_email="dev@inseggan-ros.invalid",
    description="Unsupervised instance segmentation of identical objects in a bin (InSeGAN)",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "inseggan = inseggan_ros.cli:main",
            "bin_replay = inseggan_ros.ros.bin_replay:main",
            "segmenter = inseggan_ros.ros.segmenter:main",
        ],
    },
)
