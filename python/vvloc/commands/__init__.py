"""Implementations of the ``vvloc`` CLI commands, one module per command (see vvloc.cli)."""
