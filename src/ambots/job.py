"""A print job, as a sequence of steps: model file -> placed mesh -> parts
(one per arm) -> sliced G-code per part -> coordinated per-arm programs.

Every step is a plain function of the previous step's result, so callers
(the ``slice`` CLI, the front-end node, tests) can run all of it or stop
anywhere.  Units: mm in the bed frame (the G-code frame) for geometry.
"""
import functools
import gc
import glob
import json
import math
import os
from dataclasses import dataclass, field, replace
from typing import Dict, List

from ambots import data_path
from ambots.errors import AmbotsError, ConfigError, MeshError
from ambots.partition import is_beam
from ambots.units import m_to_mm

#: the model of the menu's "start demo" and of ``make demo`` (package-relative): a
#: 240 x 40 x 10 mm block, long enough across the seam for two facing arms to
#: print at the same time (they must stay ~90 mm apart, see ambots.coordinate)
DEMO_MODEL = "config/models/demo_block.stl"

__all__ = ["DEMO_MODEL", "Job", "Candidate", "prepare_model", "split", "slice_parts", "coordinate", "run_job",
           "write_job", "plan_lines", "REPAIRED_MESH", "overhang_lines", "unsupported_line", "TIE_SHARE"]


#: the garbage collector's first threshold while a job is planned or written
#: (Python's default: 700 allocations).  A job makes millions of small
#: objects (segments, tuples) that live until it ends, and each full
#: collection walks all of them: the 60 mm sphere's job (``bench_frontend``)
#: made 7 full collections taking 0.67 s of its 6.9 CPU s in one process.
#: With this threshold, side by side on the same machine (session 25, two
#: runs each): CPU 8.5 -> 7.5-7.7 s, wall 1.28x -> 1.15x prusa-slicer's
#: (50,000 and 200,000: no better).  Reference cycles are still collected
#: (with the collector off the same job peaked at 1.7 GB instead of 1.1 GB).
GC_THRESHOLD = 10000


def fewer_collections(fn):
    """``fn`` run with the collector's first threshold raised to
    :data:`GC_THRESHOLD` (restored after; the worker processes it forks
    inherit it)."""
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        old = gc.get_threshold()
        gc.set_threshold(max(old[0], GC_THRESHOLD), *old[1:])
        try:
            return fn(*args, **kwargs)
        finally:
            gc.set_threshold(*old)
    return wrapped


