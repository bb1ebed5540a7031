"""The one place where millimetres (G-code, user-facing reports) and metres
(everything inside, REP 103) are converted."""
import numpy as np

MM = 1e-3  #: one millimetre in metres


def mm_to_m(x):
    """Millimetres -> metres; scalars or arrays of any shape."""
    return np.asarray(x, dtype=float) * MM if not np.isscalar(x) else float(x) * MM


def m_to_mm(x):
    """Metres -> millimetres; scalars or arrays of any shape."""
    return np.asarray(x, dtype=float) / MM if not np.isscalar(x) else float(x) / MM


def mm_per_min_to_m_per_s(f):
    """G-code feedrate (mm/min) -> m/s."""
    return float(f) * MM / 60.0
