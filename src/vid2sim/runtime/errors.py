"""The errors vid2sim raises for what a user gave it (as opposed to its own bugs)."""

from __future__ import annotations


class InputError(ValueError):
    """A file, folder or setting the user gave is not what vid2sim can use; the message names it and says what
    was expected. The command line prints the message alone (exit code 2)."""


class ConfigError(InputError):
    """A configuration value outside its range; the message names the field."""