@dataclass
class Candidate:
    """One plan the job considered: ``arms`` (names) printing the model
    ``how`` ("concurrent", "sequential" or "alone"), its makespan timed by
    the one timing law (:mod:`ambots.estimate`), s, or None with ``note``
    saying why it is not possible."""
    arms: List[str]
    how: str
    makespan_s: float = None
    note: str = None
    programs: dict = field(default=None, repr=False)   #: {arm name: ArmProgram}, when built
    #: {arm name: G-code events of its program}, the one parse of each program
    events: dict = field(default=None, repr=False)
    #: {arm name: {"start_s", "busy_s" (s it moves), "idle_s" (s it waits
    #: after its start), "done_s" (when it is done)}} on the plan's one
    #: clock, when timed (:func:`ambots.estimate.estimate_programs`)
    timeline: dict = field(default=None, repr=False)
    #: the seams turned by this many degrees, counter-clockwise, from the
    #: arms' power diagram (:data:`SEAM_TURNS_DEG`)
    seam_turn_deg: float = 0.0
    #: a stepped seam (:mod:`ambots.seam_steps`): per layer, mm the seam moves
    #: along the first arm's plane normal from the straight seam (None: straight)
    seam_offsets: object = field(default=None, repr=False)
    #: {arm name: pace} its parts were split with (:func:`split`), None: all alike
    pace: dict = field(default=None, repr=False)
    #: {arm name: (its program's figures, :func:`ambots.gcode.summarize`; its
    #: extrusion paths, :func:`ambots.overhang.extrusion_paths`)}: what the job
    #: writes of :attr:`events`, made instead of them when the candidate is sent
    #: from a worker process (:meth:`__getstate__`), else None
    figures: dict = field(default=None, repr=False)

    def __getstate__(self):
        """Pickled (sent back by a worker process, :mod:`ambots.parallel`)
        with :attr:`figures` of its events instead of the events: the job
        writes only those (:meth:`Job.summary`, :meth:`Job.overhang`), and
        the 60 mm sphere's program's 116,000 events took 0.45 s to pickle and
        read back, on the way from the planning to the written job."""
        state = dict(self.__dict__)
        if self.events:
            from ambots.gcode import summarize
            from ambots.overhang import extrusion_paths
            state["figures"] = dict(self.figures or {}, **{
                n: (summarize(ev), extrusion_paths(ev)) for n, ev in self.events.items()})
            state["events"] = None
        return state

    @property
    def seam_steps_mm(self):
        """[least, most] mm a stepped seam moves from the straight seam on
        its layers, or None."""
        o = self.seam_offsets
        return None if o is None else [round(float(min(o)), 1), round(float(max(o)), 1)]

    @property
    def busy_s(self):
        """{arm name: s it moves (its time less its waits)}, when timed."""
        return None if self.timeline is None else {n: a["busy_s"] for n, a in self.timeline.items()}

    def as_dict(self):
        return {"arms": list(self.arms), "how": self.how,
                "makespan_s": None if self.makespan_s is None else round(float(self.makespan_s), 1),
                "note": self.note, "seam_turn_deg": float(self.seam_turn_deg), "seam_steps_mm": self.seam_steps_mm}


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
    #: the plans considered (:class:`Candidate`), the chosen one first
    candidates: list = field(default_factory=list)
    #: True when the arm set was forced (``--arms``): no other plan was considered
    forced: bool = False
    #: the slicer.SliceSettings the parts were sliced with (None: the defaults)
    settings: object = None
    #: the repaired model's file name in the job folder, once :func:`write_job` wrote it
    repaired_path: str = None

    @property
    def chosen(self):
        return self.candidates[0] if self.candidates else None

    @property
    def one_arm_estimate_s(self):
        """The best arm printing the whole model alone, s (None if no
        candidate has one arm, or none of them is possible)."""
        alone = [c.makespan_s for c in self.candidates if len(c.arms) == 1 and c.makespan_s is not None]
        return min(alone) if alone else None

    def plan_summary(self):
        """The choice, for job.json, report.json and the summaries."""
        chosen = self.chosen
        alone = self.one_arm_estimate_s
        return {"arms": list(chosen.arms) if chosen else [a.name for a in self.arms],
                "how": chosen.how if chosen else self.mode,
                "seam_turn_deg": float(chosen.seam_turn_deg) if chosen else 0.0,
                "seam_steps_mm": chosen.seam_steps_mm if chosen else None,
                "makespan_estimate_s": None if chosen is None or chosen.makespan_s is None
                else round(float(chosen.makespan_s), 1),
                "best_single_arm_s": None if alone is None else round(float(alone), 1),
                "speedup": None if not (chosen and chosen.makespan_s and alone) else round(alone / chosen.makespan_s, 3),
                "forced": self.forced,
                "candidates": [c.as_dict() for c in self.candidates]}

    def summary(self):
        """Per-arm figures of the programs (``python -m ambots info`` keys)."""
        from ambots.gcode import summarize
        from ambots.mesh import signed_volume
        # the programs' figures, from the one parse that timed them (parsed here if not timed);
        # summed for the chosen plan only
        out = {"model": self.model_path, "cell": self.cell.name, "mode": self.mode, "slicer": self.slicer,
               "model_volume_mm3": signed_volume(self.mesh) if self.mesh is not None else None,
               "one_arm_estimate_s": self.one_arm_estimate_s, "plan": self.plan_summary(), "arms": {}}
        built = self._built()
        timeline = (built.timeline if built is not None else None) or {}
        figures = self._figures()
        out["overhang"] = self.overhang()
        out["repair"] = self.repair()
        out["seams"] = self.seam_setup()
        for part in self.parts:
            name = part.arm.name
            if name not in self.programs:
                continue
            s = figures[name][0] if name in figures else summarize(self.events()[name])
            out["arms"][name] = {
                "id": part.arm.id, "part_volume_mm3": part.volume, "layers": s["layers"],
                "moves": s["moves"], "extrude_path_mm": s["extrude_path_mm"],
                "travel_path_mm": s["travel_path_mm"], "extruded_filament_mm": s["extruded_filament_mm"],
                "print_time_s": s["print_time_s"], "a_commands": s["a_commands"],
                # the one timing law's figures of this arm in the plan (None: not timed)
                **{k: None if name not in timeline else round(float(timeline[name][k]), 1)
                   for k in ("busy_s", "idle_s", "done_s")},
                "stripped_lines": [{"line": l, "text": t} for l, t in self.programs[name].removed]}
        return out


    def seam_setup(self, settings=None):
        """What the seam figures are measured against
        (:func:`ambots.seams.seam_setup`: planes, layers, bead width), with
        the job's slice settings (or ``settings``); None for one part."""
        from ambots.seams import seam_setup
        from ambots.slicer import SliceSettings
        if self.mesh is None or not self.parts:
            return None
        return seam_setup(self.parts, self.seam, settings or self.settings or SliceSettings(),
                          float(self.mesh.bounds[1][2]))

    def repair(self):
        """The model's repair report (:meth:`ambots.repair.RepairReport.as_dict`;
        ``path``: the repaired mesh in the job folder once :func:`write_job`
        wrote it), or None when the model was not loaded with repair."""
        report = (self.mesh.metadata or {}).get("ambots_repair") if self.mesh is not None else None
        if report is None:
            return None
        out = report.as_dict()
        out["notes"] = list(self.mesh.metadata.get("ambots_repairs", [])) + list(report.notes)
        out["path"] = self.repaired_path
        return out

    def _built(self):
        """The chosen :class:`Candidate` when :attr:`programs` are its
        programs (its timing and events describe them), else None."""
        chosen = self.chosen
        return chosen if chosen is not None and chosen.programs is self.programs else None

    def _figures(self):
        """{arm name: (summary, extrusion paths)} of the chosen plan's
        programs when a worker process sent it (:attr:`Candidate.figures`),
        else {}."""
        built = self._built()
        return (built.figures if built is not None else None) or {}

    def events(self):
        """{arm name: G-code events of its program}: the parse that timed the
        chosen plan, else parsed now (once: kept)."""
        built = self._built()
        kept = (built.events if built is not None else None) or {}
        if built is not None:
            built.events = kept
        for n in self.programs:
            if n not in kept:
                kept[n] = self.programs[n].parse()
        return kept

    def overhang(self):
        """Extrusion with nothing under it in all the programs together
        (:func:`ambots.overhang.unsupported_extrusion`, the bead width of the
        slice settings), plus ``support``: whether the slicer was asked for
        support (None if it does not say).  Computed once per job."""
        if getattr(self, "_overhang", None) is None:
            from ambots.overhang import unsupported_extrusion
            from ambots.slicer import SliceSettings
            settings = self.settings or SliceSettings()
            figures = self._figures()
            if all(n in figures for n in self.programs):    # sent by a worker: its paths, not its events
                programs, paths = (), [p for n in self.programs for p in figures[n][1]]
            else:
                programs, paths = self.events().values(), None
            out = unsupported_extrusion(programs, bead_width_mm=settings.bead_width_mm,
                                        layer_height_mm=settings.layer_height_mm, paths=paths)
            out["support"] = getattr(settings, "support", None)
            self._overhang = out
        return self._overhang


def unsupported_line(overhang):
    """One line for people: the unsupported share of the extruded length."""
    return "unsupported: %.2f %% of %.0f mm extruded (%.0f mm; nothing of the layer below within %g mm, " \
           "bridges up to %g mm allowed)" % (100.0 * overhang["unsupported_share"], overhang["extruded_mm"],
                                            overhang["unsupported_mm"], overhang["bead_width_mm"],
                                            overhang["bridge_max_mm"])


def overhang_lines(overhang):
    """Warnings for people about extrusion in mid-air (``job.json``'s
    "overhang", :meth:`Job.overhang`): none when everything is supported."""
    from ambots.overhang import layer_ranges
    if not overhang or not overhang.get("unsupported_mm"):
        return []
    layers = overhang["unsupported_layers"]
    z = [l["z_mm"] for l in layers]
    where = "layer%s %s (z %s mm)" % ("" if len(layers) == 1 else "s", layer_ranges(l["layer"] for l in layers),
                                      "%.2f" % z[0] if len(z) == 1 else "%.2f-%.2f" % (min(z), max(z)))
    support = overhang.get("support")
    why = {False: "support is off (--support on adds it)", True: "support did not reach it"}.get(support, "")
    return ["warning: %.2f %% of the extruded length (%.1f mm) has nothing under it within one bead width "
            "(bridges up to %g mm allowed), on %s%s" % (
                100.0 * overhang["unsupported_share"], overhang["unsupported_mm"], overhang["bridge_max_mm"], where,
                "; " + why if why else "")]


