"""ambots.rviz.closeup_view: the capture's second view, close to the seam
of two arms' deposits, and rviz_config with it."""
import numpy as np
import pytest
import yaml

from ambots.config import default_cell_path, load_cell
from ambots.rviz import FIELD_OF_VIEW, OVERVIEW_YAW, closeup_view, rviz_config

H = 0.2e-3


def _half(x0, x1, y0=-0.02, y1=0.02, layers=50, step=1e-3):
    """Nozzle points filling a box [x0, x1] x [y0, y1], ``layers`` layers high."""
    x, y, k = np.meshgrid(np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step), np.arange(layers))
    return np.c_[x.ravel(), y.ravel(), (k.ravel() + 1) * H]


def test_closeup_looks_at_the_seam_on_the_outer_wall_close_enough_for_layers():
    left, right = _half(-0.12, -0.0002), _half(0.0002, 0.12)      # two halves, the seam at x = 0
    v = closeup_view({"a": left, "b": right}, H)
    f = v["Focal Point"]
    assert abs(f["X"]) < 1e-3                                       # at the seam
    # on the long wall the camera's side of (the overview looks from -y)
    assert f["Y"] == pytest.approx(-0.02, abs=1e-3)
    assert 0 < f["Z"] <= 50 * H
    # one layer at least 6 pixels tall in a 700-pixel-high view
    visible = 2 * v["Distance"] * np.tan(FIELD_OF_VIEW / 2)
    assert H * 700 / visible >= 6 - 1e-9
    # the camera (Orbit: focal + distance along yaw/pitch) is outside the part, on the -y side, above the bed
    c = np.array([f["X"], f["Y"], f["Z"]]) + v["Distance"] * np.array(
        [np.cos(v["Pitch"]) * np.cos(v["Yaw"]), np.cos(v["Pitch"]) * np.sin(v["Yaw"]), np.sin(v["Pitch"])])
    assert c[1] < -0.02 and c[2] > 0
    assert 0 < v["Near Clip Distance"] < v["Distance"]


def test_closeup_of_one_arm_and_of_nothing():
    assert closeup_view({}, H) is None
    assert closeup_view({"a": np.zeros((0, 3))}, H) is None
    v = closeup_view({"a": _half(0.0, 0.05)}, H)
    assert v is not None and v["Distance"] > 0


def test_rviz_config_takes_the_view():
    cell = load_cell(default_cell_path())
    view = {"Focal Point": {"X": 0.5, "Y": -0.02, "Z": 0.005}, "Distance": 0.03, "Yaw": 5.0, "Pitch": 0.3,
            "Near Clip Distance": 0.003}
    cfg = yaml.safe_load(rviz_config(cell, view))
    current = cfg["Visualization Manager"]["Views"]["Current"]
    for k, value in view.items():
        assert current[k] == value
    assert current["Class"] == "rviz/Orbit"
    overview = yaml.safe_load(rviz_config(cell))["Visualization Manager"]["Views"]["Current"]
    assert overview["Yaw"] == OVERVIEW_YAW and overview["Distance"] > 1.0
    # the same displays in both
    assert cfg["Visualization Manager"]["Displays"] == \
        yaml.safe_load(rviz_config(cell))["Visualization Manager"]["Displays"]
