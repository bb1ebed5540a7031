"""Deposited beads: analytic volume, the mesh's volume and shape, colours,
export, the empty case and a large deposit."""
import numpy as np
import pytest
import trimesh

from ambots.deposit import Deposit, bead_boxes

W, H = 0.45e-3, 0.2e-3            # bead width and layer height, m
AREA = W * H


def square_loop(side=0.02, z=0.0002, centre=(0.0, 0.0)):
    cx, cy = centre
    c = np.array([[cx - side / 2, cy - side / 2, z], [cx + side / 2, cy - side / 2, z],
                  [cx + side / 2, cy + side / 2, z], [cx - side / 2, cy + side / 2, z]])
    return c, np.roll(c, -1, axis=0)


def disjoint_beads(rng, k):
    """k beads in random directions (some sloped, one vertical), each in its
    own 10 mm cell of a grid, so that no two boxes meet."""
    cells = np.stack(np.meshgrid(np.arange(10), np.arange(10), np.arange(10), indexing="ij"), -1).reshape(-1, 3)
    centres = cells[rng.choice(len(cells), k, replace=False)] * 0.01
    d = rng.normal(size=(k, 3))
    d[: k // 2, 2] = 0.0                                              # half of them horizontal
    d[0] = (0.0, 0.0, 1.0)                                            # and one vertical
    d *= (rng.uniform(0.5, 3.0, k) * 1e-3 / np.linalg.norm(d, axis=1))[:, None]
    return centres - d / 2, centres + d / 2


def test_volume_of_disjoint_beads():
    rng = np.random.default_rng(4)
    s, e = disjoint_beads(rng, 60)
    area = rng.uniform(0.5, 2.0, 60) * AREA
    height = rng.uniform(0.1, 0.3, 60) * 1e-3
    dep = Deposit()
    dep.add("ur10", s[:40], e[:40], area[:40], height[:40])
    dep.add("kinova", s[40:], e[40:], area[40:], height[40:])
    expected = np.sum(np.linalg.norm(e - s, axis=1) * area)
    assert dep.volume_m3() == pytest.approx(expected, rel=1e-12)
    assert dep.volume_m3("ur10") + dep.volume_m3("kinova") == pytest.approx(expected, rel=1e-12)
    assert dep.volume_mm3() == pytest.approx(expected * 1e9, rel=1e-12)
    mesh = dep.to_mesh()
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(expected, rel=1e-9)            # positive: outward normals
    assert len(mesh.split(only_watertight=True)) == 60
    # every box is one bead: its extents along its own frame are length, width, height
    corners = bead_boxes(s, e, area, height)
    for c, a, h, L in zip(corners[:5], area, height, np.linalg.norm(e - s, axis=1)):
        assert np.linalg.norm(c[4] - c[0]) == pytest.approx(L)
        assert np.linalg.norm(c[2] - c[0]) == pytest.approx(a / h)
        assert np.linalg.norm(c[1] - c[0]) == pytest.approx(h)


def test_square_loop():
    side, z = 0.02, 0.0004
    s, e = square_loop(side, z)
    dep = Deposit()
    dep.add("kinova", s, e, AREA, H)
    assert dep.volume_m3() == pytest.approx(4 * side * AREA)
    mesh = dep.to_mesh()
    assert len(mesh.vertices) == 32 and len(mesh.faces) == 48
    # overlapping corners are counted once per bead, as in the analytic volume
    assert mesh.volume == pytest.approx(4 * side * AREA, rel=1e-9)
    # top faces at the nozzle height, beads centred on the path, notched corners
    lo, hi = dep.bounds()
    np.testing.assert_allclose(lo, [-side / 2 - W / 2, -side / 2 - W / 2, z - H], atol=1e-12)
    np.testing.assert_allclose(hi, [side / 2 + W / 2, side / 2 + W / 2, z], atol=1e-12)
    np.testing.assert_allclose(mesh.bounds, dep.bounds())
    assert not mesh.contains([[side / 2 + W / 4, side / 2 + W / 4, z - H / 2]])[0]   # corner notch
    assert mesh.contains([[0.0, -side / 2, z - H / 2]])[0]                            # inside a bead
    seg = dep.segments("kinova")
    np.testing.assert_array_equal(seg.starts, s)
    np.testing.assert_allclose(seg.height, H)


def test_colours_and_export(tmp_path):
    dep = Deposit()
    s, e = square_loop()
    dep.add("kinova", s, e, AREA, H)
    dep.add("ur10", s + [0.05, 0, 0], e + [0.05, 0, 0], AREA, H)
    mesh = dep.to_mesh(colours={"kinova": (0.95, 0.40, 0.05, 1.0)})
    vc = mesh.visual.vertex_colors
    assert np.all(vc[:32] == [242, 102, 13, 255]) and np.all(vc[32:] == [178, 178, 178, 255])
    ply = dep.export(tmp_path / "beads.ply", colours={"kinova": (1, 0, 0), "ur10": (0, 0, 1)}, scale=1000.0)
    back = trimesh.load(ply, process=False)
    assert back.volume == pytest.approx(dep.volume_mm3(), rel=1e-6)
    assert np.all(back.visual.vertex_colors[32:, :3] == [0, 0, 255])
    stl = trimesh.load(dep.export(tmp_path / "beads.STL"))
    assert stl.volume == pytest.approx(dep.volume_m3(), rel=1e-5)
    with pytest.raises(ValueError, match="ply or .stl"):
        dep.export(tmp_path / "beads.obj")
    with pytest.raises(ValueError):
        dep.to_mesh(colours={"ur10": (255, 0, 0)})


def test_empty_deposit():
    dep = Deposit()
    mesh = dep.to_mesh(colours={"kinova": (1, 0, 0)})
    assert mesh.is_empty and len(mesh.faces) == 0
    assert dep.volume_m3() == 0.0 and dep.bounds() is None and len(dep) == 0
    assert dep.segments("kinova").starts.shape == (0, 3)
    dep.add("kinova", np.zeros((0, 3)), np.zeros((0, 3)), AREA, H)
    assert dep.to_mesh().is_empty and dep.arms == ["kinova"]


def test_bad_input():
    dep = Deposit()
    s, e = square_loop()
    with pytest.raises(ValueError):
        dep.add("a", s, e[:3], AREA, H)
    with pytest.raises(ValueError):
        dep.add("a", s[:, :2], e[:, :2], AREA, H)
    with pytest.raises(ValueError):
        dep.add("a", s, e, -AREA, H)
    with pytest.raises(ValueError):
        dep.add("a", s, e, [AREA] * 3, H)
    with pytest.raises(ValueError):
        dep.add("a", s, e * np.nan, AREA, H)
    assert len(dep) == 0


def test_many_beads():
    rng = np.random.default_rng(0)
    k = 100_000
    s = rng.uniform(-0.1, 0.1, (k, 3))
    e = s + rng.normal(scale=1e-3, size=(k, 3)) * [1, 1, 0]
    dep = Deposit()
    dep.add("ur10", s, e, AREA, H)
    mesh = dep.to_mesh(colours={"ur10": (0, 0, 1)})
    assert len(mesh.faces) == 12 * k
    assert mesh.volume == pytest.approx(dep.volume_m3(), rel=1e-6)


def test_the_one_deposit_builder_keeps_the_filament_volume():
    """deposit_of_beads (used by plan and by the live capture): each bead's
    box holds exactly the filament pushed for it, pi (1.75/2)^2 mm^2 x E mm;
    beads without length or filament are left out."""
    from ambots.deposit import deposit_of_beads
    rng = np.random.default_rng(3)
    p0 = rng.uniform(-0.05, 0.05, (40, 3))
    p1 = p0 + rng.uniform(-0.01, 0.01, (40, 3))
    p1[5] = p0[5]                                   # no length
    e = rng.uniform(0.01, 0.5, 40)
    e[7] = 0.0                                      # no filament
    dep = deposit_of_beads({"a": (p0[:20], p1[:20], e[:20]), "b": (p0[20:], p1[20:], e[20:])}, 0.0002)
    want = np.pi * (1.75 / 2) ** 2 * (e.sum() - e[5])
    assert dep.volume_mm3() == pytest.approx(want, rel=1e-9)
    assert len(dep.segments("a").starts) == 18 and len(dep.segments("b").starts) == 20
