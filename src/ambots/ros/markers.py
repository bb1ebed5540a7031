"""Markers whose points and colours are numpy arrays.

A shaded deposit layer is tens of thousands of vertices; as
``geometry_msgs/Point`` objects one by one, building and serialising a
marker takes a Python object and a ``struct.pack`` per vertex (about 0.2 s
for a demo layer).  :class:`ArrayMarker` keeps ``xyz`` (N, 3) and ``rgba``
(M, 4) as arrays and writes them with one ``tobytes`` each; everything else
is written by ``Marker.serialize`` itself, so the bytes are exactly those of
a ``visualization_msgs/Marker`` with the same points and colours (the unit
tests compare them).  :class:`ArrayMarkers` is a ``MarkerArray`` that
serialises each marker with its own ``serialize`` (the generated one writes
the markers' fields inline).  ``points`` and ``colors`` still read and
write as lists of objects (built from the arrays, slowly), so an
ArrayMarker in a plain MarkerArray, or code that reads ``points``, still
gets the right values.  Subscribers see ordinary messages."""
import struct
from io import BytesIO

import numpy as np
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

__all__ = ["ArrayMarker", "ArrayMarkers"]

_OTHER_FIELDS = [f for f in Marker.__slots__ if f not in ("points", "colors")]


def _xyz(value):
    return np.ascontiguousarray(value, dtype="<f8").reshape(-1, 3)


def _rgba(value):
    return np.ascontiguousarray(value, dtype="<f4").reshape(-1, 4)


class ArrayMarker(Marker):
    """A Marker whose points and colours are the arrays ``xyz`` (N, 3) and
    ``rgba`` (M, 4; M = 0, N or N / 3 for a ``TRIANGLE_LIST``)."""

    def __init__(self, *args, xyz=None, rgba=None, **kwds):
        super().__init__(*args, **kwds)
        if xyz is not None:
            self.xyz = _xyz(xyz)
        if rgba is not None:
            self.rgba = _rgba(rgba)

    xyz = np.zeros((0, 3))
    rgba = np.zeros((0, 4), "<f4")

    @property
    def points(self):
        return [Point(*p) for p in self.xyz.tolist()]

    @points.setter
    def points(self, value):
        self.xyz = _xyz([(p.x, p.y, p.z) for p in value or ()])

    @property
    def colors(self):
        return [ColorRGBA(*c) for c in self.rgba.tolist()]

    @colors.setter
    def colors(self, value):
        self.rgba = _rgba([(c.r, c.g, c.b, c.a) for c in value or ()])

    def serialize(self, buff):
        # the other fields, by the generated code, from a plain Marker (thread-safe: self is not touched)
        head = BytesIO()
        Marker(**{f: getattr(self, f) for f in _OTHER_FIELDS}).serialize(head)
        b = head.getvalue()
        # after colors come text (uint32 length + bytes), mesh_resource (the same), one uint8
        tail = 4 + len(self.text.encode("utf-8")) + 4 + len(self.mesh_resource.encode("utf-8")) + 1
        cut = len(b) - tail - 8                  # the two uint32 lengths (0) of points and colors
        if b[cut:cut + 8] != bytes(8):
            raise RuntimeError("visualization_msgs/Marker is not laid out as ArrayMarker expects")
        buff.write(b[:cut])
        buff.write(struct.pack("<I", len(self.xyz)))
        buff.write(self.xyz.tobytes())
        buff.write(struct.pack("<I", len(self.rgba)))
        buff.write(self.rgba.tobytes())
        buff.write(b[cut + 8:])

    @property
    def n_bytes(self):
        """Size of the serialised marker."""
        b = BytesIO()
        self.serialize(b)
        return len(b.getvalue())


class ArrayMarkers(MarkerArray):
    """A MarkerArray of :class:`ArrayMarker` (or plain Marker) objects."""

    def serialize(self, buff):
        buff.write(struct.pack("<I", len(self.markers)))
        for m in self.markers:
            m.serialize(buff)
