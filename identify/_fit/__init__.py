"""Private: the public API is `identify/__init__.py`."""
