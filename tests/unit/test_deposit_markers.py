"""The firmware's deposit markers (ambots.ros.firmware.DepositMarkers,
ambots.ros.markers): shaded TRIANGLE_LIST markers, one per layer, checked
through their serialised bytes as a subscriber (RViz) reads them.  Message
classes only, no ROS master."""
from io import BytesIO

import numpy as np
import pytest
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from ambots.deposit import FILAMENT_AREA_MM2
from ambots.ros.firmware import DepositMarkers
from ambots.ros.markers import ArrayMarker, ArrayMarkers
from ambots.runner import Bead

COLOUR = (1.0, 0.45, 0.0, 1.0)
H = 0.2e-3


def _bytes(msg):
    b = BytesIO()
    msg.serialize(b)
    return b.getvalue()


def _read(msg):
    """What a subscriber gets: the MarkerArray deserialised from the bytes."""
    return MarkerArray().deserialize(_bytes(msg))


def _xyz(m):
    return np.array([[p.x, p.y, p.z] for p in m.points]).reshape(-1, 3)


@pytest.mark.parametrize("n_colours", [0, 1, 3])
def test_array_marker_bytes_equal_a_plain_markers(n_colours):
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(9, 3))
    rgba = rng.uniform(size=({0: 0, 1: 3, 3: 9}[n_colours], 4)).astype(np.float32)   # none, per face, per vertex
    kw = dict(ns="kinova", id=7, type=Marker.TRIANGLE_LIST, action=Marker.ADD, text="t\u00e9xt",
              mesh_resource="package://x/y.stl", mesh_use_embedded_materials=True, frame_locked=True)
    a = ArrayMarker(xyz=xyz, rgba=rgba if n_colours else None, **kw)
    a.header.frame_id, a.header.stamp.secs = "world", 12
    a.pose.orientation.w, a.scale.x, a.color.g = 1.0, 0.5, 0.25
    plain = Marker(**kw)
    plain.header.frame_id, plain.header.stamp.secs = "world", 12
    plain.pose.orientation.w, plain.scale.x, plain.color.g = 1.0, 0.5, 0.25
    plain.points = [Point(*p) for p in xyz.tolist()]
    plain.colors = [ColorRGBA(*c) for c in rgba.tolist()] if n_colours else []
    assert _bytes(a) == _bytes(plain)
    assert _bytes(ArrayMarkers(markers=[a, plain])) == _bytes(MarkerArray(markers=[plain, plain]))
    assert a.n_bytes == len(_bytes(plain))


def test_array_marker_reads_and_writes_points_as_objects_too():
    xyz = np.arange(9.0).reshape(3, 3)
    a = ArrayMarker(xyz=xyz, rgba=[(0.5, 0.25, 0.0, 1.0)], type=Marker.TRIANGLE_LIST)
    assert [(p.x, p.y, p.z) for p in a.points] == [tuple(r) for r in xyz.tolist()]
    assert [(c.r, c.g, c.b, c.a) for c in a.colors] == [(0.5, 0.25, 0.0, 1.0)]
    # in a plain MarkerArray (inline serialisation) the points still go out
    got = _read(MarkerArray(markers=[a])).markers[0]
    np.testing.assert_array_equal(_xyz(got), xyz)
    assert len(got.colors) == 1
    b = ArrayMarker()
    b.points = [Point(1, 2, 3)]
    np.testing.assert_array_equal(b.xyz, [[1, 2, 3]])
    assert ArrayMarker().points == [] and ArrayMarker().xyz.shape == (0, 3)


def _square(z, side=0.02, per_side=8, line0=1):
    """Beads of one square loop at height z, each side laid as ``per_side``
    beads (one G-code line each side), 0.085 mm^2 of cross-section."""
    c = np.array([[0, 0], [side, 0], [side, side], [0, side], [0, 0]], float)
    pts = np.concatenate([np.linspace(a, b, per_side + 1)[:-1] for a, b in zip(c[:-1], c[1:])] + [c[-1:]])
    pts = np.c_[pts, np.full(len(pts), z)]
    p0, p1 = pts[:-1], pts[1:]
    L_mm = np.linalg.norm(p1 - p0, axis=1) * 1e3
    e_mm = 0.085 * L_mm / FILAMENT_AREA_MM2
    line = line0 + np.repeat(np.arange(4), per_side)
    return p0, p1, e_mm, line


