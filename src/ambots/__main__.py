import sys

from ambots.cli import main

sys.exit(main())