def arm_time_columns(arm):
    """An arm's ``busy s`` and ``done s`` columns (8 wide each) of the slice
    summaries (job.json's ``arms.<name>``): the one timing law's seconds the
    arm moves and when it is done on the plan's clock, the same law as the
    plan's makespan; "-" where the plan could not be timed."""
    return " ".join("%8s" % ("-" if arm.get(k) is None else "{:,.0f}".format(arm[k])) for k in ("busy_s", "done_s"))


def _how(arms, how, turn_deg=0.0, steps=None):
    if len(arms) == 1:
        return "%s alone" % arms[0]
    turn = ", seam%s turned %+g deg" % ("" if len(arms) == 2 else "s", turn_deg) if turn_deg else ""
    if steps:
        turn += ", seam stepped per layer (%+.1f to %+.1f mm)" % tuple(steps)
    return "%d arms %s%s (%s)" % (len(arms), how, turn, ", ".join(arms))


def plan_lines(plan, brief=False):
    """What the planner chose, for people (the menu's slice summary, ``slice``,
    ``plan`` and, ``brief``: two lines, the run summaries): ``plan`` as
    :meth:`Job.plan_summary` gives it (job.json's "plan")."""
    if not plan or not plan.get("candidates"):
        return []
    chosen, rest = plan["candidates"][0], plan["candidates"][1:]
    fmt = lambda t: "not timed" if t is None else "%s s" % format(round(t), ",")
    # job.json before session 30 has no turn, before session 31 no steps
    how = lambda c: _how(c["arms"], c["how"], c.get("seam_turn_deg") or 0.0, c.get("seam_steps_mm"))  # noqa: E731
    head = "plan: %s: %s" % (how(chosen), fmt(chosen["makespan_s"]))
    if plan.get("forced"):
        head += (" (sequential mode: the arms in turn, no other plan considered)" if chosen["how"] == "sequential"
                 else " (arms given: no other plan considered)")
    lines = [head]
    singles = [c for c in plan["candidates"] if len(c["arms"]) == 1 and c["makespan_s"] is not None]
    if len(chosen["arms"]) > 1 and singles:
        best = min(singles, key=lambda c: c["makespan_s"])
        lines[0] += "; best single arm (%s): %s; speed-up %.2fx" % (
            best["arms"][0], fmt(best["makespan_s"]), best["makespan_s"] / chosen["makespan_s"])
    if brief:
        if rest:
            lines.append("  also considered: " + "; ".join(
                "%s %s%s" % (how(c), fmt(c["makespan_s"]), " (%s)" % c["note"] if c.get("note") else "") for c in rest))
        return lines
    for c in rest:
        why = " (%s)" % c["note"] if c.get("note") else ""
        lines.append("  also considered: %s: %s%s" % (how(c), fmt(c["makespan_s"]), why))
    if rest:
        lines.append("  (makespans by the one timing law, ambots.estimate; fewer arms unless more are "
                     "faster by more than %d %%)" % round(100 * TIE_SHARE))
    return lines


class DoesNotFit(MeshError):
    """A model larger than the cell's bed or printable height.  The message
    says which shipped cells would take it and the largest ``--scale``
    that fits this cell (:attr:`scale_to_fit`, relative to the file)."""

    def __init__(self, message, scale_to_fit):
        super().__init__(message)
        self.scale_to_fit = scale_to_fit


def prepare_model(path, cell, scale=1.0, crossings=True):
    """Step 1: read, repair and check the model; centre it on the bed (bed
    frame, mm) and refuse it if it does not fit the bed
    (:class:`DoesNotFit`, with advice).  ``crossings`` False: without the
    search for a surface crossing itself (:func:`ambots.mesh.load_model`)."""
    from ambots.mesh import check_fits, load_model, place_on_bed
    mesh = place_on_bed(load_model(path, scale=scale, crossings=crossings))
    try:
        check_fits(mesh, m_to_mm(cell.bed.size[:2]), m_to_mm(cell.bed.max_height))
    except MeshError as exc:
        fit = scale * _largest_scale(mesh.extents, cell)
        fit = math.floor(fit * 1000.0) / 1000.0          # rounded down: it must still fit
        others = [c for c in shipped_cells() if c.path != cell.path and _largest_scale(mesh.extents, c) >= 1.0]
        advice = []
        if others:
            advice.append("it fits " + " and ".join("cell %s (--cell %s)" % (
                c.name, os.path.relpath(c.path, data_path())) for c in others))
        advice.append("cell %s takes it at --scale %g" % (cell.name, fit) if fit > 0 else
                      "no scale makes it fit cell %s" % cell.name)
        raise DoesNotFit("%s; %s" % (exc, "; ".join(advice)), fit) from None
    return mesh


def _largest_scale(size_mm, cell):
    """The largest factor by which a model of extents ``size_mm`` still fits
    ``cell``'s bed and printable height (> 1: it fits as it is)."""
    limits = (m_to_mm(cell.bed.size[0]), m_to_mm(cell.bed.size[1]), m_to_mm(cell.bed.max_height))
    return min(lim / s for lim, s in zip(limits, size_mm) if s > 0)


def shipped_cells():
    """The cells in ``config/cells`` (loaded; one that fails to load is skipped)."""
    from ambots.config import load_cell
    out = []
    for path in sorted(glob.glob(data_path("config", "cells", "*.yaml"))):
        try:
            out.append(load_cell(path))
        except ConfigError:
            continue
    return out


