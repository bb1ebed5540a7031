"""A print job, as a sequence of steps: model file -> placed mesh -> parts
(one per arm) -> sliced G-code per part -> coordinated per-arm programs.

Every step is a plain function of the previous step's result, so callers
(the ``slice`` CLI, the front-end node, tests) can run all of it or stop
anywhere.  Units: mm in the bed frame (the G-code frame) for geometry.
"""
import json
import os
from dataclasses import dataclass, field
from typing import Dict, List

from ambots.units import m_to_mm

#: the model of the menu's "start demo" and of ``make demo`` (package-relative): a
#: 240 x 40 x 10 mm block, long enough across the seam for two facing arms to
#: print at the same time (they must stay ~90 mm apart, see coordinate.py)
DEMO_MODEL = "config/models/demo_block.stl"

__all__ = ["DEMO_MODEL", "Job", "prepare_model", "split", "slice_parts", "estimate_one_arm", "coordinate",
           "run_job", "write_job"]


@dataclass
class Job:
    """What a job produced so far."""
    model_path: str
    cell: object
    arms: list
    slicer: str = "builtin"
    mode: str = "concurrent"
    seam: str = "straight"
    mesh: object = None                            #: placed trimesh.Trimesh, mm
    parts: list = field(default_factory=list)      #: partition.Part per arm
    sliced: Dict[str, str] = field(default_factory=dict)
    programs: dict = field(default_factory=dict)   #: arm name -> coordinate.ArmProgram
    #: the best arm printing the whole model alone, timed by the one timing law
    #: on a sample of the layers (:func:`estimate_one_arm`), s; None for a one-arm
    #: job or when no arm reaches the whole model
    one_arm_estimate_s: float = None

    def summary(self):
        """Per-arm figures of the programs (``python -m ambots info`` keys)."""
        from ambots.gcode import parse_gcode_text, summarize
        out = {"model": self.model_path, "cell": self.cell.name, "mode": self.mode, "slicer": self.slicer,
               "model_volume_mm3": float(self.mesh.volume) if self.mesh is not None else None,
               "one_arm_estimate_s": self.one_arm_estimate_s, "arms": {}}
        for part in self.parts:
            name = part.arm.name
            s = summarize(parse_gcode_text(self.programs[name].text, name + ".gcode"))
            out["arms"][name] = {
                "id": part.arm.id, "part_volume_mm3": part.volume, "layers": s["layers"],
                "moves": s["moves"], "extrude_path_mm": s["extrude_path_mm"],
                "travel_path_mm": s["travel_path_mm"], "extruded_filament_mm": s["extruded_filament_mm"],
                "print_time_s": s["print_time_s"], "a_commands": s["a_commands"],
                "stripped_lines": [{"line": l, "text": t} for l, t in self.programs[name].removed]}
        return out


def prepare_model(path, cell, scale=1.0):
    """Step 1: read, repair and check the model; centre it on the bed (bed
    frame, mm) and refuse it if it does not fit the bed."""
    from ambots.mesh import check_fits, load_model, place_on_bed
    mesh = place_on_bed(load_model(path, scale=scale))
    check_fits(mesh, m_to_mm(cell.bed.size[:2]), m_to_mm(cell.bed.max_height))
    return mesh


def split(mesh, cell, arms, seam="straight", settings=None):
    """Step 2: one part per arm, balanced, each inside its arm's reach."""
    from ambots.mesh import to_manifold
    from ambots.partition import PrintEstimate, partition
    est = PrintEstimate()
    if settings is not None:
        est = PrintEstimate(settings.bead_width_mm, settings.layer_height_mm, settings.perimeters,
                            settings.infill_density)
    return partition(to_manifold(mesh), cell, arms, seam=seam, est=est)


def slice_parts(parts, slicer="builtin", settings=None):
    """Step 3: G-code text per arm name."""
    from ambots.slicer import slice_mesh
    return {p.arm.name: slice_mesh(p.to_trimesh(), settings, backend=slicer) for p in parts if not p.empty}


def estimate_one_arm(mesh, cell, arms, slicer="builtin", settings=None):
    """The whole model printed by one arm alone -- what the split is
    measured against: the best of ``arms``, each timed by the firmware's one
    timing law on a sample of the layers (:func:`ambots.motion.estimate_time`),
    s; None if no arm reaches the whole model."""
    from ambots.motion import estimate_time
    from ambots.slicer import slice_mesh
    text = slice_mesh(mesh, settings, backend=slicer)
    times = [t for t in (estimate_time(text, arm, cell, path="whole model") for arm in arms) if t is not None]
    return min(times) if times else None


def coordinate(sliced, parts, cell, mode="concurrent", **kw):
    """Step 4: per-arm programs with A-series coordination."""
    from ambots.coordinate import build_programs
    parts = [p for p in parts if p.arm.name in sliced]
    return build_programs(sliced, parts, cell, mode=mode, **kw)


def run_job(model_path, cell, arms=None, slicer="builtin", mode="concurrent", seam="straight",
            scale=1.0, settings=None):
    """All four steps; returns the :class:`Job`."""
    arms = list(cell.arms if arms is None else arms)
    job = Job(model_path, cell, arms, slicer, mode, seam)
    job.mesh = prepare_model(model_path, cell, scale)
    job.parts = split(job.mesh, cell, arms, seam, settings)
    job.sliced = slice_parts(job.parts, slicer, settings)
    job.programs = coordinate(job.sliced, job.parts, cell, mode)
    if len(arms) > 1:
        job.one_arm_estimate_s = estimate_one_arm(job.mesh, cell, arms, slicer, settings)
    return job


def write_job(job, out_dir):
    """Write ``<arm>.gcode`` (program), ``<arm>.stl`` (part) per arm and
    ``job.json`` (summary) into ``out_dir``; returns the summary."""
    os.makedirs(out_dir, exist_ok=True)
    for part in job.parts:
        name = part.arm.name
        part.to_trimesh().export(os.path.join(out_dir, name + ".stl"))
        if name in job.programs:
            with open(os.path.join(out_dir, name + ".gcode"), "w") as f:
                f.write(job.programs[name].text)
    summary = job.summary()
    with open(os.path.join(out_dir, "job.json"), "w") as f:
        json.dump(summary, f, indent=2)
    return summary
