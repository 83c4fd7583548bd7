"""The Kinect capture process: libfreenect's sync API in a process of its own.

`hardware.depth` launches it as ``python -m hardware.kinect_worker --fd FD --index N
--stream depth`` and never imports freenect itself. A process of its own because

- fakenect (a recorded folder replayed through the real sync API) needs Debian's fake
  libfreenect and the `freenect_camera_to_world` shim in LD_PRELOAD, which only takes
  effect when a process starts, and the live Kinect goes through the same process so
  that the fakenect tests exercise the live code path;
- a USB Kinect can be opened by one process at a time, so its depth and video streams
  share one worker (the parent asks for a second stream by a line on stdin);
- a blocked `sync_get_depth` (an unplugged device, the end of a fakenect recording)
  cannot be interrupted from Python: the parent ends the process instead.

Wire format (the pipe `--fd`, written only by this process): each record is the
28-byte little-endian `HEADER` — magic b"WKF1", stream (1 depth, 2 video), status
(0 frame, 1 error), width, height, channels, libfreenect timestamp (uint32),
arrival (the host's `time.monotonic()` right after `sync_get_*` returned, float64),
payload length — followed by the payload: a frame's pixels in row-major order (depth:
uint16 in host byte order, 11-bit raw disparity; video: uint8 RGB), or an error's
UTF-8 text. No pickle: plain bytes both ways.

stdin carries commands, one per line: ``depth`` or ``video`` starts that stream.
End of stdin (the parent closed it, or died) ends the process at once.

C libraries print to stdout (libfreenect's "Error: Invalid index", the Python binding's
"Can't open device"): stdout is redirected to stderr here, so nothing can corrupt the
frame pipe, and the parent keeps stderr for its error messages.
"""

from __future__ import annotations

import argparse
import os
import struct
import sys
import threading
import time

MAGIC = b"WKF1"
HEADER = struct.Struct("<4sBBHHHIdI")
STREAM_DEPTH = 1
STREAM_VIDEO = 2
STREAM_IDS = {"depth": STREAM_DEPTH, "video": STREAM_VIDEO}
STATUS_FRAME = 0
STATUS_ERROR = 1


class _Pipe:
    """Writes whole records to the frame pipe; one writer at a time."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.lock = threading.Lock()

    def _write_all(self, data: bytes | memoryview) -> None:
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            view = view[n:]

    def send(
        self,
        stream: int,
        status: int,
        payload: bytes,
        shape: tuple[int, ...] = (0, 0),
        timestamp: int = 0,
        arrival: float = 0.0,
    ) -> None:
        height, width = shape[0], shape[1]
        channels = shape[2] if len(shape) > 2 else 1
        head = HEADER.pack(
            MAGIC, stream, status, width, height, channels, timestamp, arrival, len(payload)
        )
        try:
            with self.lock:
                self._write_all(head)
                self._write_all(payload)
        except OSError:
            # The parent closed its end: nobody is listening any more.
            os._exit(0)


def _capture(freenect, kind: str, index: int, pipe: _Pipe) -> None:
    stream = STREAM_IDS[kind]
    get = freenect.sync_get_depth if kind == "depth" else freenect.sync_get_video
    while True:
        got = get(index)  # blocks until the next frame (the binding releases the GIL)
        arrival = time.monotonic()
        if got is None:
            pipe.send(
                stream,
                STATUS_ERROR,
                f"libfreenect could not open Kinect {index} for {kind} "
                "(not connected, or no permission for its USB device)".encode(),
            )
            return
        image, timestamp = got
        # The array points into libfreenect's ring buffer: copy before the next call.
        payload = image.tobytes()
        pipe.send(stream, STATUS_FRAME, payload, image.shape, int(timestamp), arrival)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m hardware.kinect_worker")
    parser.add_argument("--fd", type=int, required=True, help="the frame pipe's file descriptor")
    parser.add_argument("--index", type=int, default=0, help="libfreenect device index")
    parser.add_argument("--stream", action="append", choices=sorted(STREAM_IDS), default=[])
    args = parser.parse_args(argv)

    sys.stdout.flush()
    os.dup2(2, 1)
    pipe = _Pipe(args.fd)
    try:
        import freenect
    except ImportError as exc:
        if isinstance(exc, ModuleNotFoundError):
            message = (
                "the freenect Python binding is not installed: "
                "apt-get install libfreenect-dev, then pip install 'walker-slam[kinect]'"
            )
        else:  # e.g. an undefined symbol: the binding found but libfreenect did not load
            message = f"the freenect Python binding failed to load: {exc}"
        for kind in args.stream or ["depth"]:
            pipe.send(STREAM_IDS[kind], STATUS_ERROR, message.encode())
        os._exit(0)

    started: set[str] = set()

    def start(kind: str) -> None:
        if kind in STREAM_IDS and kind not in started:
            started.add(kind)
            threading.Thread(
                target=_capture, args=(freenect, kind, args.index, pipe), daemon=True
            ).start()

    for kind in args.stream:
        start(kind)
    for line in sys.stdin:
        start(line.strip())
    # stdin closed: the parent is done. Do not wait for the capture threads: they may be
    # blocked in libfreenect for ever (no device, or the end of a recording).
    os._exit(0)


if __name__ == "__main__":
    main()
