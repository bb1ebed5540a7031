"""`make bench`: runs every tests/bench/bench_*.py (each has a main() that
prints its measurements), one after the other in one process."""
import glob
import importlib.util
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv):
    wanted = set(argv)
    for path in sorted(glob.glob(os.path.join(HERE, "bench_*.py"))):
        name = os.path.basename(path)[:-3]
        if wanted and name not in wanted and name[6:] not in wanted:
            continue
        spec = importlib.util.spec_from_file_location(name, path)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        print("== %s" % name, flush=True)
        t = time.perf_counter()
        mod.main()
        print("   (%.1f s)" % (time.perf_counter() - t), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
