"""The band choice of the banded sweeps (:mod:`ambots.coordinate.bands`):
its estimate on layers grouped by content is the layer-by-layer one, and
the edges it chooses on a demo-like strip (balanced, not equal widths: the
near band narrower than the middle ones) keep two nozzles the zone apart
across the seam in the offline simulation with random timing, checked on
the executed traces (:func:`test_timing.nozzle_slack`), not on the
scheduler's own figures."""
import numpy as np
import pytest
import trimesh

from ambots.config import default_cell_path, load_cell
from ambots.coordinate import bands
from ambots.coordinate.bands import _estimate, _phase_of
from ambots.job import run_job
from ambots.sim import check_motion, simulate

from test_timing import nozzle_slack


class _Arm:
    def __init__(self, name):
        self.name = name


def _naive_estimate(arms, stats, colour, n_layers, k, t):
    """The estimate's rule written out layer by layer, piece by piece, arm
    by arm: the arms sweeping away print their phases one after the other;
    an arm sweeping towards the seam starts phase p after its phase p-1 and
    after every arm sweeping away has ended its phase p-1 (that end counted
    1 + SYNC_MARGIN); the layer ends with the last arm.  An arm with no
    work on a layer still goes through its phases (it retreats into its
    bands) and waits at the barriers."""
    total = 0.0
    for layer in range(n_layers):
        phases = {}
        for a in arms:              # an arm without work on the layer still sweeps it (and waits)
            d, dur, follows = stats.get((a.name, layer), ((), (), ()))
            per_band = [0.0] * k
            prev = None
            for x, y, f in zip(d, dur, follows):
                b = min(max(int(np.searchsorted(t[a.name], x, side="right")) - 1, 0), k - 1)
                fresh = (not f) or (prev is not None and b != prev)
                per_band[b] += y + (bands.PIECE_S if fresh else 0.0)
                prev = b
            phase_t = [0.0] * k
            for b in range(k):
                phase_t[_phase_of(b, colour[a.name], layer, k)] = per_band[b]
            phases[a.name] = (phase_t, (colour[a.name] + layer) % 2 == 0)
        ends = [0.0] * k            # the latest end of each phase among the arms sweeping away
        for ph, away in phases.values():
            if away:
                done = 0.0
                for p in range(k):
                    done += ph[p]
                    ends[p] = max(ends[p], done)
        layer_t = ends[-1]
        for ph, away in phases.values():
            if not away:
                e = 0.0
                for p in range(k):
                    if p:
                        e = max(e, ends[p - 1] * (1 + bands.SYNC_MARGIN))
                    e += ph[p]
                layer_t = max(layer_t, e)
        total += layer_t + 0.5 * k
    return total


def test_estimate_on_grouped_layers_is_the_layer_by_layer_one():
    rng = np.random.default_rng(0)
    arms = [_Arm("a"), _Arm("b")]
    kinds = []
    for _ in range(3):
        n = int(rng.integers(20, 60))
        kinds.append((rng.uniform(0, 150, n), rng.uniform(0.01, 0.5, n), rng.random(n) < 0.6))
    stats = {}
    for layer in range(11):      # three layer contents, repeated, on both parities
        for i, a in enumerate(arms):
            if layer == 4 and i == 1:
                continue         # an arm without work on a layer
            stats[a.name, layer] = kinds[(layer + i) % 3 if layer < 8 else 0]
    colour = {"a": 0, "b": 1}
    for k in (2, 3, 5):
        t = {"a": np.linspace(0, 150, k), "b": np.array([0.0] + list(np.sort(rng.uniform(0, 150, k - 1))))}
        assert _estimate(arms, stats, colour, 11, k, t) == pytest.approx(
            _naive_estimate(arms, stats, colour, 11, k, t), rel=1e-12)


@pytest.fixture(scope="module")
def strip(tmp_path_factory):
    """Two arms on a 240 x 40 mm strip of six layers (the demo block's plan, thinner)."""
    cell = load_cell(default_cell_path())
    box = trimesh.creation.box((240.0, 40.0, 1.2))
    box.apply_translation((0.0, 0.0, 0.6))
    model = str(tmp_path_factory.mktemp("bands") / "strip.stl")
    box.export(model)
    return cell, run_job(model, cell, list(cell.arms))


def _edges(program):
    """k and the band edges (mm) from the program's header."""
    line = next(l for l in program.lines if "band(s) per layer from" in l)
    t = [float(v) for v in line.split(" from ")[1].split(" mm")[0].split()]
    return int(line.split(" band(s)")[0].split()[-1]), np.array(t)


def test_strip_gets_bands_that_keep_the_zone(strip):
    cell, job = strip
    zone = float(job.programs["kinova"].lines[2].split("seam zone ")[1].split(" mm")[0])
    (k, ta), (kb, tb) = _edges(job.programs["kinova"]), _edges(job.programs["ur10"])
    assert k == kb >= 2
    assert all(ta[i] + tb[k - 1 - i] >= zone - 1e-6 for i in range(k))
    # the zone (50 mm: the heads' fan ducts) is well inside each 120 mm half:
    # two bands, the near one holding about half of each arm's work
    assert zone < ta[1] < 120.0 and zone < tb[1] < 120.0


@pytest.mark.parametrize("seed", (3, 4))
def test_balanced_bands_keep_nozzles_a_zone_apart_with_random_timing(strip, seed):
    """Every block of each arm's motion 0.5-2x as long as planned (``--slow
    ARM=0.5:2``): no contact, and from the simulated traces, whenever both
    nozzles are down at the part, the sum of their distances to the seam
    plane is at least the zone (within how far each strays from its own
    program's path)."""
    cell, job = strip
    result = simulate(job.programs, cell, slow={n: (0.5, 2.0) for n in job.programs}, seed=seed)
    assert result.finished, result.reason
    motion = check_motion(result, cell)
    assert motion["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}, motion
    slack = nozzle_slack(result, cell, job)
    assert ("kinova", "ur10") in slack
    s, n, off = slack["kinova", "ur10"]
    assert n > 1000                                  # both worked at the part at once for a while
    for inside, da, db in off:
        assert inside <= da + db + 0.05, (inside, da, db)
    assert s >= -0.5, "nozzles %.2f mm inside their zone" % -s
