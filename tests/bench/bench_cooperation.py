"""Does cooperation pay?  Models of our own making, of different sizes and
shapes (none is the demo's or the beam's): per model the makespan of the
best single arm, of the two arms of the default cell together, of the
three arms of config/cells/three_arms.yaml around a point (the ring and
the hex plate) and of the four arms of config/cells/four_arms.yaml
together (each with that cell's best single arm), all timed by the one timing law (``ambots.estimate``, as the
planner times its candidates), and the plan the planner chooses
(``ambots.job.run_job``: never slower than one arm; in a cell of three or
four arms also every smaller group of them, the others parked).  Goals (issue
"Cooperation pays"): no chosen plan slower than the best arm alone (ratio
<= 1.00); two arms <= 0.60 on every model at least 250 mm across; the demo
<= 0.53; four arms <= 0.35 on a model of 300 mm or more.

Then every chosen plan runs in the offline simulation on one clock
(``python -m ambots plan``'s engine: every move planned, the real-size
bodies checked continuously), once as planned, then with every block
of each arm's motion stretched by a random factor in [0.5, 2] (``--slow
ARM=0.5:2``, seeds 1, 2 and 3 when more than one arm prints, seed 1
otherwise), the cell's arms without work standing at home until the
first program parks them (A7): contacts (arm-arm, arm-bed, arm-part) must be 0 and the
simulated makespan is printed next to the estimate.  ``BENCH_COOPERATION_SIM=0`` skips the
simulations (the estimates take about a minute in all)."""
import math
import os
import tempfile
import time

import numpy as np
import trimesh

from ambots import data_path
from ambots.config import default_cell_path, load_cell, resolve_path
from ambots.job import DEMO_MODEL, run_job

SLOW = (0.5, 2.0)
#: the seeds of the random per-move factors (several for plans of more than one arm)
SEEDS = (1, 2, 3)


def _lifted(m):
    m.apply_translation((0.0, 0.0, -m.bounds[0][2]))
    return m


def hex_prism(across_corners, height, hole=0.0):
    m = trimesh.creation.cylinder(across_corners / 2.0, height, sections=6)
    if hole > 0:
        m = trimesh.boolean.difference([m, trimesh.creation.cylinder(hole / 2.0, height * 1.5, sections=64)],
                                       engine="manifold")
    return _lifted(m)