def split(mesh, cell, arms, seam="straight", settings=None, reach=None, pace=None, turn_deg=0.0, offsets=None):
    """Step 2: one part per arm, balanced, each inside its arm's reach
    (``reach``: a dict shared by the splits of one mesh, see
    :func:`ambots.partition.partition`'s ``reach_cache``; ``pace``: its
    arms' relative speeds, see there; ``turn_deg``: the seams turned by
    this many degrees, counter-clockwise, there ``turn``; ``offsets``: two
    arms' seam stepped by this much (mm) on each layer,
    :func:`ambots.seam_steps.stepped_parts`, each part checked for reach again)."""
    from ambots.mesh import to_manifold
    from ambots.partition import PrintEstimate, check_part_reach, partition
    from ambots.slicer import SliceSettings, layer_heights
    s = settings or SliceSettings()
    est = PrintEstimate(s.bead_width_mm, s.layer_height_mm, s.perimeters, s.infill_density)
    model = to_manifold(mesh)
    # an interlocking seam's slabs are the slicer's layers
    layers = layer_heights(float(model.bounding_box()[5]), s)
    parts = partition(model, cell, arms, seam=seam, est=est, reach_cache=reach, layers=layers, pace=pace,
                      turn=math.radians(turn_deg))
    if offsets is not None:
        from ambots.seam_steps import stepped_parts
        parts = stepped_parts(model, parts, offsets, *layers)
        for part in parts:
            check_part_reach(cell, part, reach)
    return parts


def slice_parts(parts, slicer="builtin", settings=None, whole=None, seam="straight", clip=True):
    """Step 3: G-code text per arm name.  ``whole``: the placed model the
    parts were cut from (trimesh, mm, or a :class:`ambots.slicer.WholeModel`
    of it).  With the built-in slicer and a straight seam, each part's
    G-code is the whole model's toolpaths clipped to the part's prism
    (:mod:`ambots.seam_clip`): no walls on the seam faces, the lines a single
    arm would print there.  Otherwise (an interlocking seam, or ``clip``
    False) each part is
    sliced on its own, and the built-in slicer finds the overhangs on the
    whole model and prints each part's support inside that part's prism
    (``Part.planes``), so every arm prints the support under its own part
    and a cut makes no overhang.  The prusa back end supports each part on
    its own (it cannot take the whole model)."""
    from ambots.seam_clip import prisms
    from ambots.seams import seam_kind
    from ambots.slicer import SliceSettings, WholeModel, slice_mesh
    if slicer != "builtin" or whole is None or len(parts) < 2:
        return {p.arm.name: slice_mesh(p.to_trimesh(), settings, backend=slicer) for p in parts if not p.empty}
    s = settings or SliceSettings()
    if not isinstance(whole, WholeModel) or whole.settings != s:
        whole = WholeModel(whole.mesh if isinstance(whole, WholeModel) else whole, s)   # sliced once for the parts
    prism = prisms(parts) if clip and seam_kind(seam) == "straight" else None
    if prism is not None:                # each arm's part clipped side by side (:mod:`ambots.parallel`)
        from ambots.parallel import fork_map
        whole.toolpaths()                # once, before the fork
        names = [p.arm.name for p in parts if not p.empty]
        return dict(zip(names, fork_map(lambda n: whole.clipped(prism[n]), names)))
    return {p.arm.name: slice_mesh(p.to_trimesh(), settings, backend=slicer, whole=whole, keep=p.planes or None)
            for p in parts if not p.empty}


def coordinate(sliced, parts, cell, mode="concurrent", idle=(), **kw):
    """Step 4: per-arm programs with A-series coordination (``idle``: the
    cell's arms without work, parked first by a one-arm job).  ``sliced``:
    {arm name: G-code text, or that text read once
    (:func:`ambots.coordinate.read_sliced`)}."""
    from ambots.coordinate import build_programs
    parts = [p for p in parts if p.arm.name in sliced]
    return build_programs(sliced, parts, cell, mode=mode, idle=idle, **kw)


#: more arms are chosen only when their plan is faster than the fewer arms' by
#: more than this share (the estimate's spread against the simulation: 1-2 %)
TIE_SHARE = 0.03


def _timed(programs, cell):
    """Makespan of programs by the one timing law (s), or None and why not,
    the programs' events ({arm name: events}, None if not parsed) and each
    arm's times on the one clock (:attr:`Candidate.timeline`): each
    program is parsed once (the emitter's programs: not at all, see
    :meth:`ambots.coordinate.ArmProgram.parse`), for the timing and later
    the chosen plan's figures (:meth:`Job.summary`)."""
    from ambots.estimate import estimate_programs
    try:
        events = {n: p.parse() for n, p in programs.items()}
        est = estimate_programs(programs, cell, events=events)
    except AmbotsError as exc:
        return None, str(exc), None, None
    if est["errors"]:
        return None, "; ".join(est["errors"].values()), events, None
    return est["makespan_s"], None, events, {
        n: {"start_s": a["start_s"], "busy_s": a["busy_s"], "idle_s": a["idle_s"], "done_s": a["finish_s"],
            "layer_busy_s": a["layer_busy_s"]}
        for n, a in est["arms"].items()}


def _plan(parts, sliced, programs, arms, how, cell, turn_deg=0.0, offsets=None, pace=None):
    """A plan's (parts, sliced, programs, Candidate), timed; ``turn_deg``,
    ``offsets``, ``pace``: how its parts were split (:func:`split`)."""
    t, why, events, timeline = _timed(programs, cell)
    return parts, sliced, programs, Candidate(arms, how, t, why, programs, events, timeline, turn_deg, offsets, pace)


#: a plan of several arms that is faster than each arm alone is split again
#: (once) when its arms' busy times differ by more than this share, each
#: arm's pace (:func:`ambots.partition.partition`) its busy time over their
#: mean: the split's estimate sees the volume, not the arm's speed or what
#: its part's program costs (on the demo the Kinova's half took 1.1 % longer
#: than the UR10's; the Kinova alone takes 1.7 % longer)
REBALANCE_SHARE = 0.004
#: ... each arm's pace rounded to this many decimals: the busy times carry
#: noise in their last bits (numpy's vector loops depend on where the arrays
#: lie in memory), and the seam the split finds from them moved by as
#: little, which the slicing and the bands then turned into different
#: programs: the demo's plan was one of three (5,098.1, 5,098.5 or
#: 5,100.0 s) from one run to the next in one process (a pace to 1e-6
#: moves a 240 mm seam by at most 0.2 um)
PACE_DIGITS = 6


def _pays(plan, timed):
    """Whether ``plan`` (parts, sliced, programs, Candidate) is faster than
    each arm alone (``timed``: their makespans, s)."""
    return bool(timed) and plan[3].makespan_s is not None and plan[3].makespan_s < min(timed)


