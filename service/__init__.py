"""photomap: live aerial photo maps by iFMI registration (see DESIGN.md for conventions)."""

__version__ = "0.1.0"
