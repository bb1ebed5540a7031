"""``python -m ambots info FILE.gcode [--json]``: what a G-code file holds."""
import json


def register(sub):
    p = sub.add_parser("info", help="summarize a G-code file (moves, filament, layers, bbox, time)",
                       description="Read a G-code file with the project's reader and print a summary "
                                   "(mm, mm/min, s).  A bad file exits with code 2 and names "
                                   "file:line.")
    p.add_argument("file", help="G-code file")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (keys documented in README, 'info --json')")
    p.add_argument("--arc-tolerance", type=_positive, default=None, metavar="MM",
                   help="largest chord-to-arc distance for G2/G3, mm (default 0.01)")
    p.add_argument("--bead-width", type=_positive, default=None, metavar="MM",
                   help="bead width of the unsupported-extrusion rule, mm (default 0.45): a point is "
                        "unsupported when nothing of the layer below lies within it")
    p.set_defaults(func=run)


def _positive(text):
    import argparse
    try:
        value = float(text)
    except ValueError:
        value = 0.0
    if not 0 < value < 1e6:
        raise argparse.ArgumentTypeError("must be a number > 0, not %r" % text)
    return value


def run(args):
    from ambots.gcode import DEFAULT_ARC_TOLERANCE_MM, read_gcode, summarize
    from ambots.overhang import DEFAULT_BEAD_WIDTH_MM, unsupported_extrusion

    tol = DEFAULT_ARC_TOLERANCE_MM if args.arc_tolerance is None else args.arc_tolerance
    events = list(read_gcode(args.file, tol))          # parsed once, for both
    s = {"file": str(args.file)}
    s.update(summarize(events))
    o = unsupported_extrusion([events], bead_width_mm=args.bead_width or DEFAULT_BEAD_WIDTH_MM)
    s.update({"unsupported_share": o["unsupported_share"], "unsupported_mm": o["unsupported_mm"],
              "bridged_mm": o["bridged_mm"], "unsupported_layers": o["unsupported_layers"]})
    if args.json:
        print(json.dumps(s, sort_keys=False))
        return 0
    print(format_summary(s))
    return 0


def _unsupported(s):
    if "unsupported_share" not in s:
        return "not measured"
    from ambots.overhang import DEFAULT_BRIDGE_MAX_MM, layer_ranges
    text = "%.2f %% of the extruded length (%.1f mm; nothing of the layer below within one bead width, " \
           "bridges up to %g mm allowed)" % (100.0 * s["unsupported_share"], s["unsupported_mm"],
                                            DEFAULT_BRIDGE_MAX_MM)
    if s["unsupported_layers"]:
        text += ", layers %s" % layer_ranges(l["layer"] for l in s["unsupported_layers"])
    return text


def format_summary(s, max_warnings=10):
    """Human-readable text of a :func:`ambots.gcode.summarize_file` dict."""
    t = int(round(s["print_time_s"]))
    bbox = s["bbox_mm"]
    lines = [
        s["file"],
        "  moves            %d (G0/G1/G2/G3), %d segments" % (s["moves"], s["segments"]),
        "  layers           %d" % s["layers"],
        "  filament         %.3f mm net (retractions subtracted; %.3f mm still retracted at end)"
        % (s["extruded_filament_mm"], s["retracted_at_end_mm"]),
        "  extrude path     %.3f mm" % s["extrude_path_mm"],
        "  travel path      %.3f mm" % s["travel_path_mm"],
        "  bbox (extruded)  %s" % ("none" if bbox is None else
                                   "[%.3f, %.3f, %.3f] .. [%.3f, %.3f, %.3f] mm" % tuple(bbox[0] + bbox[1])),
        "  print time       %dh %02dm %02ds at programmed feedrates (no acceleration)"
        % (t // 3600, t // 60 % 60, t % 60),
        "  other commands   %d passed through, of which %d A-series" % (s["commands"], s["a_commands"]),
        "  unsupported      %s" % _unsupported(s),
        "  warnings         %d" % len(s["warnings"]),
    ]
    for w in s["warnings"][:max_warnings]:
        lines.append("    line %s: %s" % (w["line"], w["message"]))
    if len(s["warnings"]) > max_warnings:
        lines.append("    ... (%d more; see --json)" % (len(s["warnings"]) - max_warnings))
    return "\n".join(lines)
