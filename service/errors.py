"""User-facing errors: the CLI prints their message on one line, never a traceback."""


class PhotomapError(Exception):
    """An error a user can act on; ``exit_code`` is what the CLI returns."""

    exit_code = 1


class ConfigError(PhotomapError):
    """A bad config file, an unknown key or a value of the wrong type."""

    exit_code = 2


class InputError(PhotomapError):
    """A missing or unreadable input: camera, video, image folder, log."""

    exit_code = 3


class OutputError(PhotomapError):
    """The output folder cannot take the run's files: not a folder, not writable, disk full."""

    exit_code = 4
