"""``report.json``: one builder for the offline run (``python -m ambots plan``,
:func:`ambots.sim.report`) and the live one (the capture node), so both say
the same things with the same keys.

Inputs are plain data: per arm its :class:`~ambots.runner.RunStats` as a
dict (the runner's own offline, the firmware's ``~stats`` topic live), the
contact check of :func:`ambots.sim.check_traces`, and the job's metadata.
Units in the report: mm, mm3, s.
"""

__all__ = ["arm_entry", "makespan_s", "build"]


def _r(v, digits=3):
    return None if v is None else round(float(v), digits)


def _mm(metres):
    return None if metres is None else round(float(metres) * 1000.0, 3)


def arm_entry(arm_id, state, stats, beads, filament_mm=None, error=None):
    """One arm's entry: ``stats`` a RunStats dict (may be empty before the
    firmware's first stats), ``beads`` deposited, ``filament_mm`` pushed
    (offline only), ``error`` the last error text (live: from the hub)."""
    s = stats or {}
    return {"id": arm_id, "state": state, "moves": s.get("moves"),
            "extrude_mm": _mm(s.get("extrude_m")), "travel_mm": _mm(s.get("travel_m")),
            "print_time_s": _r(s.get("print_time_s")), "idle_time_s": _r(s.get("idle_time_s")),
            "ik_failures": s.get("ik_failures"), "max_path_error_mm": _r(s.get("max_path_error_mm"), 5),
            "filament_mm": _r(filament_mm), "beads": int(beads),
            "done_at_s": _r(s.get("done_s")), "planned_blocks": dict(s.get("plans") or {}), "error": error}


def makespan_s(stats, clocks=None):
    """From the first motion of any arm to the last arm done (an arm not done
    counts until its clock in ``clocks``, if given), s; None before any motion."""
    starts = [s["first_motion_s"] for s in stats.values() if s and s.get("first_motion_s") is not None]
    ends = []
    for name, s in stats.items():
        if not s or s.get("first_motion_s") is None:
            continue
        end = s.get("done_s")
        if end is None and clocks is not None:
            end = clocks.get(name)
        if end is not None:
            ends.append(end)
    return round(max(ends) - min(starts), 3) if starts and ends else None


def build(meta, finished, arms, makespan, motion, deposit_volume_mm3, model_volume_mm3, wall_time_s, **extra):
    """The report dictionary.  ``meta``: model, cell, mode, slicer; ``arms``:
    {name: :func:`arm_entry`}; ``motion``: :func:`ambots.sim.check_traces`'s
    dict, or None when nothing was checked; ``extra``: more keys (reason,
    errors, live figures, ...)."""
    out = dict(meta)
    out.update({"finished": bool(finished), "arms": arms, "makespan_s": makespan})
    if motion is None:
        out["collisions"] = None                  # not checked: no executed motion to check
    else:
        bounds = motion.get("bound_mm")
        out.update({
            "collisions": motion["collisions"],
            "min_clearance_mm": _r(motion["min_clearance_mm"], 2),
            "min_bed_clearance_mm": _r(motion["min_bed_clearance_mm"], 2),
            "min_part_clearance_mm": _r(motion["min_part_clearance_mm"], 2),
            "closest_pair": motion.get("closest_pair"), "closest_time_s": _r(motion.get("closest_time_s")),
            "clearance_bound_mm": None if bounds is None else {k: _r(v, 2) for k, v in bounds.items()},
            "collision_checks": motion.get("samples"), "check_resolution_mm": motion.get("resolution_mm")})
    out.update({"deposit_volume_mm3": _r(deposit_volume_mm3, 1), "model_volume_mm3": _r(model_volume_mm3, 1),
                "wall_time_s": _r(wall_time_s)})
    out.update(extra)
    return out