def _to_square(xy, side=0.02):
    """Distance (N,) of points to the outline of the square [0, side]^2."""
    c = np.array([[0, 0], [side, 0], [side, side], [0, side], [0, 0]], float)
    a, d = c[:-1], np.diff(c, axis=0)
    t = np.clip(np.einsum("nsk,sk->ns", xy[:, None] - a[None], d) / np.sum(d * d, axis=1), 0, 1)
    return np.linalg.norm(xy[:, None] - (a[None] + t[..., None] * d[None]), axis=2).min(axis=1)


def _bead(p0, p1, e_mm, line, layer):
    k = len(p0)
    return Bead(p0, p1, e_mm, line, np.full(k, layer), np.arange(k, dtype=float))


def test_one_shaded_triangle_list_per_layer():
    dm = DepositMarkers("kinova", "world", COLOUR, H)
    for layer in (0, 1):
        p0, p1, e, line = _square(H * (layer + 1), line0=10 * layer)
        for i in range(0, len(p0), 5):                 # a few beads per step, as the firmware lays them
            dm.add(_bead(p0[i:i + 5], p1[i:i + 5], e[i:i + 5], line[i:i + 5], layer))
    assert dm.n_beads == 64
    arr = _read(dm.changed())
    assert [(m.ns, m.id) for m in arr.markers] == [("kinova", 0), ("kinova", 1)]
    for layer, m in enumerate(arr.markers):
        assert (m.type, m.action, m.header.frame_id) == (Marker.TRIANGLE_LIST, Marker.ADD, "world")
        np.testing.assert_allclose((m.color.r, m.color.g, m.color.b, m.color.a), COLOUR, atol=1e-6)
        # 4 sides merged from 8 beads each -> 4 tubes of 6 faces, 2 triangles a face
        assert len(m.points) == 4 * 12 * 3
        assert len(m.colors) == len(m.points) // 3            # one colour per triangle
        P = _xyz(m)
        z = H * (layer + 1)
        assert P[:, 2].max() == pytest.approx(z, abs=1e-9) and P[:, 2].min() == pytest.approx(z - H, abs=1e-9)
        # every vertex within the tube's half-width (4/3 of the box's, 0.085 / 0.2 mm wide) of the square
        half = 4 / 3 * 0.085e-6 / H / 2
        assert _to_square(P[:, :2]).max() <= half + 1e-9
        C = np.array([[c.r, c.g, c.b, c.a] for c in m.colors])
        assert len(np.unique(np.round(C[:, 0], 6))) >= 3, "one flat colour: not shaded"
        np.testing.assert_allclose(C[:, 1], C[:, 0] * 0.45, atol=1e-6)       # the arm's hue
    assert dm.changed() is None                                # nothing new


def test_only_changed_markers_are_built_again_and_all_gives_everything():
    dm = DepositMarkers("ur10", "world", COLOUR, H, max_beads=20)
    p0, p1, e, line = _square(H)
    dm.add(_bead(p0[:10], p1[:10], e[:10], line[:10], 0))
    first = dm.changed()
    assert [m.id for m in first.markers] == [0]
    dm.add(_bead(p0[10:], p1[10:], e[10:], line[10:], 0))       # 32 beads: marker 0 full at 20, then 1
    again = dm.changed(stamp=None)
    assert [m.id for m in again.markers] == [0, 1]
    assert again.markers[0] is not first.markers[0]                # rebuilt with the new beads
    dm.new_run()
    dm.add(_bead(p0[:4], p1[:4], e[:4], line[:4], 0))
    assert [m.id for m in dm.changed().markers] == [2]             # a new run never overwrites
    every = dm.all()
    assert [m.id for m in every.markers] == [0, 1, 2]
    assert every.markers[2] is dm.all().markers[2]                 # built once, kept
    n = sum(len(m.points) for m in _read(every).markers) // 3
    assert n > 0 and n % 12 == 0