def _pace_of(plan, arms, timed):
    """Each arm's pace ({name: busy / mean busy}) to split ``plan`` of
    ``arms`` again by, or None: only when cooperating pays (``timed``: each
    arm alone, s) and the busy times differ by more than
    :data:`REBALANCE_SHARE`."""
    busy = plan[3].busy_s
    if not (_pays(plan, timed) and busy and len(busy) == len(arms)
            and max(busy.values()) > (1.0 + REBALANCE_SHARE) * min(busy.values())):
        return None
    mean = sum(busy.values()) / len(busy)
    return {n: round(b / mean, PACE_DIGITS) for n, b in busy.items()}


def _rebalanced(job, cell, arms, seam, settings, reach, slicer, whole, mode, idle, plan, timed):
    """``plan`` of ``arms`` together, or the same arms split again with each
    arm's share sized by how long its part took (:func:`_pace_of`), when
    that is faster.  Returns (the plan, the pace tried or None)."""
    pace = _pace_of(plan, arms, timed)
    if pace is not None:
        again = _cooperative(job, cell, arms, seam, settings, reach, pace, slicer, whole, mode, idle)
        if again[3].makespan_s is not None and again[3].makespan_s < plan[3].makespan_s:
            plan = again
    return plan, pace


#: a cell of three or four arms also makes the plan of every smaller group of
#: two or more of its arms together, the others parked (:func:`_group_plans`):
#: in the four-arm cell the demo block takes 7,909 s on all four arms, whose
#: zones cover its 40 mm width, and 5,280 s on two of them (session 33).  A
#: larger cell (the eight-arm beam: 246 groups) does not
GROUPS_MAX_ARMS = 4


def _groups(arms):
    """The groups of two or more of ``arms``, fewer than all, in the cell's
    order, the smallest first (none for fewer than three arms or more than
    :data:`GROUPS_MAX_ARMS`)."""
    import itertools
    if not 3 <= len(arms) <= GROUPS_MAX_ARMS:
        return []
    return [list(g) for k in range(2, len(arms)) for g in itertools.combinations(arms, k)]


#: a group's plan is first made with the arms' shares by volume; those within
#: this share of the fastest plan so far are then split again by pace
#: (:func:`_rebalanced`), which gained 0.5-1.1 % on two arms (the demo block)
GROUP_AGAIN_SHARE = 0.05


def _group_plans(job, cell, arms, seam, settings, reach, slicer, whole, mode, idle, timed, known):
    """The plan of each smaller group of ``arms`` together (:func:`_groups`;
    the cell's other arms parked first, as for an arm alone), made side by
    side (:func:`ambots.parallel.fork_map`), each arm's share by volume
    (:func:`_cooperative`); those within :data:`GROUP_AGAIN_SHARE` of the
    fastest plan so far are then split again by pace (:func:`_rebalanced`),
    as the plan of all.
    Returns ([(None, sliced, programs, Candidate)], without parts (cut again
    if chosen, :func:`_to_send`), {group (arm names): the pace its split
    again was (or would have been) made with, or None}).  ``timed``: each
    arm alone, s; ``known``: the makespans of
    the plans made so far.  A plan slower than the fastest by more than
    :data:`TIE_SHARE` cannot be chosen: it comes back timed, without
    programs.  One that cannot be made (a part out of an arm's reach) is a
    plan not timed, with the reason as its note."""
    from ambots.parallel import fork_map
    groups = _groups(arms)
    best = min([t for t in list(timed) + list(known) if t] or [math.inf])

    def build(spec):                     # (the plan as sent, the pace to split it again by)
        group, pace, bar = spec
        names = [a.name for a in group]
        rest = idle + [a for a in arms if a.name not in names]
        try:
            plan = _cooperative(job, cell, group, seam, settings, reach, pace, slicer, whole, mode, rest)
        except AmbotsError as exc:       # a part out of an arm's reach, an arm that cannot reach a move
            return (None, None, Candidate(names, mode, None, str(exc))), None
        c, again = plan[3], _pace_of(plan, group, timed) if pace is None else None
        return _to_send(plan, c.makespan_s is not None and c.makespan_s <= bar), again

    first = fork_map(build, [(g, None, best * (1.0 + GROUP_AGAIN_SHARE)) for g in groups])
    made, paces = [m for m, _ in first], [p for _, p in first]
    best = min([best] + [m[2].makespan_s for m in made if m[2].makespan_s])
    near = best * (1.0 + GROUP_AGAIN_SHARE)
    again = [i for i, m in enumerate(made) if paces[i] is not None and m[2].makespan_s <= near]
    for i, (m, _) in zip(again, fork_map(build, [(groups[i], paces[i], best * (1.0 + TIE_SHARE)) for i in again])):
        if m[2].makespan_s is not None and m[2].makespan_s < made[i][2].makespan_s:
            made[i] = m
    best = min([best] + [m[2].makespan_s for m in made if m[2].makespan_s])
    # one slower than the fastest by more than the tie share cannot be chosen: timed, without programs
    return ([_received_plan(m if m[2].makespan_s is not None and m[2].makespan_s <= best * (1.0 + TIE_SHARE)
                            else _to_send((None,) + m, False), cell) for m in made],
            {tuple(a.name for a in g): p for g, p in zip(groups, paces)})


def _to_send(plan, keep=True):
    """A plan (parts, sliced, programs, Candidate) made in a worker process
    (:mod:`ambots.parallel`), as it is sent back: (sliced, as :class:`_Text`,
    programs, Candidate), without parts (a manifold cannot be pickled: the
    chosen plan's are cut again, :func:`split`); without sliced G-code and
    programs, (None, None, Candidate), when it cannot be chosen (``keep``
    False) or has none."""
    _, sliced, programs, c = plan
    if not keep or programs is None:
        return None, None, replace(c, programs=None, events=None)
    return {n: _Text(t) for n, t in sliced.items()}, programs, c


def _received_plan(sent, cell):
    """:func:`_to_send`'s plan as received: (None, sliced, programs, Candidate),
    its programs with the cell's own arm objects again."""
    sliced, programs, c = sent
    if programs is None:
        return None, None, None, c
    c.programs = _own_arms(programs, cell)
    return None, {n: t.text for n, t in sliced.items()}, programs, c


