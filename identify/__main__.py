"""`python -m identify ...`: the `identify` command line (`identify.cli`)."""

from .cli import console_main

console_main()