def test_marker_bytes_per_bead_segment():
    """The cost of a layer on the wire: 12 triangles a straight segment,
    3 points of 24 bytes and one colour of 16 bytes each."""
    dm = DepositMarkers("kinova", "world", COLOUR, H)
    p0, p1, e, line = _square(H)
    dm.add(_bead(p0, p1, e, line, 0))
    m = dm.changed().markers[0]
    empty = ArrayMarker(xyz=np.zeros((0, 3)))
    empty.header, empty.ns, empty.type = m.header, m.ns, m.type
    assert m.n_bytes - empty.n_bytes == 4 * 12 * (3 * 24 + 16)


def _block_layer(z, layer, per_line=4):
    """Beads of one solid layer 20 x 4 mm at nozzle height z: the outline
    (G-code lines 0-3), then lines along x 0.4 mm apart (one G-code line
    each), every line laid as ``per_line`` beads."""
    c = [(0, 0), (0.02, 0), (0.02, 0.004), (0, 0.004), (0, 0)]
    lines = list(zip(c[:-1], c[1:])) + [((4e-4, y), (0.02 - 4e-4, y)) for y in np.arange(4e-4, 0.0038, 4e-4)]
    p0, p1, line = [], [], []
    for k, (a, b) in enumerate(lines):
        P = np.linspace(np.r_[a, z], np.r_[b, z], per_line + 1)
        p0.append(P[:-1]), p1.append(P[1:]), line.append(np.full(per_line, k))
    p0, p1, line = np.concatenate(p0), np.concatenate(p1), np.concatenate(line)
    e_mm = 0.08 * np.linalg.norm(p1 - p0, axis=1) * 1e3 / FILAMENT_AREA_MM2       # 0.4 x 0.2 mm
    return _bead(p0, p1, e_mm, line, layer)


def test_buried_segments_are_left_out_and_fully_buried_markers_deleted():
    # 5 layers; a marker holds at most 16 beads: each layer's outline (4 lines x 4 beads) is one
    # marker, its infill (9 lines) two or three more
    dm = DepositMarkers("ur10", "world", COLOUR, H, max_beads=16, floor_z=0.0)
    for k in range(5):
        dm.add(_block_layer(H * (k + 1), k))
    before = _read(dm.changed())
    assert all(len(m.points) for m in before.markers)           # no exposure found yet: all drawn
    n_before = sum(len(m.points) for m in before.markers) // 3
    assert n_before == 5 * 13 * 12
    assert dm.update_exposure(force=True)
    assert not dm.update_exposure(force=True)                     # no new beads: nothing to do
    after = {(m.id): m for m in _read(dm.changed()).markers}
    every = {m.id: m for m in _read(dm.all()).markers}
    # the top layer and every outline stay whole; the infill under the top is gone
    for mid, m in every.items():
        P = _xyz(m)
        top = len(P) and P[:, 2].max() > 4.5 * H
        outline = len(P) and (np.isclose(P[:, 1], 0, atol=4e-4) | np.isclose(P[:, 1], 0.004, atol=4e-4)).any()
        if m.action == Marker.DELETE:
            assert mid in after and not top and len(P) == 0
        else:
            assert top or outline, "a buried marker is still drawn"
    deleted = [m for m in every.values() if m.action == Marker.DELETE]
    assert len(deleted) >= 4 * 2                                  # the infill markers of layers 0-3
    n_after = sum(len(m.points) for m in every.values()) // 3
    assert n_after == (4 * 4 + 13) * 12                            # outlines of 4 layers + the whole top
    # a new layer on top: the old top is buried at the next update, the new one drawn
    dm.add(_block_layer(H * 6, 5))
    dm.update_exposure(force=True)
    n_final = sum(len(m.points) for m in _read(dm.all()).markers) // 3
    assert n_final == (5 * 4 + 13) * 12


def test_exposure_waits_for_its_period():
    dm = DepositMarkers("ur10", "world", COLOUR, H, exposure_period=10.0)
    dm.add(_block_layer(H, 0))
    assert dm.update_exposure(now=100.0)
    dm.add(_block_layer(2 * H, 1))
    assert not dm.update_exposure(now=105.0)
    assert dm.update_exposure(now=110.5)