def _cooperative(job, cell, arms, seam, settings, reach, pace, slicer, whole, mode, idle, turn_deg=0.0,
                 zone_floor=None, offsets=None):
    """The plan of ``arms`` together: (parts, sliced, programs, Candidate);
    ``turn_deg``: the seams turned, ``offsets``: stepped (:func:`split`);
    ``zone_floor`` (mm): the least seam zone of its pair (two arms)."""
    parts = split(job.mesh, cell, arms, seam, settings, reach, pace, turn_deg, offsets)
    sliced = slice_parts(parts, slicer, settings, whole or job.mesh, seam)
    zone = None
    if zone_floor is not None:
        from ambots.coordinate import seam_zones_for
        from ambots.seam_steps import extremes
        # a stepped seam: the zone of its two extremes (every layer's seam lies between them)
        zone = max([zone_floor] + [z for ps in ([parts] if offsets is None else [parts] + extremes(parts))
                                   for z in seam_zones_for(cell, arms, ps).values()])
    programs = coordinate(sliced, parts, cell, mode, idle=idle, zone_mm=zone)
    plan = _plan(parts, sliced, programs, [a.name for a in arms], mode, cell, turn_deg, offsets, pace)
    return _fastest_schedule(plan, cell, mode, idle)


#: a plan of two arms that beats each arm alone is also made with the seam
#: turned by each of these angles (degrees, counter-clockwise, about the
#: model's centre; :func:`ambots.partition.partition`'s ``turn``), and the
#: fastest plan is chosen: the seam perpendicular to the line between the
#: arms can run along a bar of the part, all of it within the seam zone,
#: where the arms take turns (session 30: an L, a cross, a ring and a plate gain
#: 1-24 %, the demo, a ramp and a hex plate keep the straight seam:
#: ``bench_cooperation``, docs/benchmarks.md).  Turned further, an arm's
#: base comes near its seam plane, and the arms reach past each other
#: along the seam
SEAM_TURNS_DEG = (30.0, -30.0)


#: a plan with the seam turned or stepped is chosen over the straight one only
#: when faster by more than this share: closer, the estimate cannot tell them
#: apart (session 31, the demo: stepped 5,097 s against 5,098 s estimated,
#: 5,182 s against 5,180 s simulated)
VARIANT_SHARE = 0.002


def _seam_plans(job, cell, arms, seam, settings, reach, pace, slicer, whole, mode, idle, straight):
    """The plans of two ``arms`` together with the seam turned by each of
    :data:`SEAM_TURNS_DEG` and, where the layers' work lies unevenly about
    the straight seam, stepped per layer (:mod:`ambots.seam_steps`, from the
    ``straight`` plan's time on each layer: :func:`_stepped_offsets`);
    ``pace``: each arm's, from the ``straight`` plan, or None, for the
    turned seams (the stepped seam's parts are the straight plan's, split
    with its own pace).  Made side by
    side (:func:`ambots.parallel.fork_map`): [(None, sliced, programs,
    Candidate)], without parts (a manifold cannot be pickled: the chosen
    one's are cut again, :func:`split`), and without programs for one no
    faster than the straight plan by more than :data:`VARIANT_SHARE` (it
    cannot be chosen; a note says so when it is faster by less).  One that cannot be
    made (a part out of an arm's reach: an
    :class:`~ambots.errors.AmbotsError`) is a plan that is not timed, with
    the reason as its note.  Each keeps at least the seam zone of the straight
    plan's parts: the zone of a turned seam comes from the clearance of
    sampled poses (the arms no longer face each other across it,
    :func:`ambots.collision.seam_zones_mm`), and turned by 90 deg those gave
    the 10 mm margin where the arms met (session 30); a stepped seam's grows
    by its largest step (:func:`ambots.coordinate.build_programs`)."""
    from ambots.coordinate import seam_zones_for
    from ambots.parallel import fork_map
    floor = max(seam_zones_for(cell, arms, straight[0]).values())
    beat = straight[3].makespan_s * (1.0 - VARIANT_SHARE)
    specs = [(deg, None, pace) for deg in SEAM_TURNS_DEG]
    offsets = _stepped_offsets(straight, whole, seam, floor)
    if offsets is not None:
        specs.append((0.0, offsets, straight[3].pace))

    def variant(spec):
        deg, steps, rates = spec
        try:
            _, sliced, programs, c = _cooperative(job, cell, arms, seam, settings, reach, rates, slicer, whole,
                                                  mode, idle, deg, floor, steps)
        except AmbotsError as exc:       # a part out of an arm's reach, an arm that cannot reach a move
            return None, None, Candidate([a.name for a in arms], mode, None, str(exc), seam_turn_deg=deg,
                                         seam_offsets=steps)
        if c.makespan_s is not None and beat <= c.makespan_s < straight[3].makespan_s:
            c = replace(c, note="within %g %% of the plan with the seam straight, which is kept"
                        % (100 * VARIANT_SHARE))
        return _to_send((None, sliced, programs, c), c.makespan_s is not None and c.makespan_s < beat)

    return [_received_plan(sent, cell) for sent in fork_map(variant, specs)]


def _stepped_offsets(straight, whole, seam, zone):
    """The per-layer offsets of a stepped seam (:func:`ambots.seam_steps.
    plan_offsets`) from the ``straight`` plan of two arms, each layer shared
    only where it reaches half the ``zone`` (mm) past the seam on both
    sides (a layer narrower than the zone about its seam is printed in
    turns, no faster); None without the built-in slicer's whole model, with
    another seam kind, or when the seam would hardly move."""
    from ambots.seam_steps import plan_offsets
    from ambots.seams import seam_kind
    parts, sliced, _, c = straight
    if whole is None or seam_kind(seam) != "straight" or c.timeline is None or parts is None:
        return None
    busy = {n: a.get("layer_busy_s") for n, a in c.timeline.items()}
    if any(b is None for b in busy.values()):
        return None
    return plan_offsets(parts, sliced, busy, whole.toolpaths(), zone / 2.0)


