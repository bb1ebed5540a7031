"""ambots: cooperative 3D printing with robot arms of different brands.

The core (everything in this package except ``ambots.ros``) never imports
rospy, so it can be used and tested without a ROS master.  Units inside are
metres and radians (REP 103); millimetres appear only at the G-code boundary
(see :mod:`ambots.units`).
"""
import os

__version__ = "0.1.0"

#: Root of the package's data (``urdf/``, ``config/``, ``gcode/``...).  In a
#: source checkout or catkin devel space it is the repository root; an install
#: puts the same folders in ``share/ambots``.
PACKAGE_ROOT = os.environ.get(
    "AMBOTS_ROOT",
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def data_path(*parts):
    """Absolute path of a file shipped with the package, e.g.
    ``data_path('config', 'cells', 'kinova_ur10.yaml')``."""
    return os.path.join(PACKAGE_ROOT, *parts)
