"""Subcommands of the velab CLI that belong to the application core."""
