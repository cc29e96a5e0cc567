"""Command-line interface and console: the only code that imports click or rich."""