def _fastest_schedule(plan, cell, mode, idle):
    """A scheduled timeline's plan (three or more arms around a point) built
    with each of :data:`ambots.coordinate.CHUNK_BAND_CHOICES` chunk bands
    per seam, timed by the one timing law, the fastest kept (ties: the
    first built); any other plan as it is."""
    from ambots.coordinate import CHUNK_BAND_CHOICES, read_sliced
    parts, sliced, programs, candidate = plan
    bands = {p.chunk_bands for p in programs.values()}
    if None in bands or candidate.makespan_s is None:
        return plan
    from ambots.parallel import fork_map
    read = {n: read_sliced(t, "%s.gcode" % n) if isinstance(t, str) else t for n, t in sliced.items()}

    def build(b):                        # (programs, Candidate): no parts, which cannot be pickled
        return _plan(parts, sliced, coordinate(read, parts, cell, mode, idle=idle, chunk_bands=b),
                     candidate.arms, candidate.how, cell, candidate.seam_turn_deg, candidate.seam_offsets,
                     candidate.pace)[2:]

    best = plan
    for programs, other in fork_map(build, [b for b in CHUNK_BAND_CHOICES if b not in bands]):
        if other.makespan_s is not None and other.makespan_s < best[3].makespan_s:
            best = parts, sliced, _own_arms(programs, cell), other
    return best


def _own_arms(programs, cell):
    """``programs`` ({name: ArmProgram}, or None) with the cell's own arm
    objects again (a worker process sends back copies)."""
    for name, p in (programs or {}).items():
        p.arm = cell.arm(name)
    return programs


def _alone(mesh, cell, arm, text, idle, settings, read, reach=None):
    """The whole model by ``arm`` alone: (parts, sliced, programs, Candidate).
    ``read``: {} shared by the arms, where the model's G-code ``text`` is
    kept once read (:func:`ambots.coordinate.read_sliced`, on first use),
    and what the first arm's program wrote of it, which the others copy
    where theirs is the same (``written``: :class:`ambots.coordinate.emit.Emitter`);
    ``reach``: the job's reach checks, shared by its plans."""
    from ambots.coordinate import read_sliced
    try:
        parts = split(mesh, cell, [arm], settings=settings, reach=reach)
    except AmbotsError as exc:
        return None, None, None, Candidate([arm.name], "alone", None, str(exc))
    if "gcode" not in read:
        read["gcode"] = read_sliced(text, "%s.gcode" % arm.name)
    programs = coordinate({arm.name: read["gcode"]}, parts, cell, "concurrent", idle=idle,
                          written=read.setdefault("written", []))
    return _plan(parts, {arm.name: text}, programs, [arm.name], "alone", cell)


def _alone_plans(mesh, cell, arms, gcode, settings, reach):
    """Each of ``arms`` alone (:func:`_alone`) on the whole model's G-code,
    read once, in the order of ``arms``, as sent back from a worker process
    (:func:`_to_send`), with programs and the G-code text only for the
    fastest (the only one of them that can be chosen, see :func:`_best`).
    ``gcode()`` returns that G-code (written once), sent back as
    :class:`_Text` (the job's process need not write it again: 0.36 s of
    the 100 mm sphere's 5.4 s)."""
    text = gcode()
    read = {}
    plans = [_alone(mesh, cell, arm, text, [a for a in cell.arms if a.name != arm.name], settings, read, reach)
             for arm in arms]
    best = _best([p[3] for p in plans])
    return [_to_send(p, i == best) for i, p in enumerate(plans)]


class _Text:
    """A G-code text a worker sends back (``.text``): pickled as the plain
    text, without the built-in slicer's reading of it
    (:class:`ambots.sliced.SlicedText`), which costs more to pickle than to
    parse; in one process (nothing pickled) the text as it was."""

    def __init__(self, text):
        self.text = text

    def __reduce__(self):
        return _Text, (str(self.text),)


@fewer_collections
def run_job(model_path, cell, arms=None, slicer="builtin", mode="concurrent", seam="straight",
            scale=1.0, settings=None, choose=None):
    """All four steps; returns the :class:`Job`.

    ``arms``: the arms to print with (default: all of the cell's).  With
    ``choose`` (default: when ``arms`` is not given, in concurrent mode) the planner also
    considers every arm alone, and in a cell of three or four arms every
    smaller group of them (:func:`_group_plans`): each plan is timed by the one timing law
    (:func:`ambots.estimate.estimate_programs`) and the fastest one is
    chosen, fewer arms unless more are faster by more than ``TIE_SHARE``.
    A plan of several arms that beats each arm alone is split once more with
    each arm's share sized by its busy time in the first (:data:`REBALANCE_SHARE`).
    Without it the given arms print together (``job.forced``).  The arms
    alone are planned in a worker process beside the plan together
    (:mod:`ambots.parallel`; ``AMBOTS_JOBS=1``: one after the other, here).

    The model's search for a surface crossing itself (0.35 s of a
    300,000-triangle model, on one core while the other waited) runs in a
    worker process too, beside the planning: the plans are made on the
    model as read and repaired otherwise; if the surface crosses itself,
    the model is loaded again with the search (the crossing repaired, or
    refused) and planned again.  xacro builds the arms' URDFs aside while
    the model is read (:func:`ambots.model.prefetch_urdfs`)."""
    from ambots.mesh import crosses_itself
    from ambots.parallel import Forked, workers
    if choose is None:                   # sequential mode is the original's way: the arms asked for, in turn
        choose = arms is None and mode == "concurrent"
    arms = list(cell.arms if arms is None else arms)
    args = (model_path, cell, arms, slicer, mode, seam, settings, choose)
    if workers() < 2:
        return _plan_job(prepare_model(model_path, cell, scale), *args)
    from ambots.model import prefetch_urdfs
    keep_urdfs, drop_urdfs = prefetch_urdfs([a.profile for a in cell.arms])     # xacro aside, while reading
    try:
        mesh = prepare_model(model_path, cell, scale, crossings=False)
    except Exception:                    # refused: the error the search would have given first, if any
        mesh = None
    except BaseException:
        drop_urdfs()
        raise
    try:
        keep_urdfs()
    except Exception:                    # xacro's error: raised where the kinematics are built, as before
        pass
    if mesh is None:
        return _plan_job(prepare_model(model_path, cell, scale), *args)
    before = hash(mesh)
    check = Forked(lambda: crosses_itself(mesh))
    try:
        job = _plan_job(mesh, *args)
    except Exception:
        if check.result():               # the crossing may be why: as without the search aside
            return _plan_job(prepare_model(model_path, cell, scale), *args)
        raise
    except BaseException:
        check.cancel()
        raise
    if check.result():
        return _plan_job(prepare_model(model_path, cell, scale), *args)
    if hash(mesh) == before:             # found clean, as the search in the load marks it
        from ambots.mesh import UNCROSSED_KEY
        mesh.metadata[UNCROSSED_KEY] = before
    return job


