"""ambots: cooperative 3D printing with robot arms of different brands.

The core (everything in this package except ``ambots.ros``) never imports
rospy, so it can be used and tested without a ROS master.  Units inside are
metres and radians (REP 103); millimetres appear only at the G-code boundary
(see :mod:`ambots.units`).
"""
import os

__version__ = "0.1.0"


def _package_root():
    """Root of the package's data (``urdf/``, ``config/``, ``gcode/``...): the
    repository root in a source checkout or catkin devel space (where this
    file may run from catkin's relay, so ``__path__`` is searched), else the
    installed ``share/ambots``; ``AMBOTS_ROOT`` overrides both."""
    if os.environ.get("AMBOTS_ROOT"):
        return os.environ["AMBOTS_ROOT"]
    for p in list(globals().get("__path__", [])) + [os.path.dirname(os.path.abspath(__file__))]:
        root = os.path.dirname(os.path.dirname(os.path.realpath(p)))
        if os.path.isfile(os.path.join(root, "package.xml")) and os.path.isdir(os.path.join(root, "urdf")):
            return root
    try:  # installed: data lives in share/ambots
        import rospkg
        return rospkg.RosPack().get_path("ambots")
    except Exception:  # rospkg missing or package not on ROS_PACKAGE_PATH
        return os.getcwd()


#: see :func:`_package_root`
PACKAGE_ROOT = _package_root()


def data_path(*parts):
    """Absolute path of a file shipped with the package, e.g.
    ``data_path('config', 'cells', 'kinova_ur10.yaml')``."""
    return os.path.join(PACKAGE_ROOT, *parts)
