"""Drivers: everything that talks to a camera, a file or an autopilot link."""
