"""The four test shapes (mm), built at test time so that no binary fixture
lives in the repository: a cube, a cylinder, a model with an overhang (a T)
and a model with a hole through it."""
import manifold3d as m3
import trimesh

from ambots.mesh import from_manifold


def cube():
    return trimesh.creation.box((20.0, 20.0, 20.0))


def cylinder():
    return trimesh.creation.cylinder(radius=8.0, height=12.0, sections=48)


def overhang():  # a T: the bar overhangs the stem on both sides
    return from_manifold(m3.Manifold.cube([6, 6, 10]).translate([-3, -3, 0])
                         + m3.Manifold.cube([24, 6, 4]).translate([-12, -3, 10]))


def hole_through():
    return from_manifold(m3.Manifold.cube([24, 24, 8], True)
                         - m3.Manifold.cylinder(12, 5, 5, 48, True))


MODELS = {"cube": cube, "cylinder": cylinder, "overhang": overhang, "hole": hole_through}


def sections(mesh, z):
    """shapely (Multi)Polygons of the mesh's cross-sections at heights ``z`` (mm)."""
    import shapely
    out = []
    for path in mesh.section_multiplane([0, 0, 0], [0, 0, 1], list(z)):
        polys = [] if path is None else path.polygons_full
        out.append(shapely.union_all(polys) if polys else shapely.Polygon())
    return out
