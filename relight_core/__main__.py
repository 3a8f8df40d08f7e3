"""`python -m relight_core ...` entry point."""

import sys

from relight_core.cli import main

sys.exit(main())