def models():
    """name -> (mesh, mm across).  Sizes 30-300 mm."""
    figure = trimesh.boolean.union([trimesh.creation.cylinder(12.0, 8.0, sections=64),
                                    trimesh.creation.cylinder(6.0, 20.0, sections=64).apply_translation((0, 0, 10)),
                                    trimesh.creation.icosphere(3, 8.0).apply_translation((0, 0, 24))],
                                   engine="manifold")
    ring = trimesh.boolean.difference([trimesh.creation.cylinder(70.0, 8.0, sections=128),
                                       trimesh.creation.cylinder(50.0, 10.0, sections=128)], engine="manifold")
    ell = trimesh.boolean.union([trimesh.creation.box((200.0, 40.0, 8.0)).apply_translation((0, -55, 0)),
                                 trimesh.creation.box((40.0, 150.0, 8.0)).apply_translation((-80, 0, 0))],
                                engine="manifold")
    cross = trimesh.boolean.union([trimesh.creation.box((180.0, 30.0, 10.0)),
                                   trimesh.creation.box((30.0, 180.0, 10.0))], engine="manifold")
    # a ramp: 0 to 20 mm high along its 200 mm (the top layers only at one end)
    wedge = trimesh.Trimesh([[-100, -20, 0], [100, -20, 0], [100, 20, 0], [-100, 20, 0], [100, -20, 20],
                             [100, 20, 20]],
                            [[0, 2, 1], [0, 3, 2], [1, 2, 5], [1, 5, 4], [0, 1, 4], [3, 5, 2], [0, 4, 5], [0, 5, 3]])
    wedge.fix_normals()
    # a block leaning 45 deg along the arms' line: its layers move 40 mm from the bed to its top
    x0, x1 = -100.0, 60.0
    lean = trimesh.Trimesh([[x0, -20, 0], [x1, -20, 0], [x1, 20, 0], [x0, 20, 0], [x0 + 40, -20, 40],
                            [x1 + 40, -20, 40], [x1 + 40, 20, 40], [x0 + 40, 20, 40]],
                           [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                            [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    lean.fix_normals()
    plate = hex_prism(300.0, 6.0)
    plate.apply_scale((276.0 / 300.0, 174.0 / (300.0 * math.sqrt(3) / 2), 1.0))
    out = {
        "small figure (32 mm)": _lifted(figure),
        "hex nut (46 mm)": hex_prism(46.0, 20.0, hole=24.0),
        "tower 20x20x120": _lifted(trimesh.creation.box((20.0, 20.0, 120.0))),
        "sphere (100 mm)": _lifted(trimesh.creation.icosphere(4, 50.0)),
        "ring (140 mm)": _lifted(ring),
        "L (200 x 150 mm)": _lifted(ell),
        "cross (180 x 180 mm)": _lifted(cross),
        "wedge (200 x 40 x 0-20 mm)": _lifted(wedge),
        "leaning block (160 x 40 x 40 mm, 45 deg)": _lifted(lean),
        "hex plate (276 x 174 mm)": _lifted(plate),
        "plate 300 x 300 x 4": _lifted(trimesh.creation.box((300.0, 300.0, 4.0))),
        "box 300 x 300 x 20": _lifted(trimesh.creation.box((300.0, 300.0, 20.0))),
    }
    return out


#: the print head the profiles carried before session 14: on the flange's
#: axis, 100 mm out, where turning it about the nozzle axis moves nothing but
#: the head (for the "before" of the nozzle-to-nozzle distance)
COAXIAL_HEAD = """tool:
  xyz: [0.0, 0.0, 0.10]
  rpy: [0.0, 0.0, 0.0]
  head:
    - {name: nozzle, tube: [[0, 0, -0.009], [0, 0, -0.012]], radius: 0.004}
    - {name: heater_block, tube: [[-0.002, 0, -0.022], [0.010, 0, -0.022]], radius: 0.012}
    - {name: fan_duct, tube: [[0, 0, -0.025], [0, 0, -0.045]], radius: 0.020}
    - {name: hot_end, tube: [[0.008, 0, -0.045], [0.008, 0, -0.078]], radius: 0.022}
    - {name: mount, tube: [[0, 0, -0.090], [0, 0, -0.092]], radius: 0.032}
"""


def with_coaxial_heads(cell, folder):
    """The cell with every arm's profile copied into ``folder`` with
    :data:`COAXIAL_HEAD` instead of its own print head."""
    import yaml
    profiles = {}
    for arm in cell.arms:
        if arm.profile.path in profiles:
            continue
        text = open(arm.profile.path).read()
        start, end = text.index("\ntool:") + 1, text.index("\nreach:") + 1
        path = os.path.join(folder, os.path.basename(arm.profile.path))
        with open(path, "w") as f:
            f.write(text[:start] + COAXIAL_HEAD + text[end:])
        profiles[arm.profile.path] = path
    doc = yaml.safe_load(open(cell.path))
    for entry in doc["arms"]:
        entry["profile"] = profiles[resolve_path(entry["profile"], cell.path)]
    path = os.path.join(folder, os.path.basename(cell.path))
    with open(path, "w") as f:
        yaml.safe_dump(doc, f)
    return load_cell(path)


def nozzle_distances(cells, model=None, label="the model"):
    """Item 2 of the issue: how near two arms' nozzles may come across the
    seam between them (the seam zone: both arms' bodies facing each other
    plus the 10 mm margin, :func:`ambots.collision.seam_zones_mm`), with the
    print head on the flange's axis (before) and on the profiles' bracket,
    over the whole bed; and the zone a job of ``model`` (a mesh, called
    ``label`` in the printout) uses, from
    the poses on its parts, where arms at an angle to their seam get the
    clearance those poses keep (:func:`ambots.coordinate.seam_zones_for`)."""
    from ambots.collision import seam_zones_mm
    from ambots.coordinate import seam_zones_for
    from ambots.job import split
    with tempfile.TemporaryDirectory() as tmp:
        for cell in cells:
            before = seam_zones_mm(with_coaxial_heads(cell, tmp))
            after = seam_zones_mm(cell)
            job = seam_zones_for(cell, list(cell.arms), split(model, cell, list(cell.arms))) \
                if model is not None else {}
            for (a, b), mm in sorted(after.items()):
                if a < b:
                    print("nozzle to nozzle across the seam, %-10s %-8s %-8s head on the flange's axis %6.1f mm, "
                          "on the bracket %6.1f mm%s" % (cell.name, a, b, before[a, b], mm,
                                                        ", a job on %s %6.1f mm" % (label, job[a, b])
                                                        if (a, b) in job else ""), flush=True)


def _best_single(job):
    alone = [c for c in job.candidates if len(c.arms) == 1 and c.makespan_s is not None]
    return min(alone, key=lambda c: c.makespan_s) if alone else None


def _row(label, cell, path, simulate_runs):
    from ambots.sim import check_motion, simulate
    t0 = time.perf_counter()
    job = run_job(path, cell)
    wall = time.perf_counter() - t0
    chosen, single = job.chosen, _best_single(job)
    # all the arms with the seams straight (the planner may choose them turned, ambots.job.SEAM_TURNS_DEG,
    # or stepped per layer, ambots.seam_steps)
    together = next((c for c in job.candidates if len(c.arms) == len(cell.arms) and not c.seam_turn_deg
                     and c.seam_steps_mm is None), None)
    how = "+".join(chosen.arms) + (" seam %+g deg" % chosen.seam_turn_deg if chosen.seam_turn_deg else "")
    how += " seam stepped %+.0f..%+.0f mm" % tuple(chosen.seam_steps_mm) if chosen.seam_steps_mm else ""
    ratio = lambda c: (c.makespan_s / single.makespan_s) if c is not None and c.makespan_s and single else math.nan
    line = ("%-32s %-10s best single %s %8s s | %d arms %8s s = %.3f | chosen %-26s %.3f (plan %.0f s wall)"
            % (label, cell.name, single.arms[0] if single else "-", "%.0f" % single.makespan_s if single else "-",
               len(cell.arms), "%.0f" % together.makespan_s if together and together.makespan_s else "-",
               ratio(together), how, ratio(chosen), wall))
    print(line, flush=True)
    if simulate_runs:
        seeds = SEEDS if len(chosen.arms) > 1 else SEEDS[:1]     # one arm: nothing to meet but the bed and part
        runs = [(None, "as planned", 0)] + [({n: SLOW for n in job.programs}, "0.5-2x per move, seed %d" % seed, seed)
                                            for seed in seeds]
        for slow, tag, seed in runs:
            t1 = time.perf_counter()
            res = simulate(job.programs, cell, slow=slow, seed=seed,
                           idle=[a for a in cell.arms if a.name not in job.programs])     # parked by an A7
            motion = check_motion(res, cell)
            hits = motion["collisions"]
            around = sum(r.stats.plans.get("ompl", 0) for r in res.runners.values())
            closest = motion["min_clearance_mm"]          # None: one arm, no two arms to measure
            print("    simulated (%s): makespan %.0f s (estimate %.0f s), %s, contacts %d (%s), closest %s, "
                  "joint moves planned around the bed %d; %.0f s wall"
                  % (tag, res.makespan_s, chosen.makespan_s, "finished" if res.finished else "NOT finished",
                     sum(hits.values()), ", ".join("%s %d" % kv for kv in sorted(hits.items())),
                     "-" if closest is None else "%.1f mm" % closest, around, time.perf_counter() - t1), flush=True)
    return ratio(chosen), ratio(together)


def main():
    two = load_cell(default_cell_path())
    three = load_cell(data_path("config", "cells", "three_arms.yaml"))
    four = load_cell(data_path("config", "cells", "four_arms.yaml"))
    nozzle_distances([two, four], models()["plate 300 x 300 x 4"], "the 300 mm plate")
    sim = os.environ.get("BENCH_COOPERATION_SIM", "1") != "0"
    worst = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        # the demo block on four arms too: their zones cover its width, two of them are faster (session 33)
        rows = [("demo block (240 mm)", data_path(*DEMO_MODEL.split("/")), [two, four])]
        for name, mesh in models().items():
            path = os.path.join(tmp, "".join(c if c.isalnum() else "_" for c in name) + ".stl")
            mesh.export(path)
            cells = [two, four] if "plate" in name or "ring" in name or "box 300" in name else [two]
            if name.startswith(("ring", "hex plate")):          # three around a point (the Panda by data)
                cells.insert(1, three)
            rows.append((name, path, cells))
        for name, path, cells in rows:
            for cell in cells:
                try:
                    chosen, _ = _row(name, cell, path, sim)
                except Exception as exc:          # a model the cell cannot print: say so, go on
                    print("%-32s %-10s cannot be planned: %s" % (name, cell.name, exc), flush=True)
                    continue
                worst = max(worst, chosen)
    print("worst chosen plan / best single arm: %.3f (goal <= 1.00)" % worst, flush=True)


if __name__ == "__main__":
    main()
