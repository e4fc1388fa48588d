"""A real RTSP server on loopback for tests: Debian's gst-rtsp-server through PyGObject.

Run with the system Python that has ``gi`` (``/usr/bin/python3 tests/rtsp_server.py PORT FILE.ts``):
serves the H.264 MPEG-TS file at ``rtsp://127.0.0.1:PORT/cam`` in real time (a new session starts the
file from its beginning), prints ``ready`` once it listens, and runs until killed.
"""

import sys

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstRtspServer", "1.0")
from gi.repository import GLib, Gst, GstRtspServer  # noqa: E402


def main() -> None:
    port, path = sys.argv[1], sys.argv[2]
    Gst.init(None)
    server = GstRtspServer.RTSPServer()
    server.set_address("127.0.0.1")
    server.set_service(port)
    factory = GstRtspServer.RTSPMediaFactory()
    factory.set_launch(f"( filesrc location={path} ! tsdemux ! h264parse "
                       f"! rtph264pay name=pay0 pt=96 )")
    server.get_mount_points().add_factory("/cam", factory)
    if server.attach(None) == 0:
        sys.exit(f"cannot listen on 127.0.0.1:{port}")
    print("ready", flush=True)
    GLib.MainLoop().run()


if __name__ == "__main__":
    main()
