"""photomap: live aerial photo maps (2D mosaics) from a down-looking drone camera by iFMI registration.

Layers, bottom to top (docs/architecture.md): ``errors``, ``config``, ``geometry`` -> ``core`` ->
``geo``, ``telemetry`` -> ``drivers``, ``io`` -> ``mapping`` -> ``live``, ``sim``, ``eval`` -> ``cli``.
"""

__version__ = "0.1.0"
