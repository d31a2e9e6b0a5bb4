"""`python -m identify ...`: the `identify` command line (`identify.cli`)."""

import sys

from .cli import main

sys.exit(main())
