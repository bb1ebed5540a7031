"""Benchmark of the G-code reader (run by ``tests/bench/run.py``, or alone).

Writes a 1,000,000-line slicer-like G-code file to a temporary directory and
reads it (1) with :func:`ambots.gcode.read_gcode` (typed segments, all
checks) and (2) with the plain regular-expression loop of the original design
(``G0/G1 X.. Y.. Z.. E..`` per line, nothing else), in the same run.
Target: the reader does 1 M lines in <= 3 s on one core.
"""
import os
import random
import re
import tempfile
import time

from ambots.gcode import read_gcode, summarize

N_LINES = 1_000_000
TARGET_S = 3.0

_BASELINE_RE = re.compile(
    r"G[01](?:\s+X(?P<x>-?\d*\.?\d+))?(?:\s+Y(?P<y>-?\d*\.?\d+))?"
    r"(?:\s+Z(?P<z>-?\d*\.?\d+))?(?:\s+E(?P<e>-?\d*\.?\d+))?")


def write_file(path, n_lines=N_LINES, seed=1):
    """A PrusaSlicer-like file of exactly ``n_lines`` lines: per layer a
    comment block, a Z move, retract/travel/deretract, then mostly short
    extrusions; every ~40 lines a ``;TYPE``/``;WIDTH`` comment."""
    rng = random.Random(seed)
    out = ["G21 ; millimetres", "G90", "M83", "M104 S200", "G28", "G1 Z5 F5000"]
    z, x, y = 0.0, 100.0, 100.0
    while len(out) < n_lines:
        z += 0.2
        out += [";LAYER_CHANGE", ";Z:%.1f" % z, "G1 Z%.3f F7800" % z, "G92 E0",
                "G1 E-2 F2400", "G1 X%.3f Y%.3f F7800" % (x, y), "G1 E2 F2400", "G1 F1800"]
        for k in range(400):
            if k % 40 == 0:
                out += [";TYPE:Perimeter", ";WIDTH:0.45"]
            x = min(max(x + rng.uniform(-5, 5), 50.0), 150.0)
            y = min(max(y + rng.uniform(-5, 5), 50.0), 150.0)
            out.append("G1 X%.3f Y%.3f E%.5f" % (x, y, rng.uniform(0.01, 0.3)))
    with open(path, "w") as f:
        f.write("\n".join(out[:n_lines]) + "\n")


def baseline(path):
    """The original design's reader: one regex per line, positions and E only."""
    x = y = z = e = 0.0
    moves = 0
    match = _BASELINE_RE.match
    with open(path) as f:
        for line in f:
            m = match(line)
            if m:
                moves += 1
                gx, gy, gz, ge = m.group("x", "y", "z", "e")
                if gx: x = float(gx)
                if gy: y = float(gy)
                if gz: z = float(gz)
                if ge: e += float(ge)
    return moves, e


def main():
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "bench.gcode")
        write_file(path)
        t0 = time.perf_counter()
        n_events = sum(1 for _ in read_gcode(path))
        t_ours = time.perf_counter() - t0
        t0 = time.perf_counter()
        summary = summarize(read_gcode(path))
        t_summary = time.perf_counter() - t0
        t0 = time.perf_counter()
        base_moves, base_e = baseline(path)
        t_base = time.perf_counter() - t0
    assert summary["moves"] == base_moves, (summary["moves"], base_moves)
    assert abs(summary["extruded_filament_mm"] - base_e) <= 1e-9 * abs(base_e)
    print("gcode_reader: %d lines in %.2f s (%.0f lines/s); regex baseline: %.2f s; "
          "ratio ours/baseline = %.2f" % (N_LINES, t_ours, N_LINES / t_ours, t_base, t_ours / t_base))
    print("gcode_reader: %d events; info summary (reader + totals): %.2f s; target <= %.1f s: %s"
          % (n_events, t_summary, TARGET_S, "met" if t_ours <= TARGET_S else "MISSED"))


if __name__ == "__main__":
    main()
