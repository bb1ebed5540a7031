"""Sub-commands of ``python -m ambots``.  Each module defines
``register(subparsers)``, which adds its parser and sets ``func``; heavy
imports happen inside ``func`` so that ``--help`` stays fast."""