def _plan_job(mesh, model_path, cell, arms, slicer, mode, seam, settings, choose):
    """:func:`run_job` on the prepared model ``mesh``."""
    job = Job(model_path, cell, arms, slicer, mode, seam, forced=not choose, settings=settings)
    job.mesh = mesh
    idle = [a for a in cell.arms if a.name not in {b.name for b in arms}]
    plans = []
    reach = {}                           # the reach checks of this mesh, shared by the plans
    whole = None
    if slicer == "builtin":              # the whole model sliced once for the parts and the arms alone
        from ambots.slicer import SliceSettings, WholeModel
        whole = WholeModel(job.mesh, settings or SliceSettings())
    background = None
    if len(arms) > 1 and choose:         # each arm alone, on the same G-code of the whole model, beside the plan together
        from ambots.kinematics import shared_arm_kinematics
        from ambots.parallel import Forked
        from ambots.slicer import slice_mesh
        for arm in arms:                 # built once, before the fork (xacro: 0.15 s an arm), for both processes
            shared_arm_kinematics(arm)
        if whole is not None:
            whole.toolpaths()            # made once, before the fork: the plans of both processes clip it
        # the whole model's G-code: the built-in slicer's written when asked (once), another's now
        gcode = whole.text if whole is not None else (lambda t=slice_mesh(job.mesh, settings, backend=slicer): t)
        background = Forked(lambda: _alone_plans(job.mesh, cell, arms, gcode, settings, reach))
    if len(arms) > 1:
        try:
            plan = _cooperative(job, cell, arms, seam, settings, reach, None, slicer, whole, mode, idle)
        except BaseException:
            if background is not None:
                background.cancel()
            raise
        alone = [_received_plan(p, cell) for p in background.result()] if background else []
        timed = [p[3].makespan_s for p in alone if p[3].makespan_s]
        plan, pace = _rebalanced(job, cell, arms, seam, settings, reach, slicer, whole, mode, idle, plan, timed)
        plans.append(plan)
        tried = {tuple(a.name for a in arms): pace}       # each plan's pace split again by (or None)
        if choose:
            groups, paces = _group_plans(job, cell, arms, seam, settings, reach, slicer, whole, mode, idle, timed,
                                         [plan[3].makespan_s])
            plans += groups
            tried.update(paces)
        pairs = [p for p in plans if len(p[3].arms) == 2 and p[2] is not None and _pays(p, timed)]
        if pairs and not is_beam(cell):  # the fastest plan of two arms that pays, with its seam turned or stepped
            pair = min(pairs, key=lambda p: p[3].makespan_s)
            group = [cell.arm(n) for n in pair[3].arms]
            # the turned seams split with the pace its busy times gave, whether or not that split was kept
            rates = tried.get(tuple(pair[3].arms))
            rest = idle + [a for a in arms if a.name not in pair[3].arms]
            if pair[0] is None:          # made in a worker: its parts cut again (the stepped seam needs them)
                c = pair[3]
                pair = (split(job.mesh, cell, group, seam, settings, reach, c.pace),) + tuple(pair[1:])
            plans += _seam_plans(job, cell, group, seam, settings, reach, rates, slicer, whole, mode, rest, pair)
        plans += alone
    if len(arms) == 1:                   # one arm: its plan (an arm that cannot reach the model is an error)
        parts = split(job.mesh, cell, arms, seam, settings)
        sliced = slice_parts(parts, slicer, settings, job.mesh)
        programs = coordinate(sliced, parts, cell, mode, idle=idle)
        plans.append(_plan(parts, sliced, programs, [arms[0].name], "alone", cell))
    best = _best([p[3] for p in plans]) if choose else 0
    if best is None:                     # nothing could be timed: the arms asked for, as before
        best = 0
    if plans[best][0] is None and plans[best][2] is not None:     # planned in a worker: its parts cut again
        c = plans[best][3]
        group = [cell.arm(n) for n in c.arms]
        parts = (split(job.mesh, cell, group, settings=settings, reach=reach) if len(c.arms) == 1
                 else split(job.mesh, cell, group, seam, settings, reach, c.pace, c.seam_turn_deg, c.seam_offsets))
        plans[best] = (parts,) + tuple(plans[best][1:])
    job.parts, job.sliced, job.programs = plans[best][0], plans[best][1], plans[best][2]
    if plans[best][3].arms != [a.name for a in arms]:
        job.arms = [cell.arm(n) for n in plans[best][3].arms]
    job.candidates = [plans[best][3]] + [p[3] for i, p in enumerate(plans) if i != best]
    return job


def _best(candidates):
    """Index of the fastest candidate; fewer arms win unless more are faster
    by more than TIE_SHARE.  None if none could be timed.  A candidate
    without programs (a seam plan not kept, :func:`_seam_plans`) is not chosen."""
    timed = [(i, c) for i, c in enumerate(candidates) if c.makespan_s is not None and c.programs is not None]
    if not timed:
        return None
    fastest = min(c.makespan_s for _, c in timed)
    # among the plans within the tie share of the fastest, the one with fewest arms
    close = [(len(c.arms), c.makespan_s, i) for i, c in timed if c.makespan_s <= fastest * (1.0 + TIE_SHARE)]
    return min(close)[2]


#: file name of the repaired model in the job folder (bed frame, mm)
REPAIRED_MESH = "model_repaired.stl"


@fewer_collections
def write_job(job, out_dir):
    """Write ``<arm>.gcode`` (program), ``<arm>.stl`` (part) per arm,
    :data:`REPAIRED_MESH` when the model was repaired (holes closed or
    shells merged; the mesh as placed on the bed, mm) and ``job.json``
    (summary, its ``"repair"`` the repair report) into ``out_dir``;
    returns the summary."""
    os.makedirs(out_dir, exist_ok=True)
    repaired = os.path.join(out_dir, REPAIRED_MESH)
    report = (job.mesh.metadata or {}).get("ambots_repair") if job.mesh is not None else None
    if report is not None and report.changed:
        job.mesh.export(repaired)
        job.repaired_path = REPAIRED_MESH
    elif os.path.exists(repaired):       # an earlier job's repair: not this model's
        os.remove(repaired)
    for arm in job.cell.arms:            # an earlier job's program of an arm without work now: gone
        if arm.name not in job.programs:
            for ext in (".gcode", ".stl"):
                if os.path.exists(os.path.join(out_dir, arm.name + ext)):
                    os.remove(os.path.join(out_dir, arm.name + ext))
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
