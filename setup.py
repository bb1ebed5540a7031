"""Python package layout for catkin_python_setup(); not for pip."""
from setuptools import setup

from catkin_pkg.python_setup import generate_distutils_setup

setup(**generate_distutils_setup(packages=["ambots", "ambots.commands", "ambots.coordinate", "ambots.ros"],
                                 package_dir={"": "src"}))
